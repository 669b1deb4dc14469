"""A self-contained interactive 3D view of a reconstruction: one HTML file, no network.

:func:`write_html_view` writes the cameras (as frustums, coloured by component), the
triangulated points (in their image colours) and, when given, the ground-truth cameras with a
line from each estimate to its ground truth. The page draws on a 2D canvas with a few hundred
lines of inline JavaScript (no WebGL, no library, no font or script fetched), so it opens from
disk in any browser, offline.

Mouse: drag to orbit, wheel to zoom, shift+drag or right-drag to pan, hover a camera for its
image name. Keys ``p`` / ``g`` toggle points / ground truth, ``r`` resets the view. The view is
kept in the address's ``#`` part (``#yaw=30&pitch=20&zoom=1.5``), so a view can be bookmarked.
"""

from __future__ import annotations

import html
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .io import atomic_write_text

__all__ = ["write_html_view"]

#: component colours (the first is the largest component); ground truth is drawn in grey
_PALETTE = ("#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2",
            "#17becf", "#bcbd22")


def _matrix(value: Any, what: str) -> np.ndarray:
    m = np.asarray(value, np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise ValueError(f"{what}: expected a finite 4x4 camera-to-world matrix, got "
                         f"shape {m.shape}")
    return m


def write_html_view(
    path: str | os.PathLike[str],
    cameras: Mapping[str, Mapping[str, Any]],
    points: np.ndarray | None = None,
    colours: np.ndarray | None = None,
    ground_truth: Mapping[str, Any] | None = None,
    title: str = "posernet reconstruction",
    units: str = "scale-free",
    max_points: int = 60000,
) -> Path:
    """Write the interactive view to ``path`` (atomically) and return it.

    Args:
        cameras: ``{name: record}`` as in ``poses.json``'s ``cameras``: ``camera_to_world``
            (4, 4), ``K`` (3, 3), ``size`` (W, H), ``component``; unsolved records (no
            ``camera_to_world`` or ``solved`` false) are left out.
        points: ``(P, 3)`` points in the cameras' frame; ``colours`` ``(P, 3)`` RGB 0-255.
        ground_truth: ``{name: camera_to_world (4, 4)}`` in the same frame as ``cameras``
            (already aligned); drawn in grey, each joined to its estimate.
        units: axis unit shown in the legend (``"m"`` when aligned to metric ground truth).
        max_points: points beyond this are subsampled (evenly, deterministically) to keep the
            file small and the page fluid.

    The page's status line counts the cameras and every point given, the number a title
    should quote; points not drawn (not finite, subsampled, or far out: beyond 20 x the
    cameras' radius, which would shrink the cameras to a dot) are counted there as well.
    """
    cams = {k: c for k, c in cameras.items()
            if c.get("camera_to_world") is not None and c.get("solved", True)}
    if not cams:
        raise ValueError(f"{path}: no solved camera to show")
    names = list(cams)
    c2w = np.stack([_matrix(cams[k]["camera_to_world"], f"camera {k!r}") for k in names])
    comps = [int(cams[k].get("component") or 0) for k in names]
    sizes = {c: comps.count(c) for c in set(comps)}
    rank = {c: r for r, c in enumerate(sorted(sizes, key=lambda c: (-sizes[c], c)))}
    gt = {}
    for k, m in (ground_truth or {}).items():
        if k in cams:
            gt[k] = _matrix(m, f"ground truth of {k!r}")
    pts = np.zeros((0, 3)) if points is None else np.asarray(points, np.float64).reshape(-1, 3)
    rgb = (np.full((len(pts), 3), 150) if colours is None
           else np.asarray(colours).reshape(-1, 3))
    if len(rgb) != len(pts):
        raise ValueError(f"colours: {len(rgb)} rows for {len(pts)} points")
    n_given = len(pts)
    ok = np.isfinite(pts).all(1)
    pts, rgb = pts[ok], rgb[ok]
    left_out = {"not finite": n_given - len(pts)}
    if len(pts) > max_points:
        pick = np.linspace(0, len(pts) - 1, max_points).round().astype(np.int64)
        left_out["thinned out"] = len(pts) - max_points
        pts, rgb = pts[pick], rgb[pick]

    # display frame: centred on the cameras, scaled to unit radius, "up" the cameras' mean -y
    centres = c2w[:, :3, 3]
    all_c = np.concatenate([centres, *[m[None, :3, 3] for m in gt.values()]])
    mid = np.median(all_c, axis=0)
    if len(pts):  # between the cameras and what they look at
        mid = 0.5 * (mid + np.median(pts, axis=0))
    up = -c2w[:, :3, 1].mean(0)
    up = up / (np.linalg.norm(up) or 1.0) if np.linalg.norm(up) > 1e-9 else np.array([0, 1.0, 0])
    fwd = c2w[:, :3, 2].mean(0)
    fwd = fwd - up * (fwd @ up)
    if np.linalg.norm(fwd) < 1e-6:  # cameras looking along "up": any perpendicular will do
        fwd = np.cross(up, [1.0, 0, 0] if abs(up[0]) < 0.9 else [0, 0, 1.0])
    fwd /= np.linalg.norm(fwd)
    # rows: display x (right), y (up), z (towards the viewer at yaw 0)
    D = np.stack([np.cross(fwd, up), up, -fwd])
    radius = float(np.percentile(np.linalg.norm(all_c - mid, axis=1), 90)) or 1.0
    if len(pts):  # points far out (a few bad triangulations) must not shrink the cameras
        keep = np.linalg.norm(pts - mid, axis=1) < 20 * radius
        left_out["far from the cameras"] = int((~keep).sum())
        pts, rgb = pts[keep], rgb[keep]
    status = f"{len(names)} cameras, {n_given} points"
    if len(pts) < n_given:
        status += f" ({len(pts)} drawn; left out: " + ", ".join(
            f"{n} {why}" for why, n in left_out.items() if n) + ")"
    if len(sizes) > 1:
        status += f", {len(sizes)} components"

    def show(x: np.ndarray) -> np.ndarray:
        return ((x - mid) @ D.T) / radius

    depth = 0.12 * radius if len(names) > 1 else radius
    frust = []
    for k, m in zip(names, c2w, strict=True):
        K = np.asarray(cams[k].get("K", [[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]]), np.float64)
        w, h = (cams[k].get("size") or [2 * K[0, 2], 2 * K[1, 2]])[:2]
        corners = np.array([[0, 0, 1], [w, 0, 1], [w, h, 1], [0, h, 1]], np.float64)
        rays = corners @ np.linalg.inv(K).T
        rays *= depth / np.maximum(rays[:, 2:], 1e-9)
        frust.append(show(np.concatenate([m[:3, 3][None], rays @ m[:3, :3].T + m[:3, 3]])))
    data = {
        "title": title, "units": units,
        "cameras": [{"name": k, "colour": _PALETTE[rank[c] % len(_PALETTE)],
                     "component": rank[c], "f": np.round(f, 5).tolist()}
                    for k, c, f in zip(names, comps, frust, strict=True)],
        "truth": [{"name": k, "c": np.round(show(m[:3, 3][None])[0], 5).tolist()}
                  for k, m in gt.items()],
        "points": np.round(show(pts), 4).reshape(-1).tolist() if len(pts) else [],
        "rgb": np.clip(rgb, 0, 255).astype(np.int64).reshape(-1).tolist(),
        "components": len(sizes),
        "status": status,
    }
    # "</" inside the script element would end it: escape the slash
    blob = json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
    page = _PAGE.replace("__TITLE__", html.escape(title)).replace("__DATA__", blob)
    return atomic_write_text(path, page)


_PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>__TITLE__</title>
<style>
 html, body { margin: 0; height: 100%; background: #fafafa; font: 13px sans-serif; }
 #view { position: fixed; inset: 0; width: 100%; height: 100%; cursor: grab; }
 #panel { position: fixed; left: 8px; top: 8px; background: rgba(255,255,255,.88);
          padding: 6px 10px; border-radius: 4px; box-shadow: 0 1px 3px rgba(0,0,0,.25); }
 #panel h1 { font-size: 14px; margin: 0 0 4px; }
 #tip { position: fixed; pointer-events: none; background: #222; color: #fff; padding: 2px 6px;
        border-radius: 3px; display: none; }
 .key { display: inline-block; width: 10px; height: 10px; margin-right: 4px; }
</style></head>
<body>
<canvas id="view"></canvas>
<div id="panel"><h1>__TITLE__</h1>
 <div id="status">loading...</div>
 <div id="legend"></div>
 <label><input type="checkbox" id="showPoints" checked> points (p)</label>
 <label><input type="checkbox" id="showTruth" checked> ground truth (g)</label>
 <button id="reset">reset view (r)</button>
 <div style="color:#666">drag: orbit &middot; wheel: zoom &middot; shift/right drag: pan</div>
</div>
<div id="tip"></div>
<script id="data" type="application/json">__DATA__</script>
<script>
"use strict";
const D = JSON.parse(document.getElementById("data").textContent);
const canvas = document.getElementById("view"), ctx = canvas.getContext("2d");
const tip = document.getElementById("tip");
const home = {yaw: 35, pitch: 20, zoom: 1, panX: 0, panY: 0};
let v = Object.assign({}, home);
function readHash() {
  for (const part of location.hash.slice(1).split("&")) {
    const [k, val] = part.split("=");
    if (k in home && isFinite(parseFloat(val))) v[k] = parseFloat(val);
  }
}
function writeHash() {
  const h = Object.keys(home).map(k => k + "=" + (+v[k].toFixed(3))).join("&");
  try { history.replaceState(null, "", "#" + h); } catch (err) { /* some file:// pages */ }
}
function rotation() {
  const a = v.yaw * Math.PI / 180, b = v.pitch * Math.PI / 180;
  const ca = Math.cos(a), sa = Math.sin(a), cb = Math.cos(b), sb = Math.sin(b);
  // yaw about the display y (up) axis, then pitch about x
  return [[ca, 0, sa], [sb * sa, cb, -sb * ca], [-cb * sa, sb, cb * ca]];
}
let R, W, H, F;
function project(p) {
  const x = R[0][0] * p[0] + R[0][1] * p[1] + R[0][2] * p[2];
  const y = R[1][0] * p[0] + R[1][1] * p[1] + R[1][2] * p[2];
  const z = R[2][0] * p[0] + R[2][1] * p[1] + R[2][2] * p[2];
  const d = 4 - z;  // eye 4 units out on +z
  if (d < 0.05) return null;
  return [W / 2 + F * (x / d) + v.panX, H / 2 - F * (y / d) + v.panY, d];
}
function line(a, b) {
  if (!a || !b) return;
  ctx.moveTo(a[0], a[1]); ctx.lineTo(b[0], b[1]);
}
let screen = [];
function draw() {
  const dpr = window.devicePixelRatio || 1;
  W = canvas.clientWidth; H = canvas.clientHeight;
  canvas.width = W * dpr; canvas.height = H * dpr;
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.fillStyle = "#fafafa"; ctx.fillRect(0, 0, W, H);
  R = rotation(); F = 2.0 * Math.min(W, H) * v.zoom;
  if (document.getElementById("showPoints").checked) {
    const P = D.points, C = D.rgb;
    for (let i = 0; i < P.length; i += 3) {
      const q = project([P[i], P[i + 1], P[i + 2]]);
      if (!q) continue;
      ctx.fillStyle = "rgb(" + C[i] + "," + C[i + 1] + "," + C[i + 2] + ")";
      ctx.fillRect(q[0] - 1, q[1] - 1, 2, 2);
    }
  }
  const byName = {};
  for (const c of D.cameras) byName[c.name] = c;
  if (document.getElementById("showTruth").checked && D.truth.length) {
    ctx.strokeStyle = "#777"; ctx.fillStyle = "#777"; ctx.lineWidth = 1;
    ctx.beginPath();
    for (const t of D.truth) line(project(t.c), project(byName[t.name].f[0]));
    ctx.stroke();
    for (const t of D.truth) {
      const q = project(t.c);
      if (q) { ctx.beginPath(); ctx.arc(q[0], q[1], 3, 0, 2 * Math.PI); ctx.fill(); }
    }
  }
  screen = [];
  for (const c of D.cameras) {
    const q = c.f.map(project);
    ctx.strokeStyle = c.colour; ctx.lineWidth = 1.3;
    ctx.beginPath();
    for (let k = 1; k <= 4; k++) { line(q[0], q[k]); line(q[k], q[k % 4 + 1]); }
    ctx.stroke();
    if (q[1] && q[2]) {  // the image's top edge drawn thick: which way is up
      ctx.lineWidth = 3; ctx.beginPath(); line(q[1], q[2]); ctx.stroke();
    }
    if (q[0]) screen.push([q[0][0], q[0][1], c]);
  }
  writeHash();
}
function legend() {
  const seen = {};
  let html = "";
  for (const c of D.cameras) {
    if (c.component in seen) { seen[c.component].n++; continue; }
    seen[c.component] = {n: 1, colour: c.colour};
  }
  for (const k of Object.keys(seen).sort((a, b) => a - b)) {
    html += '<div><span class="key" style="background:' + seen[k].colour + '"></span>' +
      (k == 0 ? "largest component" : "component " + (+k + 1)) + ": " + seen[k].n +
      " cameras</div>";
  }
  if (D.truth.length) html += '<div><span class="key" style="background:#777"></span>' +
    "ground truth (linked to its estimate)</div>";
  html += "<div>units: " + D.units + "</div>";
  document.getElementById("legend").innerHTML = html;
}
let drag = null;
canvas.addEventListener("contextmenu", e => e.preventDefault());
canvas.addEventListener("mousedown", e => {
  drag = {x: e.clientX, y: e.clientY, pan: e.shiftKey || e.button === 2};
  canvas.style.cursor = "grabbing";
});
window.addEventListener("mouseup", () => { drag = null; canvas.style.cursor = "grab"; });
window.addEventListener("mousemove", e => {
  if (drag) {
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX; drag.y = e.clientY;
    if (drag.pan) { v.panX += dx; v.panY += dy; }
    else { v.yaw += dx * 0.4; v.pitch = Math.max(-89, Math.min(89, v.pitch + dy * 0.4)); }
    draw();
    return;
  }
  let best = null, bd = 64;
  for (const s of screen) {
    const d = (s[0] - e.clientX) ** 2 + (s[1] - e.clientY) ** 2;
    if (d < bd) { bd = d; best = s; }
  }
  if (best) {
    tip.textContent = best[2].name; tip.style.display = "block";
    tip.style.left = (e.clientX + 12) + "px"; tip.style.top = (e.clientY + 12) + "px";
  } else tip.style.display = "none";
});
canvas.addEventListener("wheel", e => {
  e.preventDefault();
  v.zoom *= Math.exp(-e.deltaY * 0.001);
  draw();
}, {passive: false});
window.addEventListener("keydown", e => {
  if (e.key === "p") document.getElementById("showPoints").click();
  else if (e.key === "g") document.getElementById("showTruth").click();
  else if (e.key === "r") { v = Object.assign({}, home); draw(); }
});
document.getElementById("showPoints").addEventListener("change", draw);
document.getElementById("showTruth").addEventListener("change", draw);
document.getElementById("reset").addEventListener("click", () => {
  v = Object.assign({}, home); draw();
});
window.addEventListener("resize", draw);
readHash();
legend();
draw();
document.getElementById("status").textContent = D.status;
document.body.dataset.rendered = "1";
</script>
</body></html>
"""

"""Real photos: ``posernet-reconstruct`` against COLMAP (global and incremental) on the same
image folders with the same fixed pinhole intrinsics, side by side in one run.

Each method runs in its own subprocess on each set (``posernet-reconstruct`` from the venv;
COLMAP through pycolmap in a worker process of this script), so wall time and peak memory
(``ru_maxrss`` of that child) are the method's own. Per set and method the table gives:

* cameras placed (of N), the size of the largest connected component (COLMAP: the largest
  model) and the number of components (models);
* trust: of the placed cameras, how many are placed right and how many wrong
  (:func:`trust_counts`): right when, after a robust similarity alignment of the camera's
  component onto the ground truth (RANSAC over 2- and 3-camera samples fitted on centres and
  orientations, then the least-squares fit on the consensus, refitted until it settles), its
  rotation is within 5 deg and its centre within 5 % of the scene's extent, the extent being
  the diameter (largest distance between two) of all the set's ground-truth camera centres.
  Unsolved cameras (``"solved": false`` in posernet's poses.json, images in no COLMAP model)
  and a camera alone in its component are neither right nor wrong: not placed;
* on the largest component: the median absolute rotation error (deg; estimated
  camera-to-world rotations after the best global rotation, the chordal mean of
  ``R_gt R_est^T``), the median camera-position error (centres after an Umeyama similarity,
  in ground-truth units), and over every image pair the median relative rotation error and
  relative translation-direction error (deg);
* wall time of the subprocess (s, interpreter start and imports included) and its peak
  resident memory (MB).

COLMAP: SIFT extraction with the set's intrinsics (one shared PINHOLE camera; OPENCV when the
set gives distortion), exhaustive matching (``--colmap-matching sequential``: overlap 10 with
quadratic overlap, i.e. each image in name order with those 1, 2, 4, ..., 512 further on),
then ``pycolmap.global_mapping`` (GLOMAP) or ``pycolmap.incremental_mapping`` with every
intrinsic held fixed in bundle adjustment.
pycolmap is an optional benchmark-only dependency (``pip install pycolmap==4.2.1``); without
it the COLMAP rows are skipped with a note.

    python benchmarks/bench_real.py                          # benchmarks/data/real/* + rendered
    python benchmarks/bench_real.py --quick                  # 8 images per set, small render
    python benchmarks/bench_real.py --set herzjesu=benchmarks/data/real/strecha_herzjesu_p25
    python benchmarks/bench_real.py --set lab=photos/:585,585,320,240 --rendered \\
        --method posernet --method "posernet-eig=sync=eig_se3" \\
        --method "posernet-refine=refine=true" --method colmap-incremental
    python benchmarks/bench_real.py --trust --threads 2     # the trust table (TRUST_SETS)

Writes ``benchmarks/results/real.md`` and ``real.json`` (every number, the exact commands and
overrides, versions, machine; ``--trust``: ``trust.md`` and ``trust.json``; ``--out`` another
path); ``--quick`` writes under ``benchmarks/results/quick/``. ``--trust`` runs the sparse and
hard sets of ``TRUST_SETS`` (build them first: ``benchmarks/data/real/build_sets.py dino
trust``) and the rendered low-texture rooms of ``TRUST_RENDERED``, without the default rendered
scene; the per-camera verdicts and errors are in the .json
(``trust`` of each row).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

# Keep the module's own imports light: the COLMAP worker (``--colmap-worker``) runs this file
# and must not pay for torch; posernet and torch are imported where they are used.

ROOT = Path(__file__).resolve().parent
DATA = ROOT / "data" / "real"
# the trust table's sets (``--trust``): sparse and hard sets built by
# benchmarks/data/real/build_sets.py (``trust`` and ``dino``)
TRUST_SETS = ("middlebury_dino_sparse_ring", "middlebury_dino_sparse_ring_far8",
              "strecha_herzjesu_p25_every3", "strecha_fountain_p11_every3",
              "strecha_entry_p10_every3", "strecha_herzjesu_p25_far8", "squirrel_turntable",
              "squirrel_turntable_far8", "squirrel_turntable_far8_full", "dtu_scan24_far8",
              "dtu_scan97_far8", "dtu_scan69_far8", "dtu_scan106_far8",
              "dtu_scan65_far8")
# ... and rendered low-texture rooms: (name, scene preset, seed, frames of the sweep, every
# step-th frame kept, every k-th object textured)
TRUST_RENDERED = (("lowtex_chess_every3", "chess", 0, 36, 3, 8),
                  ("lowtex_office_every6", "office", 1, 72, 6, 8))
# ... and a rendered plain object seen from all round (posernet.data.render.render_object_ring):
# (name, frames on the ring, every step-th kept, textured room around it)
TRUST_RINGS = (("plain_object_ring", 24, 1, True), ("plain_object_ring_every3", 24, 3, True),
               ("bare_object_ring_every3", 24, 3, False))
COLMAP_METHODS = ("colmap-global", "colmap-incremental")
COLMAP_MATCHING = ("exhaustive", "sequential")  # the COLMAP worker's pair selection
DEFAULT_METHODS = ("posernet", *COLMAP_METHODS)
PYCOLMAP_PIN = "pycolmap==4.2.1"
POSE_SUFFIX = ".pose.txt"
# per-set defaults of the intrinsics, looked for in the set folder (then its images folder)
INTRINSICS_FILES = ("intrinsics.json", "intrinsics.txt")


class BenchError(ValueError):
    """Bad input to the benchmark: a missing folder, no ground truth, an unknown method."""


# ------------------------------------------------------------------------------------ inputs


class ImageSet:
    """One set: ``keys`` are the image names in ``images`` (as both methods see them);
    ``intrinsics`` as given to posernet-reconstruct (``"fx,fy,cx,cy"`` or a file path),
    ``K (3, 3)`` and ``dist`` (OpenCV order or ``None``) parsed from it; ``c2w`` the
    ground-truth camera-to-world pose per key. (No dataclass: the benchmark scripts are also
    loaded as unregistered modules, see tests/benchmarks/test_benchmarks.py.)"""

    def __init__(self, name: str, images: Path, keys: list[str], intrinsics: str,
                 K: np.ndarray, dist: np.ndarray | None, c2w: dict[str, np.ndarray],
                 source: str = "", note: str = "") -> None:
        self.name, self.images, self.keys, self.intrinsics = name, images, keys, intrinsics
        self.K, self.dist, self.c2w, self.source, self.note = K, dist, c2w, source, note


class Method:
    """``kind`` is ``posernet``, ``colmap-global`` or ``colmap-incremental``; ``overrides``
    hydra overrides of a posernet method."""

    def __init__(self, label: str, kind: str, overrides: list[str] | None = None) -> None:
        self.label, self.kind, self.overrides = label, kind, list(overrides or [])


def parse_method(text: str) -> Method:
    """``posernet[-LABEL][=OVERRIDES]`` (hydra overrides, space separated), ``colmap-global``,
    ``colmap-incremental``."""
    label, eq, rest = text.strip().partition("=")
    label = label.strip()
    overrides = shlex.split(rest) if eq else []
    if label == "posernet" or label.startswith("posernet-"):
        if eq and not overrides:
            raise BenchError(f"method {text!r}: no overrides after '='")
        return Method(label, "posernet", overrides)
    if label in COLMAP_METHODS:
        if overrides:
            raise BenchError(f"method {text!r}: COLMAP methods take no overrides")
        return Method(label, label)
    raise BenchError(f"unknown method {text!r}: choose posernet[-LABEL][=HYDRA OVERRIDES], "
                     f"{', '.join(COLMAP_METHODS)}")


def parse_set(text: str) -> tuple[str, Path, str | None]:
    """``NAME=DIR[:INTRINSICS]`` -> ``(name, folder, intrinsics or None)``."""
    name, eq, rest = text.partition("=")
    if not eq or not name.strip() or not rest.strip():
        raise BenchError(f"--set {text!r}: expected NAME=DIR[:INTRINSICS]")
    folder, _, intr = rest.partition(":")
    return name.strip(), Path(folder), (intr.strip() or None)


def _pose_name(key: str) -> str:
    """The ground-truth file of an image: ``<stem>.pose.txt`` (7-Scenes: ``.color.png`` off)."""
    for suffix in (".color.png", ".color.jpg"):
        if key.endswith(suffix):
            return key[: -len(suffix)] + POSE_SUFFIX
    return str(Path(key).with_suffix("")) + POSE_SUFFIX


def load_set(name: str, folder: str | os.PathLike[str], intrinsics: str | None = None) -> ImageSet:
    """The images of ``folder`` (or ``folder/images``), their intrinsics (``intrinsics``, else
    ``folder/intrinsics.json`` or ``.txt``) and ground truth (``<stem>.pose.txt``, camera to
    world, beside the images or in ``folder``). Every problem is a :class:`BenchError` naming
    the set and the folder or file."""
    from posernet.frontend.images import ImageError, list_images, parse_intrinsics, read_pose_file

    root = Path(folder)
    if not root.is_dir():
        raise BenchError(f"set {name!r}: folder not found: {root}")
    images = root
    if not any(p.is_file() and p.suffix.lower() in _suffixes() for p in root.iterdir()) \
            and (root / "images").is_dir():
        images = root / "images"
    try:
        keys = [str(p.relative_to(images)) for p in list_images(images)]
    except ImageError as e:
        raise BenchError(f"set {name!r}: {e}") from None
    if intrinsics is None:
        found = [d / f for d in dict.fromkeys((root, images)) for f in INTRINSICS_FILES
                 if (d / f).is_file()]
        if not found:
            raise BenchError(f"set {name!r}: no intrinsics: give NAME=DIR:FX,FY,CX,CY or a file, "
                             f"or put {' or '.join(INTRINSICS_FILES)} in {root}")
        intrinsics = str(found[0].resolve())
    elif "," not in intrinsics:
        p = Path(intrinsics)
        if not p.is_file():
            raise BenchError(f"set {name!r}: intrinsics file not found: {p}")
        intrinsics = str(p.resolve())
    try:
        cams = parse_intrinsics(intrinsics, keys)
    except ImageError as e:
        raise BenchError(f"set {name!r}: {e}") from None
    K, dist = cams[0]
    for key, (Ki, di) in zip(keys, cams, strict=True):
        same_d = (di is None and dist is None) or (
            di is not None and dist is not None and di.shape == dist.shape
            and np.allclose(di, dist))
        if not np.allclose(Ki, K) or not same_d:
            raise BenchError(f"set {name!r}: image {key} has other intrinsics than {keys[0]}; "
                             "the benchmark needs one fixed camera for every image")
    if abs(K[0, 1]) > 1e-9:
        raise BenchError(f"set {name!r}: skewed intrinsics (K[0,1] = {K[0, 1]}) are not pinhole")
    c2w, missing = {}, []
    for key in keys:
        cands = [images / _pose_name(key), root / _pose_name(Path(key).name)]
        path = next((p for p in cands if p.is_file()), None)
        if path is None:
            missing.append(str(cands[0]))
            continue
        try:
            c2w[key] = read_pose_file(path)
        except ImageError as e:
            raise BenchError(f"set {name!r}: {e}") from None
    if missing:
        raise BenchError(f"set {name!r}: no ground truth for {len(missing)} of {len(keys)} "
                         f"images (camera-to-world <stem>{POSE_SUFFIX} beside the images), "
                         f"e.g. {missing[0]}")
    source = _source(root / "SOURCE.md") if (root / "SOURCE.md").is_file() else ""
    return ImageSet(name, images.resolve(), keys, intrinsics, K, dist, c2w, source)


def _source(path: Path) -> str:
    """A few words on where a set comes from: the start of SOURCE.md's ``**What**:`` paragraph
    (else its first line that is not a heading)."""
    text = path.read_text(encoding="utf-8", errors="replace")
    paras = [" ".join(p.split()) for p in text.split("\n\n") if p.strip()]
    what = [p.split("**What**:", 1)[1].strip() for p in paras if "**What**:" in p]
    words = what[0] if what else next((p for p in paras if not p.startswith("#")), "")
    cuts = [i for i in (words.find(" ("), words.find(": ")) if i > 0]
    words = words[: min(cuts)] if cuts else words
    return (words[:77] + "...") if len(words) > 80 else words


def _suffixes() -> tuple[str, ...]:
    from posernet.frontend.images import IMAGE_SUFFIXES

    return IMAGE_SUFFIXES


def subsample(s: ImageSet, n: int, work: Path) -> ImageSet:
    """``s`` cut to ``n`` evenly spaced images, linked into ``work`` with their pose files."""
    if n <= 0 or len(s.keys) <= n:
        return s
    idx = sorted({round(float(v)) for v in np.linspace(0, len(s.keys) - 1, n)})
    keys = [s.keys[i] for i in idx]
    dst = work / f"{s.name}-{len(keys)}"
    shutil.rmtree(dst, ignore_errors=True)
    dst.mkdir(parents=True)
    for key in keys:
        os.symlink(s.images / key, dst / key)
        np.savetxt(dst / _pose_name(key), s.c2w[key], fmt="%.9f")
    return ImageSet(s.name, dst, keys, s.intrinsics, s.K, s.dist, {k: s.c2w[k] for k in keys},
                    s.source, f"{len(keys)} of {len(s.keys)} images (evenly spaced)")


def every_step(folder: Path, images: Path, frames: int, step: int) -> Path:
    """Every ``step``-th of the ``frames`` rendered frames in ``images`` (colour and pose) in
    a folder of their own, ``folder/every<step>`` (made once); ``images`` itself for step 1."""
    import shutil

    if step <= 1:
        return images
    sub = folder / f"every{step}"
    if not sub.is_dir():
        tmp = folder / f".every{step}.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        for k in range(0, frames, step):
            for suffix in (".color.png", POSE_SUFFIX):
                shutil.copy(images / f"frame-{k:06d}{suffix}", tmp)
        tmp.rename(sub)
    return sub


def rendered_set(work: Path, scene: str, frames: int, width: int, height: int,
                 seed: int = 0, step: int = 1, textured_every: int = 1,
                 name: str | None = None) -> ImageSet:
    """One rendered scene (7-Scenes layout, cached in ``work``) as a set: every ``step``-th of
    ``frames`` frames of one sweep; ``textured_every`` > 1 renders it low-texture (plain room,
    only every k-th object textured; :func:`posernet.data.render.render_sevenscenes`)."""

    from posernet.data.render import render_intrinsics, render_sevenscenes

    focal = 585.0 * width / 640
    tag = "" if textured_every == 1 else f"-plain{textured_every}"
    folder = work / f"rendered-{scene}-{seed}-{frames}-{width}x{height}{tag}"
    if not (folder / scene / "render.json").is_file():
        render_sevenscenes(folder, scene, seed=seed, train_sequences=0, test_sequences=1,
                           frames_per_sequence=frames, width=width, height=height, focal=focal,
                           overwrite=True, progress=False, textured_every=textured_every)
    intr = ",".join(f"{v:g}" for v in render_intrinsics(folder / scene))
    images = every_step(folder, folder / scene / "seq-01", frames, step)
    s = load_set(name or f"rendered-{scene}", images, intr)
    texture = "" if textured_every == 1 else (
        f", low texture (plain room, one object in {textured_every} textured)")
    kept = f"one frame in {step} of {frames}" if step > 1 else f"{frames} frames"
    s.source = (f"posernet.data.render: {scene}, seed {seed}, {kept} of one sweep, "
                f"{width}x{height}, f = {focal:g}{texture}")
    return s


def ring_set(work: Path, frames: int, step: int = 1, background: bool = True,
             name: str | None = None) -> ImageSet:
    """A plain object rendered from ``frames`` views round it (cached in ``work``;
    :func:`posernet.data.render.render_object_ring`) as a set: every ``step``-th view;
    ``background``: in a textured room, else in a plain bare one."""

    from posernet.data.render import render_intrinsics, render_object_ring

    folder = work / f"object-ring-{frames}-{'room' if background else 'bare'}"
    if not (folder / "all" / "render.json").is_file():
        render_object_ring(folder / "all", frames, background=background, overwrite=True,
                           progress=False)
    intr = ",".join(f"{v:g}" for v in render_intrinsics(folder / "all"))
    images = every_step(folder, folder / "all", frames, step)
    s = load_set(name or folder.name, images, intr)
    kept = f"one view in {step} of {frames}" if step > 1 else f"{frames} views"
    s.source = (f"posernet.data.render.render_object_ring: a plain cabinet-like object, {kept} "
                f"({360 * step / frames:g} deg apart) on a ring 1.5 m round it, "
                + ("in a textured room" if background else "in a plain bare room"))
    return s


# ----------------------------------------------------------------------------------- metrics


def evaluate(keys: list[str], gt_c2w: dict[str, np.ndarray],
             est_w2c: dict[str, np.ndarray], component: dict[str, int]) -> dict[str, Any]:
    """Errors of estimated world-to-camera poses ``est_w2c`` (placed cameras only) against
    ground-truth camera-to-world ``gt_c2w``, on the largest component (``component``: id per
    placed key; ties go to the smaller id).

    Returns ``images``, ``placed``, ``largest``, ``components`` and the medians ``rot_deg``
    (absolute rotation after the best global rotation), ``pos`` (camera centres after the
    Umeyama similarity, ground-truth units), ``rel_rot_deg`` and ``rel_tdir_deg`` (every pair
    of the component), ``pairs``; NaN where there is nothing to measure.
    """
    import torch

    from posernet.geometry import invert_se3, matrix_to_pose_vec
    from posernet.metrics import absolute_pose_errors_per_camera, relative_pose_errors

    placed = [k for k in keys if k in est_w2c]
    comps = sorted({int(component[k]) for k in placed})
    sizes = {c: sum(int(component[k]) == c for k in placed) for c in comps}
    out: dict[str, Any] = {"images": len(keys), "placed": len(placed), "largest": 0,
                           "components": len(comps), "pairs": 0}
    nan = float("nan")
    out.update(rot_deg=nan, pos=nan, rel_rot_deg=nan, rel_tdir_deg=nan)
    if not placed:
        return out
    main = max(comps, key=lambda c: (sizes[c], -c))
    sel = [k for k in placed if int(component[k]) == main]
    out["largest"] = len(sel)
    est = torch.as_tensor(np.stack([est_w2c[k] for k in sel]), dtype=torch.float64)
    gt = invert_se3(torch.as_tensor(np.stack([gt_c2w[k] for k in sel]), dtype=torch.float64))
    group = torch.zeros(len(sel), dtype=torch.long)
    rot, pos = absolute_pose_errors_per_camera(est, gt, group, 1, alignment="similarity",
                                               rotation_gauge="rotations")
    out["rot_deg"], out["pos"] = float(rot.median()), float(pos.median())
    if len(sel) >= 2:
        i, j = torch.triu_indices(len(sel), len(sel), offset=1)
        rel_est = matrix_to_pose_vec(est[j] @ invert_se3(est[i]))
        rel_gt = matrix_to_pose_vec(gt[j] @ invert_se3(gt[i]))
        rrot, rtdir = relative_pose_errors(rel_est, rel_gt)
        out["pairs"] = int(i.numel())
        out["rel_rot_deg"] = _nanmedian(rrot)
        out["rel_tdir_deg"] = _nanmedian(rtdir)
    return out


def _nanmedian(x: Any) -> float:
    a = np.asarray(x, dtype=np.float64)
    a = a[np.isfinite(a)]
    return float(np.median(a)) if a.size else float("nan")


# ------------------------------------------------------------------------------------ trust

TRUST_ROT_DEG = 5.0  # a placed camera is right within this rotation error ...
TRUST_POS_FRAC = 0.05  # ... and this position error, as a fraction of the scene's extent
# alignment hypotheses of a component: every 2-camera sample up to this many (drawn at random
# when more, i.e. over 63 cameras: all n(n-1)/2 of 1024 cameras would take half an hour) ...
TRUST_MAX_PAIRS = 2000
# ... and 300 3-camera samples, chosen from the list of all of them while it is this short
TRUST_LIST_TRIPLES = 100_000


def scene_extent(gt_c2w: dict[str, np.ndarray]) -> float:
    """The scene's extent for the trust counts: the diameter (largest distance between two)
    of the ground-truth camera centres of every image of the set."""
    c = np.array([np.asarray(T, dtype=np.float64)[:3, 3] for T in gt_c2w.values()])
    if len(c) < 2:
        return 0.0
    return float(np.max(np.linalg.norm(c[:, None] - c[None], axis=2)))


def _proj_so3(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ D @ Vt


def _fit_similarity(x: np.ndarray, y: np.ndarray, A: np.ndarray, B: np.ndarray, w: np.ndarray,
                    tau_p: float, tau_r: float) -> tuple[float, np.ndarray, np.ndarray]:
    """Weighted similarity ``y ~ s R x + t`` of estimated centres ``x (n, 3)`` onto
    ground-truth ones ``y`` that also turns the estimated camera-to-world rotations ``A``
    onto the ground-truth ``B``: minimises ``sum w (|y - s R x - t|^2 / tau_p^2 +
    |B - R A|_F^2 / (2 tau_r^2))`` (the rotation term is ~ (angle / tau_r)^2), alternating
    the exact R step (SVD) and s step from the rotation-only start. The orientations keep it
    determined on two cameras and on collinear centres."""
    W = float(w.sum())
    mx, my = (w @ x) / W, (w @ y) / W
    X, Y = x - mx, y - my
    xx = float(w @ np.sum(X * X, axis=1))
    rot = np.einsum("n,nij,nkj->ik", w, B, A) / (2 * tau_r**2)  # sum w B A^T, weighted
    cross = np.einsum("n,ni,nj->ij", w, Y, X) / tau_p**2  # sum w Y X^T
    R = _proj_so3(rot)
    s = 0.0
    for _ in range(30):
        s = max(float(np.einsum("n,ni,ni->", w, Y, X @ R.T)) / xx, 0.0) if xx > 0 else 0.0
        R_new = _proj_so3(s * cross + rot)
        if np.allclose(R_new, R, atol=1e-12):
            break
        R = R_new
    return s, R, my - s * R @ mx


def _trust_errors(s: float, R: np.ndarray, t: np.ndarray, x: np.ndarray, y: np.ndarray,
                  A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position error and rotation error (deg) of every camera after ``y ~ s R x + t``."""
    pos = np.linalg.norm(y - (s * x @ R.T + t), axis=1)
    cos = (np.einsum("nij,nij->n", R @ A, B) - 1) / 2  # trace((R A)^T B)
    return pos, np.degrees(np.arccos(np.clip(cos, -1, 1)))


def _align_robust(x: np.ndarray, y: np.ndarray, A: np.ndarray, B: np.ndarray, rot_deg: float,
                  pos_tol: float, rng: np.random.Generator
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The robust alignment of :func:`trust_counts` for one component: estimated centres
    ``x (n, 3)`` and camera-to-world rotations ``A``, ground truth ``y``, ``B``. Returns which
    cameras are right and every camera's position and rotation (deg) error."""
    n = len(x)
    tau_p, tau_r = max(pos_tol, 1e-12), np.radians(rot_deg)
    samples = [list(p) for p in zip(*np.triu_indices(n, 1), strict=True)]
    if len(samples) > TRUST_MAX_PAIRS:  # over 63 cameras: a random subset of the pairs
        samples = [samples[i] for i in rng.choice(len(samples), TRUST_MAX_PAIRS, replace=False)]
    if n * (n - 1) * (n - 2) // 6 <= TRUST_LIST_TRIPLES:
        triples = [[i, j, k] for i in range(n) for j in range(i + 1, n)
                   for k in range(j + 1, n)]
        if len(triples) > 300:
            triples = [triples[i] for i in rng.choice(len(triples), 300, replace=False)]
    else:  # too many to list (1024 cameras: 1.8e8): 300 distinct ones drawn directly
        drawn: set[tuple[int, ...]] = set()
        while len(drawn) < 300:
            drawn.add(tuple(sorted(int(v) for v in rng.choice(n, 3, replace=False))))
        triples = [list(t) for t in sorted(drawn)]
    samples += triples

    def score(fit: tuple[float, np.ndarray, np.ndarray]) -> tuple[tuple[int, float], np.ndarray]:
        pos, rot = _trust_errors(*fit, x, y, A, B)
        ok = (pos <= pos_tol) & (rot <= rot_deg)
        cost = float(np.sum(((pos / tau_p) ** 2 + (np.radians(rot) / tau_r) ** 2)[ok]))
        return (int(ok.sum()), -cost), ok

    best, best_key, best_ok = None, (-1, 0.0), np.zeros(n, bool)
    for smp in samples:
        w = np.zeros(n)
        w[smp] = 1.0
        fit = _fit_similarity(x, y, A, B, w, tau_p, tau_r)
        key, ok = score(fit)
        if key > best_key:
            best, best_key, best_ok = fit, key, ok
    # Final alignment: the least-squares fit on the right cameras, refitted until the set of
    # right cameras settles; they are judged under it, not under the sample's fit (which may
    # tilt within the tolerance to take in one more camera: max-consensus alone would pass
    # cameras up to about twice the tolerance off).
    for _ in range(10):
        if best_ok.sum() < 2:
            break
        best = _fit_similarity(x, y, A, B, best_ok.astype(np.float64), tau_p, tau_r)
        _, ok = score(best)
        if np.array_equal(ok, best_ok):
            break
        best_ok = ok
    pos, rot = _trust_errors(*best, x, y, A, B)
    return (pos <= pos_tol) & (rot <= rot_deg), pos, rot


def trust_counts(keys: list[str], gt_c2w: dict[str, np.ndarray],
                 est_w2c: dict[str, np.ndarray], component: dict[str, int],
                 rot_deg: float = TRUST_ROT_DEG, pos_frac: float = TRUST_POS_FRAC,
                 seed: int = 0) -> dict[str, Any]:
    """Cameras placed right or wrong, each component (model) of the estimate on its own.

    A placed camera (a key of ``est_w2c``, world-to-camera) is *right* when, after a robust
    similarity alignment of its component onto the ground truth (``gt_c2w``, camera to
    world), its rotation is within ``rot_deg`` degrees and its centre within ``pos_frac`` of
    the scene's extent (:func:`scene_extent`: the diameter of all the set's ground-truth
    camera centres) of the truth; else *wrong*. Cameras not in ``est_w2c`` (unsolved) and a
    camera alone in its component (placed relative to nothing) are *not placed*.

    Alignment (a few wrong cameras cannot drag it): hypotheses from every 2-camera sample (up
    to ``TRUST_MAX_PAIRS``, drawn at random when more) and up to 300 3-camera samples (all
    when fewer) of the component, each a similarity fitted to
    the sample's centres and orientations (:func:`_fit_similarity`); the one with the most
    right cameras wins (ties: the smaller summed squared errors over the thresholds of the
    right ones); then the least-squares similarity on its right cameras, refitted until the
    right ones settle, is the alignment every camera is judged under. Rotations are compared
    after the same similarity.

    Returns ``right``, ``wrong``, ``not_placed``, ``extent`` and per key in ``cameras``
    ``{"status": "right" | "wrong" | "not placed", "rot_deg", "pos"}`` (errors ``None`` when
    not placed).
    """
    extent = scene_extent({k: gt_c2w[k] for k in keys})
    cams: dict[str, dict[str, Any]] = {
        k: {"status": "not placed", "rot_deg": None, "pos": None} for k in keys}
    placed = [k for k in keys if k in est_w2c]
    rng = np.random.default_rng(seed)
    for c in sorted({int(component[k]) for k in placed}):
        sel = [k for k in placed if int(component[k]) == c]
        if len(sel) < 2:
            continue
        c2w = np.linalg.inv(np.stack([np.asarray(est_w2c[k], dtype=np.float64) for k in sel]))
        gt = np.stack([np.asarray(gt_c2w[k], dtype=np.float64) for k in sel])
        ok, pos, rot = _align_robust(c2w[:, :3, 3], gt[:, :3, 3], c2w[:, :3, :3],
                                     gt[:, :3, :3], rot_deg, pos_frac * extent, rng)
        for i, k in enumerate(sel):
            cams[k] = {"status": "right" if ok[i] else "wrong",
                       "rot_deg": float(rot[i]), "pos": float(pos[i])}
    status = [v["status"] for v in cams.values()]
    return {"right": status.count("right"), "wrong": status.count("wrong"),
            "not_placed": status.count("not placed"), "extent": extent, "cameras": cams}


# ---------------------------------------------------------------------------- subprocesses


# The method's process is started by this small launcher, not forked from the benchmark
# itself: Linux keeps ru_maxrss across exec, so a child forked from a process that has torch
# loaded would report the parent's memory as its own peak.
_LAUNCHER = """
import json, os, sys, time
out, cmd = sys.argv[1], sys.argv[2:]
t0 = time.perf_counter()
pid = os.fork()
if pid == 0:
    try:
        os.execvp(cmd[0], cmd)
    finally:
        os._exit(127)
_, status, ru = os.wait4(pid, 0)
wall = time.perf_counter() - t0
with open(out, "w") as fh:
    json.dump({"status": os.waitstatus_to_exitcode(status), "wall_s": wall,
               "maxrss": ru.ru_maxrss, "user_s": ru.ru_utime, "sys_s": ru.ru_stime}, fh)
"""


def run_child(cmd: list[str], log: Path, timeout: float,
              env: dict[str, str] | None = None) -> dict[str, Any]:
    """Run ``cmd`` with stdout and stderr into ``log``; its exit code, wall time (s), CPU time
    and peak resident memory (MB: ``ru_maxrss`` of that process alone, from ``os.wait4`` in a
    small launcher). Killed (with its launcher) after ``timeout`` seconds."""
    import signal

    log.parent.mkdir(parents=True, exist_ok=True)
    usage = log.with_name(log.stem + ".usage.json")
    usage.unlink(missing_ok=True)
    timed_out = False
    t0 = time.perf_counter()
    with open(log, "wb") as fh:
        p = subprocess.Popen([sys.executable, "-S", "-c", _LAUNCHER, str(usage), *cmd],
                             stdout=fh, stderr=subprocess.STDOUT, env=env,
                             start_new_session=True)
        try:
            p.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            timed_out = True
            os.killpg(p.pid, signal.SIGKILL)  # the launcher's own session: it and the method
            p.wait()
    wall = time.perf_counter() - t0
    if not usage.is_file():  # launcher killed or broken
        return {"returncode": p.returncode or -1, "wall_s": wall, "peak_mb": float("nan"),
                "timed_out": timed_out}
    u = json.loads(usage.read_text(encoding="utf-8"))
    # Linux reports ru_maxrss in KiB, macOS in bytes
    rss = u["maxrss"] / (1024 * 1024 if sys.platform == "darwin" else 1024)
    return {"returncode": u["status"], "wall_s": u["wall_s"], "peak_mb": rss,
            "cpu_s": u["user_s"] + u["sys_s"], "timed_out": timed_out}


def _tail(log: Path) -> str:
    """The error line of a failed run's log (its last line when there is none)."""
    import re

    try:
        lines = [s.strip() for s in log.read_text(encoding="utf-8", errors="replace")
                 .splitlines() if s.strip()]
    except OSError:
        return ""
    pat = re.compile(r"(^[\w.]*(Error|Exception)\b.*)|(: error\b)")
    errs = [s for s in lines if pat.search(s) and "HYDRA_FULL_ERROR" not in s]
    return (errs or lines or [""])[-1][:200].replace("|", "/")


def child_env(threads: int) -> dict[str, str]:
    env = dict(os.environ)
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        env[var] = str(threads)
    return env


def compile_bytecode() -> str:
    """Byte-compile the posernet package once, as ``pip install`` does for a wheel.

    An editable install compiles on first import, unless ``PYTHONDONTWRITEBYTECODE`` is set
    (as on some CI machines): then every timed run would recompile ~50 modules (0.2 s), a cost
    no installed user pays and the COLMAP runs (an installed wheel) do not pay either.
    """
    import compileall
    import importlib.util

    spec = importlib.util.find_spec("posernet")
    if spec is None or not spec.submodule_search_locations:
        return "posernet not importable: not byte-compiled"
    folder = Path(next(iter(spec.submodule_search_locations)))
    ok = compileall.compile_dir(folder, quiet=1)
    state = "ok" if ok else "with errors"
    return f"posernet byte-compiled before timing ({state}), as an installed wheel is"


def posernet_command(s: ImageSet, m: Method, out: Path, threads: int) -> list[str]:
    exe = Path(sys.executable).parent / "posernet-reconstruct"
    base = [str(exe)] if exe.is_file() else [sys.executable, "-m", "posernet.cli.reconstruct"]
    # gt_poses=none: the benchmark scores the poses itself; posernet need not evaluate them.
    # workers: the threads over images and pairs (COLMAP's num_threads); torch's own threads
    # inside each worker stay at the default (num_threads=1)
    return [*base, f"images={s.images}", f"intrinsics={s.intrinsics}", f"out_dir={out}",
            "progress=false", "pictures=0", "gt_poses=none", f"workers={threads}",
            *m.overrides]


def read_posernet(out: Path) -> tuple[dict[str, np.ndarray], dict[str, int], dict[str, Any]]:
    """World-to-camera poses and component ids of the placed cameras from ``poses.json``
    (only its ``cameras`` records: ``solved``, ``component``, ``camera_to_world``)."""
    data = json.loads((out / "poses.json").read_text(encoding="utf-8"))
    w2c, comp = {}, {}
    for key, cam in data["cameras"].items():
        if cam.get("solved") and cam.get("camera_to_world") is not None:
            w2c[key] = np.linalg.inv(np.asarray(cam["camera_to_world"], dtype=np.float64))
            comp[key] = int(cam.get("component") or 0)
    extra: dict[str, Any] = {"backend": data.get("backend"), "stage": data.get("stage")}
    summary = out / "summary.json"
    if summary.is_file():
        extra["seconds_inside"] = json.loads(summary.read_text()).get("seconds_total")
    return w2c, comp, extra


def colmap_camera(K: np.ndarray, dist: np.ndarray | None) -> tuple[str, list[float]]:
    """COLMAP camera model and parameters of ``K`` and OpenCV distortion ``dist``."""
    f = [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]
    d = np.zeros(0) if dist is None else np.asarray(dist, dtype=np.float64)
    if not np.any(d):
        return "PINHOLE", f
    if d.size <= 4 or (d.size >= 5 and not np.any(d[4:])):
        return "OPENCV", f + [float(v) for v in np.pad(d[:4], (0, 4 - min(d.size, 4)))]
    if d.size <= 8:  # k1 k2 p1 p2 k3 k4 k5 k6
        return "FULL_OPENCV", f + [float(v) for v in np.pad(d, (0, 8 - d.size))]
    raise BenchError(f"distortion with {d.size} coefficients has no COLMAP camera model")


def colmap_status(kind: str) -> str | None:
    """``None`` when pycolmap can run ``kind``, else why not (the note of a skipped row)."""
    try:
        import pycolmap
    except ImportError:
        return f"skipped: pycolmap is not installed (pip install {PYCOLMAP_PIN})"
    fn = "global_mapping" if kind == "colmap-global" else "incremental_mapping"
    if not hasattr(pycolmap, fn):
        return f"skipped: pycolmap {getattr(pycolmap, '__version__', '?')} has no {fn}"
    return None


def colmap_options(kind: str, threads: int, seed: int, matching: str = "exhaustive"
                   ) -> dict[str, dict[str, Any]]:
    """The pycolmap options this benchmark sets (dotted paths; all others at their defaults):
    every intrinsic fixed in bundle adjustment and pose registration, models down to 2 images
    kept (defaults 10 incremental, 3 global) so components count as posernet's do.
    ``matching="sequential"`` adds the ``SequentialPairingOptions`` under ``pairing``:
    overlap 10 with quadratic overlap (COLMAP's defaults), loop detection off (it needs a
    vocabulary tree). In pycolmap 4.2.1 quadratic overlap pairs each image (name order) with
    those 1, 2, 4, ..., 512 further on, instead of the next 10: 33 pairs on 12 images, not
    65."""
    if matching not in COLMAP_MATCHING:
        raise BenchError(f"COLMAP matching {matching!r}: choose {', '.join(COLMAP_MATCHING)}")
    mapper: dict[str, Any] = {"num_threads": threads, "random_seed": seed, "min_model_size": 2}
    if kind == "colmap-global":
        mapper.update({
            "mapper.num_threads": threads, "mapper.random_seed": seed,
            "mapper.bundle_adjustment.refine_focal_length": False,
            "mapper.bundle_adjustment.refine_principal_point": False,
            "mapper.bundle_adjustment.refine_extra_params": False,
            "mapper.bundle_adjustment.ceres.use_gpu": False,
            "mapper.global_positioning.use_gpu": False})
    else:
        mapper.update({
            "ba_refine_focal_length": False, "ba_refine_principal_point": False,
            "ba_refine_extra_params": False, "mapper.abs_pose_refine_focal_length": False,
            "mapper.abs_pose_refine_extra_params": False})
    out = {"extraction": {"num_threads": threads}, "matching": {"num_threads": threads},
           "mapper": mapper}
    if matching == "sequential":
        out["pairing"] = {"overlap": 10, "quadratic_overlap": True, "loop_detection": False,
                          "num_threads": threads}
    return out


def _apply(obj: Any, settings: dict[str, Any]) -> Any:
    """Set ``settings`` (dotted attribute paths) on a pycolmap options object; returns it."""
    for path, value in settings.items():
        *parents, name = path.split(".")
        target = obj
        for p in parents:
            target = getattr(target, p)
        if not hasattr(target, name):
            raise AttributeError(f"pycolmap {type(target).__name__} has no option {name!r}")
        setattr(target, name, value)
    return obj


def _pair_counts(pycolmap: Any, db: Path) -> dict[str, int] | None:
    """Image pairs matched and pairs geometrically verified in the database (``None`` when
    this pycolmap cannot say)."""
    try:
        d = pycolmap.Database.open(db)
    except (AttributeError, RuntimeError, ValueError):
        return None
    try:
        return {"matched": int(d.num_matched_image_pairs()),
                "verified": int(d.num_verified_image_pairs())}
    except (AttributeError, RuntimeError, TypeError):
        return None
    finally:
        d.close()


def colmap_worker(spec_path: str) -> None:
    """The COLMAP side of one run (in its own process): SIFT with fixed intrinsics,
    exhaustive or sequential matching (``spec["matching"]``, default exhaustive; matching
    includes the two-view verification), the mapper; writes the placed cameras, the seconds
    of each step and the matched / verified pair counts to ``spec["result"]``."""
    import pycolmap

    spec = json.loads(Path(spec_path).read_text(encoding="utf-8"))
    work = Path(spec["work"])
    db = work / "database.db"
    db.unlink(missing_ok=True)
    device = pycolmap.Device.cpu if hasattr(pycolmap, "Device") else None
    dev = {"device": device} if device is not None else {}
    seconds = {}
    t0 = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = spec["camera_model"]
    reader.camera_params = ",".join(repr(v) for v in spec["camera_params"])
    extraction = _apply(pycolmap.FeatureExtractionOptions(), spec["options"]["extraction"])
    pycolmap.extract_features(db, spec["images"], image_names=spec["names"],
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, **dev)
    seconds["features"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    matching = _apply(pycolmap.FeatureMatchingOptions(), spec["options"]["matching"])
    mode = spec.get("matching", "exhaustive")
    if mode == "sequential":
        pairing = _apply(pycolmap.SequentialPairingOptions(), spec["options"]["pairing"])
        pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing,
                                  **dev)
    else:
        pycolmap.match_exhaustive(db, matching_options=matching, **dev)
    seconds["matching"] = time.perf_counter() - t0
    pairs = _pair_counts(pycolmap, db)
    t0 = time.perf_counter()
    out = work / "sparse"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    if spec["mapper"] == "colmap-global":
        opts = _apply(pycolmap.GlobalPipelineOptions(), spec["options"]["mapper"])
        models = pycolmap.global_mapping(db, spec["images"], out, opts)
    else:
        opts = _apply(pycolmap.IncrementalPipelineOptions(), spec["options"]["mapper"])
        models = pycolmap.incremental_mapping(db, spec["images"], out, opts)
    seconds["mapping"] = time.perf_counter() - t0
    # component 0 = the largest model; an image in several models keeps the largest's pose
    ranked = sorted(models.values(), key=lambda r: -r.num_reg_images())
    cams: dict[str, Any] = {}
    params = []
    for c, rec in enumerate(ranked):
        params.append([list(map(float, cam.params)) for cam in rec.cameras.values()])
        for im in rec.images.values():
            if im.name in cams or not im.has_pose:
                continue
            T = im.cam_from_world()
            M = np.eye(4)
            M[:3] = np.asarray(T.matrix() if callable(getattr(T, "matrix", None)) else T)
            cams[im.name] = {"w2c": M.tolist(), "component": c}
    Path(spec["result"]).write_text(json.dumps({
        "cameras": cams, "models": len(ranked), "seconds": seconds, "matching": mode,
        "pairs": pairs,
        "camera_params_after": params, "pycolmap": pycolmap.__version__}), encoding="utf-8")


def run_method(s: ImageSet, m: Method, work: Path, threads: int, timeout: float,
               seed: int = 0, colmap_matching: str = "exhaustive",
               poses: dict[str, np.ndarray] | None = None) -> dict[str, Any]:
    """One method on one set in a subprocess: the row of the results (errors, wall time, peak
    memory, the command), or a row with a ``note`` when it was skipped or failed.
    ``colmap_matching``: the COLMAP methods' pair selection (:data:`COLMAP_MATCHING`);
    ``poses``: filled with the placed cameras' world-to-camera poses when given."""
    row: dict[str, Any] = {"set": s.name, "method": m.label, "kind": m.kind,
                           "overrides": m.overrides, "images": len(s.keys), "note": ""}
    out = work / "runs" / s.name / m.label
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    if m.kind == "posernet":
        cmd = posernet_command(s, m, out / "out", threads)
    else:
        why = colmap_status(m.kind)
        if why:
            row["note"] = why
            return row
        model, params = colmap_camera(s.K, s.dist)
        spec = {"images": str(s.images), "names": s.keys, "camera_model": model,
                "camera_params": params, "mapper": m.kind, "matching": colmap_matching,
                "options": colmap_options(m.kind, threads, seed, colmap_matching),
                "work": str(out), "result": str(out / "result.json")}
        (out / "spec.json").write_text(json.dumps(spec, indent=1), encoding="utf-8")
        cmd = [sys.executable, str(Path(__file__).resolve()), "--colmap-worker",
               str(out / "spec.json")]
        row["colmap_camera"] = {"model": model, "params": params}
        row["colmap_options"] = spec["options"]
    row["command"] = shlex.join(cmd)
    log = out / "log.txt"
    print(f"{s.name} / {m.label}: {len(s.keys)} images ...", flush=True)
    row.update(run_child(cmd, log, timeout, child_env(threads)))
    row["log"] = str(log)
    w2c: dict[str, np.ndarray] = {}
    comp: dict[str, int] = {}
    if row["timed_out"]:
        row["note"] = f"timed out after {timeout:g} s"
    elif row["returncode"] != 0:
        row["note"] = f"failed (exit {row['returncode']}): {_tail(log)}"
    else:
        try:
            if m.kind == "posernet":
                w2c, comp, extra = read_posernet(out / "out")
                row.update(extra)
            else:
                res = json.loads((out / "result.json").read_text(encoding="utf-8"))
                w2c = {k: np.asarray(v["w2c"]) for k, v in res["cameras"].items()}
                comp = {k: int(v["component"]) for k, v in res["cameras"].items()}
                row.update(seconds_inside=res["seconds"],
                           camera_params_after=res["camera_params_after"],
                           colmap_matching=res.get("matching", colmap_matching),
                           colmap_pairs=res.get("pairs"))
        except (OSError, ValueError, KeyError, TypeError) as e:
            row["note"] = f"unreadable output ({type(e).__name__}: {e})"[:200]
    row.update(evaluate(s.keys, s.c2w, w2c, comp))
    if poses is not None:
        poses.update(w2c)
    trust = trust_counts(s.keys, s.c2w, w2c, comp, seed=seed)
    row.update(right=trust["right"], wrong=trust["wrong"], not_placed=trust["not_placed"],
               extent=trust["extent"], trust=trust["cameras"])
    print(f"  {_cell(row['placed'], '{}')}/{len(s.keys)} placed ({row['right']} right, "
          f"{row['wrong']} wrong), rot "
          f"{_cell(row.get('rot_deg'))} deg, {row['wall_s']:.1f} s, {row['peak_mb']:.0f} MB "
          f"{row['note']}", flush=True)
    return row


# ------------------------------------------------------------------------------------ pairs

#: the wide-baseline pairs mode: indoor sets (real, and a rendered room with every object
#: textured) whose pairs far apart in rotation are run two images at a time
PAIR_SETS = ("7scenes_redkitchen_wide",)
PAIR_RENDERED: tuple[tuple[str, str, int, int, int, int], ...] = ()  # (a rendered sweep turns
# by 25 deg at most: no pair is wide enough)
PAIR_MIN_DEG = 30.0  # pairs at least this far apart in rotation ...
PAIR_MIN_OVERLAP = 0.2  # ... that still see this share of each other's view (view_overlap)
PAIR_DEPTH = 2.0  # metres in front of the camera where the overlap proxy puts the scene
PAIR_LIMIT = 15  # pairs per set, spread evenly over the candidates' rotation angles
PAIR_AUC_DEG = (5.0, 10.0, 20.0)


def view_overlap(K: np.ndarray, size: tuple[int, int], c2w_a: np.ndarray, c2w_b: np.ndarray,
                 depth: float = PAIR_DEPTH, grid: int = 12) -> float:
    """Share of camera a's view, put on a fronto-parallel plane at ``depth``, that lies in
    front of camera b and inside its image ``size`` (W, H), the smaller of both directions.
    A proxy for co-visibility where a set has no depth maps (7-Scenes scenes lie 1-3 m
    away)."""
    W, H = size
    u, v = np.meshgrid(np.linspace(0.5, W - 0.5, grid), np.linspace(0.5, H - 0.5, grid))
    pix = np.stack((u.ravel(), v.ravel(), np.ones(u.size)))

    def share(src: np.ndarray, dst: np.ndarray) -> float:
        X = src[:3, :3] @ (np.linalg.solve(K, pix) * depth) + src[:3, 3:4]
        Y = np.linalg.inv(dst)[:3] @ np.vstack((X, np.ones(X.shape[1])))
        front = Y[2] > 1e-6
        p = K @ (Y / np.where(front, Y[2], 1.0))
        inside = front & (p[0] >= 0) & (p[0] < W) & (p[1] >= 0) & (p[1] < H)
        return float(inside.mean())

    return min(share(c2w_a, c2w_b), share(c2w_b, c2w_a))


def rotation_angle_deg(c2w_a: np.ndarray, c2w_b: np.ndarray) -> float:
    """Angle (deg) of the relative rotation between two camera-to-world poses."""
    R = c2w_a[:3, :3].T @ c2w_b[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def wide_pairs(s: ImageSet, size: tuple[int, int], min_deg: float = PAIR_MIN_DEG,
               min_overlap: float = PAIR_MIN_OVERLAP, limit: int = PAIR_LIMIT,
               depth: float = PAIR_DEPTH) -> list[tuple[str, str, float, float]]:
    """Pairs ``(a, b, rotation deg, overlap)`` of ``s`` at least ``min_deg`` apart in rotation
    that keep ``min_overlap`` of their views (:func:`view_overlap`): ``limit`` of them spread
    evenly over the candidates sorted by angle (ties by overlap), widest first.
    Deterministic."""
    out = []
    for i, a in enumerate(s.keys):
        for b in s.keys[i + 1:]:
            ang = rotation_angle_deg(s.c2w[a], s.c2w[b])
            if ang < min_deg:
                continue
            ov = view_overlap(s.K, size, s.c2w[a], s.c2w[b], depth)
            if ov >= min_overlap:
                out.append((a, b, ang, ov))
    out.sort(key=lambda p: (-p[2], -p[3], p[0], p[1]))
    if len(out) <= limit:
        return out
    return [out[i] for i in sorted({round(float(v)) for v in
                                    np.linspace(0, len(out) - 1, limit)})]


def pair_set(s: ImageSet, a: str, b: str, work: Path) -> ImageSet:
    """The two images ``a``, ``b`` of ``s`` linked into a folder of their own, with their
    pose files."""
    dst = work / f"{s.name}-{Path(a).stem}-{Path(b).stem}"
    shutil.rmtree(dst, ignore_errors=True)
    dst.mkdir(parents=True)
    for key in (a, b):
        os.symlink(s.images / key, dst / key)
        np.savetxt(dst / _pose_name(key), s.c2w[key], fmt="%.9f")
    return ImageSet(dst.name, dst, [a, b], s.intrinsics, s.K, s.dist,
                    {a: s.c2w[a], b: s.c2w[b]}, s.source, f"pair of {s.name}")


def pair_error(gt_c2w: dict[str, np.ndarray], est_w2c: dict[str, np.ndarray], a: str, b: str
               ) -> tuple[float, float]:
    """Relative rotation error and translation-direction error (deg) of the estimated pair
    ``a -> b`` by :func:`posernet.metrics.relative_pose_errors`, as every other relative error
    here; the direction is compared signed (a direction pointing backwards is 180 deg off).
    Both ``inf`` when either camera is not placed, the direction when it is undefined."""
    import torch

    from posernet.geometry import invert_se3, matrix_to_pose_vec
    from posernet.metrics import relative_pose_errors

    if a not in est_w2c or b not in est_w2c:
        return math.inf, math.inf
    est = torch.as_tensor(np.stack([est_w2c[a], est_w2c[b]]), dtype=torch.float64)
    gt = invert_se3(torch.as_tensor(np.stack([gt_c2w[a], gt_c2w[b]]), dtype=torch.float64))
    rot, tdir = relative_pose_errors(matrix_to_pose_vec(est[1:] @ invert_se3(est[:1])),
                                     matrix_to_pose_vec(gt[1:] @ invert_se3(gt[:1])))
    r, t = float(rot[0]), float(tdir[0])
    return (r if math.isfinite(r) else math.inf), (t if math.isfinite(t) else math.inf)


def pose_auc(errors: list[float], thresholds: tuple[float, ...] = PAIR_AUC_DEG) -> list[float]:
    """Area under the recall curve of ``errors`` (deg; ``inf`` for a failed pair) up to each
    threshold, normalised by it, in percent: the pose AUC as SuperGlue reports it."""
    e = np.sort(np.asarray(errors, np.float64))
    n = e.size
    recall = np.arange(1, n + 1) / max(n, 1)
    e = np.concatenate(([0.0], e))
    recall = np.concatenate(([0.0], recall))
    out = []
    for t in thresholds:
        last = int(np.searchsorted(e, t))
        x = np.concatenate((e[:last], [t]))
        y = np.concatenate((recall[:last], [recall[last - 1]]))
        out.append(100.0 * float(np.trapezoid(y, x)) / t)
    return out


PAIR_HEADER = ("set", "method", "pairs", "placed", "within 5 deg", "within 10 deg",
               "within 20 deg", "wrong (> 20 deg)", "AUC@5", "AUC@10", "AUC@20",
               "median wall (s)")


def pair_summary(rows: list[dict[str, Any]]) -> list[list[str]]:
    """One line per (set, method) of the pair rows: counts within 5 / 10 / 20 deg (rotation
    and signed direction), placed pairs beyond 20 deg (reported with a wrong pose), pose AUC."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["pair_set"], r["method"]), []).append(r)
    out = []
    for (name, method), rs in groups.items():
        err = [max(r["pair_rot_deg"], r["pair_tdir_deg"]) for r in rs]
        placed = [r for r in rs if math.isfinite(r["pair_rot_deg"])]
        within = [sum(e <= t for e in err) for t in PAIR_AUC_DEG]
        wrong = sum(1 for r, e in zip(rs, err, strict=True)
                    if math.isfinite(r["pair_rot_deg"]) and e > PAIR_AUC_DEG[-1])
        walls = [r["wall_s"] for r in rs if r.get("wall_s") is not None]
        out.append([name, method, str(len(rs)), str(len(placed)), *map(str, within),
                    str(wrong), *(f"{a:.1f}" for a in pose_auc(err)),
                    _cell(float(np.median(walls)) if walls else None, "{:.1f}")])
    return out


def run_pairs(sets: list[ImageSet], methods: list[Method], work: Path, threads: int,
              timeout: float, seed: int) -> tuple[list[dict[str, Any]], list[str]]:
    """Every method on every wide pair of ``sets`` (:func:`wide_pairs`): one row per pair and
    method with its errors (:func:`pair_error`), and the lines listing the pairs."""
    import cv2

    rows, lines = [], []
    for s in sets:
        first = cv2.imread(str(s.images / s.keys[0]), cv2.IMREAD_UNCHANGED)
        if first is None:
            raise BenchError(f"{s.images / s.keys[0]}: not a readable image")
        size = (first.shape[1], first.shape[0])
        pairs = wide_pairs(s, size)
        lines.append(f"- {s.name}: {len(pairs)} pairs, " + ", ".join(
            f"{Path(a).stem}/{Path(b).stem} ({ang:.0f} deg, overlap {ov:.2f})"
            for a, b, ang, ov in pairs))
        for a, b, ang, ov in pairs:
            ps = pair_set(s, a, b, work / "pairs")
            for m in methods:
                w2c: dict[str, np.ndarray] = {}
                row = run_method(ps, m, work, threads, timeout, seed, poses=w2c)
                rot, tdir = pair_error(s.c2w, w2c, a, b)
                row.update(pair_set=s.name, pair=[a, b], gt_rotation_deg=ang, overlap=ov,
                           pair_rot_deg=rot, pair_tdir_deg=tdir)
                rows.append(row)
    return rows, lines


# ------------------------------------------------------------------------------------ output


def _cell(v: Any, fmt: str = "{:.2f}") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return fmt.format(v)


HEADER = ("set", "method", "placed / N", "right", "wrong", "largest comp.", "components",
          "abs. rot (deg)", "abs. pos (GT units)", "rel. rot (deg)", "rel. tdir (deg)",
          "wall (s)", "CPU (s)", "peak mem (MB)", "note")


def table_rows(rows: list[dict[str, Any]]) -> list[list[str]]:
    out = []
    for r in rows:
        skipped = "placed" not in r
        out.append([
            r["set"], r["method"],
            "-" if skipped else f"{r['placed']} / {r['images']}",
            "-" if skipped else str(r["right"]), "-" if skipped else str(r["wrong"]),
            "-" if skipped else str(r["largest"]),
            "-" if skipped else str(r["components"]),
            _cell(r.get("rot_deg")), _cell(r.get("pos"), "{:.3f}"),
            _cell(r.get("rel_rot_deg")), _cell(r.get("rel_tdir_deg")),
            _cell(r.get("wall_s"), "{:.1f}"), _cell(r.get("cpu_s"), "{:.1f}"),
            _cell(r.get("peak_mb"), "{:.0f}"),
            r.get("note") or ""])
    return out


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, np.generic):
        return _jsonable(x.item())
    if isinstance(x, Path):
        return str(x)
    return x


def versions() -> dict[str, str | None]:
    import importlib.metadata as md
    import platform

    import cv2
    import torch

    out: dict[str, str | None] = {"python": platform.python_version()}
    for dist in ("posernet", "pycolmap"):
        try:
            out[dist] = md.version(dist)
        except md.PackageNotFoundError:
            out[dist] = None
    out.update(opencv=cv2.__version__, torch=torch.__version__, numpy=np.__version__)
    return out


def discover(names: tuple[str, ...] | None = None
             ) -> tuple[list[tuple[str, Path, str | None]], list[str]]:
    """Every folder under ``benchmarks/data/real/`` (``NAME = folder name``; only ``names``
    when given); folders not yet usable are left out with a note."""
    sets, notes = [], []
    if DATA.is_dir():
        for d in sorted(p for p in DATA.iterdir() if p.is_dir() and p.name[0] not in "._"):
            if names is None or d.name in names:
                sets.append((d.name, d, None))
    for n in names or ():
        if not (DATA / n).is_dir():
            notes.append(f"left out {DATA / n}: not built (benchmarks/data/real/build_sets.py)")
    if not sets:
        notes.append(f"no set folders under {DATA}")
    return sets, notes


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--set", action="append", default=[], metavar="NAME=DIR[:INTRINSICS]",
                    help="an image folder with <stem>.pose.txt ground truth; INTRINSICS: "
                         "FX,FY,CX,CY or a file (default DIR/intrinsics.json or .txt); repeat. "
                         "Default: every folder under benchmarks/data/real/ plus a rendered scene")
    ap.add_argument("--rendered", action="store_true",
                    help="add a rendered scene (posernet.data.render) to the --set folders")
    ap.add_argument("--method", action="append", default=[], metavar="METHOD",
                    help="posernet[-LABEL][=HYDRA OVERRIDES] (e.g. 'posernet-eig=sync=eig_se3'), "
                         f"{', '.join(COLMAP_METHODS)}; repeat (default: "
                         f"{', '.join(DEFAULT_METHODS)})")
    ap.add_argument("--max-images", type=int, default=0,
                    help="evenly spaced images per set (0: all; --quick: 8)")
    ap.add_argument("--frames", type=int, default=None,
                    help="frames of the rendered scene (default 16; --quick: 8)")
    ap.add_argument("--scene", default="chess", help="preset of the rendered scene")
    ap.add_argument("--threads", type=int, default=1,
                    help="threads of every method (posernet num_threads/workers, COLMAP "
                         "num_threads, OMP)")
    ap.add_argument("--seed", type=int, default=0, help="COLMAP mapper seed")
    ap.add_argument("--colmap-matching", choices=COLMAP_MATCHING, default="exhaustive",
                    help="COLMAP's pair selection: exhaustive (default) or sequential (overlap "
                         "10, quadratic: the images 1, 2, 4, ..., 512 further on in name order)")
    ap.add_argument("--timeout", type=float, default=3600, help="seconds per method and set")
    ap.add_argument("--work", default=None,
                    help="folder for renders and run outputs (default: a temp folder)")
    ap.add_argument("--quick", action="store_true", help="tiny run: 8 images, 320x240 render")
    ap.add_argument("--trust", action="store_true",
                    help="the trust table: the sets of TRUST_SETS under benchmarks/data/real/, "
                         "no rendered scene; writes benchmarks/results/trust.md by default")
    ap.add_argument("--pairs", action="store_true",
                    help="the wide-baseline pairs mode: pairs at least 30 deg apart of the "
                         "indoor sets of PAIR_SETS and PAIR_RENDERED, two images per run, pose "
                         "AUC@5/10/20; writes benchmarks/results/pairs.md by default")
    ap.add_argument("--out", default=None,
                    help="results table (default benchmarks/results/real.md; real.json beside)")
    ap.add_argument("--colmap-worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.colmap_worker:
        colmap_worker(args.colmap_worker)
        return 0

    methods = [parse_method(t) for t in (args.method or DEFAULT_METHODS)]
    labels = [m.label for m in methods]
    if len(set(labels)) != len(labels):
        raise BenchError(f"method labels repeat: {labels}; name variants posernet-LABEL")
    if args.trust and args.set:
        raise BenchError("--trust picks its own sets: give --trust or --set, not both")
    if args.pairs and (args.trust or args.set):
        raise BenchError("--pairs picks its own sets: give it without --trust and --set")
    if args.set:
        specs, notes = [parse_set(t) for t in args.set], []
        rendered = args.rendered
    elif args.trust:
        (specs, notes), rendered = discover(TRUST_SETS), args.rendered
    elif args.pairs:
        (specs, notes), rendered = discover(PAIR_SETS), args.rendered
    else:
        (specs, notes), rendered = discover(), True
    names = [n for n, _, _ in specs]
    if len(set(names)) != len(names):
        raise BenchError(f"set names repeat: {names}")
    work = Path(args.work or Path(tempfile.gettempdir()) / "posernet-bench-real")
    work.mkdir(parents=True, exist_ok=True)
    max_images = args.max_images or (8 if args.quick else 0)
    sets = []
    for spec in specs:  # every input checked before any run
        try:
            sets.append(load_set(*spec))
        except BenchError as e:
            if args.set:
                raise
            notes.append(f"left out {spec[1]}: {e}")  # a folder still being assembled
            print(f"note: left out {spec[1]}: {e}", file=sys.stderr)
    if rendered:
        frames = args.frames or (8 if args.quick else 16)
        size = (320, 240) if args.quick else (640, 480)
        sets.append(rendered_set(work / "render", args.scene, frames, *size))
    if args.trust:
        for name, scene, seed, frames, step, every in TRUST_RENDERED:
            sets.append(rendered_set(work / "render", scene, frames, 640, 480, seed=seed,
                                     step=step, textured_every=every, name=name))
        for name, frames, step, background in TRUST_RINGS:
            sets.append(ring_set(work / "render", frames, step, background, name))
    if args.pairs:
        for name, scene, seed, frames, step, every in PAIR_RENDERED:
            sets.append(rendered_set(work / "render", scene, frames, 640, 480, seed=seed,
                                     step=step, textured_every=every, name=name))
    sets = [subsample(s, max_images, work / "subsets") for s in sets]
    for m in methods:
        if m.kind != "posernet" and (why := colmap_status(m.kind)):
            notes.append(f"{m.label}: {why}")

    notes.append(compile_bytecode())
    pair_lines: list[str] = []
    if args.pairs:
        rows, pair_lines = run_pairs(sets, methods, work, args.threads, args.timeout, args.seed)
    else:
        rows = [run_method(s, m, work, args.threads, args.timeout, args.seed,
                           args.colmap_matching) for s in sets for m in methods]

    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))  # benchmarks/_common.py
    from _common import command, table, write_results

    from posernet.io import atomic_write_json

    ver = versions()
    body = [
        f"- packages: {', '.join(f'{k} {v}' for k, v in ver.items() if k != 'python')}",
        f"- threads per method: {args.threads}; COLMAP: SIFT with the set's intrinsics "
        f"(one shared camera), {args.colmap_matching} matching, mapper with focal length, "
        "principal point "
        "and distortion fixed and models down to 2 images kept (options in the .json)",
        "- errors on the largest component (COLMAP: largest model); abs. rot after the best "
        "global rotation, abs. pos after a similarity (Umeyama) on the camera centres; rel. "
        "errors over every image pair of that component; medians. Wall time, CPU time (user + "
        "system) and peak memory (ru_maxrss) of the method's subprocess, interpreter start and "
        "imports included",
        f"- right / wrong: a placed camera is right when, after a robust similarity alignment "
        f"of its component (model) onto the ground truth, its rotation is within "
        f"{TRUST_ROT_DEG:g} deg and its centre within {100 * TRUST_POS_FRAC:g} % of the "
        "scene's extent (the diameter of all the set's ground-truth camera centres), else "
        "wrong; unsolved cameras and a camera alone in its component count as neither "
        "(trust_counts)",
        *(f"- note: {n}" for n in notes),
        "",
        "| set | images | intrinsics (fx, fy, cx, cy) | source |",
        "|---|---:|---|---|",
        *(f"| {s.name} | {len(s.keys)} | "
          + ", ".join(f"{v:g}" for v in (s.K[0, 0], s.K[1, 1], s.K[0, 2], s.K[1, 2]))
          + f"{' + dist' if s.dist is not None and np.any(s.dist) else ''} | "
          + "; ".join(x for x in (s.source, s.note) if x) + " |" for s in sets),
        "",
    ]
    if args.pairs:
        body += [
            f"Wide-baseline pairs: every pair of a set at least {PAIR_MIN_DEG:g} deg apart in "
            f"rotation whose views overlap by at least {PAIR_MIN_OVERLAP:g} (each camera's "
            f"view on a plane {PAIR_DEPTH:g} m in front of it, the share inside the other "
            f"image, the smaller of both ways), the {PAIR_LIMIT} widest per set; each pair "
            "is its own two-image run. Error of a pair: the larger of the relative rotation "
            "error and the signed translation-direction error (a backwards direction is 180 "
            "deg off); a pair not placed has an infinite error. AUC: the area under the "
            "recall curve up to each threshold, normalised, in percent (as SuperGlue reports "
            "it). Wrong: placed, but more than 20 deg off.",
            "",
            *pair_lines,
            "",
            *table(PAIR_HEADER, pair_summary(rows)),
            "",
            *table(("set", "pair", "GT rotation (deg)", "overlap", "method", "rot. err (deg)",
                    "dir. err (deg)", "wall (s)", "note"),
                   [[r["pair_set"], " / ".join(Path(k).stem for k in r["pair"]),
                     f"{r['gt_rotation_deg']:.0f}", f"{r['overlap']:.2f}", r["method"],
                     _cell(r["pair_rot_deg"], "{:.1f}"), _cell(r["pair_tdir_deg"], "{:.1f}"),
                     _cell(r.get("wall_s"), "{:.1f}"), r.get("note") or ""] for r in rows]),
        ]
    else:
        body += table(HEADER, table_rows(rows))
    title = "posernet-reconstruct vs COLMAP on real image sets"
    kind = "pairs" if args.pairs else "trust" if args.trust else "real"
    md = write_results(kind, title + {"trust": ": cameras placed right / wrong",
                                      "pairs": ": wide-baseline image pairs"}.get(kind, ""),
                       body, args.quick, "cpu", args.out)
    report = {
        "command": command(), "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "machine": {"cpu": _cpu(), "cores": os.cpu_count(), "threads_per_method": args.threads},
        "versions": ver, "arguments": vars(args),
        "methods": [{"label": m.label, "kind": m.kind, "overrides": m.overrides}
                    for m in methods],
        "sets": [{"name": s.name, "images_dir": str(s.images), "images": len(s.keys),
                  "intrinsics": s.intrinsics, "K": s.K.tolist(),
                  "dist": None if s.dist is None else s.dist.tolist(), "source": s.source,
                  "note": s.note} for s in sets],
        "notes": notes, "rows": rows,
    }
    path = atomic_write_json(md.with_suffix(".json"), _jsonable(report))
    print(f"written: {path}")
    return 0


def _cpu() -> str:
    from posernet.report import cpu_model

    return cpu_model()


if __name__ == "__main__":
    try:
        sys.exit(main())
    except BenchError as e:
        print(f"bench_real.py: error: {e}", file=sys.stderr)
        sys.exit(2)

"""Reader and writer for the authors' released graph files (``eccv_final_objectness_set*.json``).

Schema (per graph of the top-level ``train`` / ``test`` lists):

* ``cameras[cam_id]``: ``camera_to_world`` 4x4, ``K`` 3x3, ``K_i``, optional paths, and
  ``matches[other_id]``: list of ``{bb_i, bb_f}`` pixel boxes ``(x1, y1, x2, y2)``, ``bb_i`` in
  this camera and ``bb_f`` in the other; matches are listed from both sides.
* ``detections``: ``detection_bb``, ``box_matches_sparse``, ``detection_cam``, ``detection_seq``
  and ``covisibility`` (n x n, 1 where two cameras share at least five matched detections).
* ``relative_poses[i][f]``: 4x4 ``ground_truth``, ``feature_5pt`` (KP), ``bb_centre_5pt`` (BB),
  optional ``free_keypoint``; each maps camera-i points into camera f.

The reader takes matched boxes from ``cameras[*].matches`` (they carry the coordinates) and the
edges from ``covisibility``. Cameras have no image size in the schema: an optional
``image_size`` entry (written by :func:`save_posernet_json`) is used when present, otherwise
twice the principal point (exact for 7-Scenes' Kinect intrinsics).

Ground truth is optional (for graphs to refine rather than evaluate): without
``camera_to_world`` (absent or ``null``) on every camera the graph has no ``pose_gt``; its
``edge_pose_gt`` then comes from ``relative_poses[i][f].ground_truth`` when every covisible pair
has one, else it is absent too. Ground truth given for some cameras (or pairs) but not others
is refused as malformed: nothing is filled in.

Lens distortion (node feature ``k1``, as in the synthetic training graphs, see
:func:`posernet.graph.node_attributes`): the schema has none. A camera's ``k1`` entry (written
by :func:`save_posernet_json`) or the first coefficient of a ``distortion`` list (OpenCV order
``k1, k2, p1, p2, k3``) is used when present; otherwise ``default_k1`` of
:func:`load_posernet_json` (0: the images are assumed free of radial distortion, as posernet's
image front end assumes without ``dist``). The ``paper`` synthetic preset, on which the shipped
checkpoint was trained, simulates uncorrected Kinect frames with k1 = 0.2.
"""

from __future__ import annotations

import json
import math
import os
import re
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..geometry import invert_pose_vec, invert_se3, matrix_to_pose_vec, pose_vec_to_matrix
from ..graph import (
    REF_K1,
    GraphValidationError,
    ViewGraph,
    denormalize_boxes,
    node_attributes,
    normalize_boxes,
)
from ..io import atomic_write_json
from .layout import SCENES

__all__ = ["ESTIMATE_KEYS", "SCENES", "load_posernet_json", "save_posernet_json"]

# JSON estimate name -> our short name (``ViewGraph.estimates`` key).
ESTIMATE_KEYS: dict[str, str] = {
    "feature_5pt": "kp",
    "bb_centre_5pt": "bb",
    "free_keypoint": "free",
    "ground_truth": "gt",
}
_JSON_NAME = {v: k for k, v in ESTIMATE_KEYS.items()}
_SCENE_RE = re.compile(r"(?:^|[/\\])(" + "|".join(SCENES) + r")(?:[/\\]|$)")
_SEQ_RE = re.compile(r"seq-(\d+)")
_RIGID_TOL = 1e-3


class _Malformed(Exception):
    """A graph breaks the schema; caught per graph and turned into an error or a skip."""


def _matrix(value: Any, shape: tuple[int, int], what: str) -> Tensor:
    try:
        t = torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError) as exc:
        raise _Malformed(f"{what} is not a numeric matrix ({exc})") from None
    if tuple(t.shape) != shape:
        raise _Malformed(f"{what} has shape {tuple(t.shape)}, expected {shape}")
    if not bool(torch.isfinite(t).all()):
        raise _Malformed(f"{what} contains NaN/inf")
    return t


def _rigid(value: Any, what: str) -> Tensor:
    T = _matrix(value, (4, 4), what)
    R = T[:3, :3]
    if (
        float((R.T @ R - torch.eye(3, dtype=T.dtype)).abs().max()) > _RIGID_TOL
        or float(torch.linalg.det(R)) <= 0
        or float((T[3] - T.new_tensor([0, 0, 0, 1])).abs().max()) > _RIGID_TOL
    ):
        raise _Malformed(f"{what} is not a rigid transform")
    return T


def _box(value: Any, what: str) -> tuple[float, float, float, float]:
    if not isinstance(value, (list, tuple)) or len(value) != 4:
        raise _Malformed(f"{what} must be a list of 4 numbers (x1, y1, x2, y2), got {value!r}")
    try:
        box = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise _Malformed(f"{what} must be numeric, got {value!r}") from None
    if not all(math.isfinite(v) for v in box) or box[2] < box[0] or box[3] < box[1]:
        raise _Malformed(f"{what} is not a valid box (x1, y1, x2, y2): {value!r}")
    return box  # type: ignore[return-value]


def _k1(cam: Mapping, cid: str, default: float) -> float:
    """The camera's first radial distortion coefficient (``k1`` or ``distortion[0]``)."""
    value: Any = cam.get("k1")
    what = f"camera {cid!r} 'k1'"
    if value is None and cam.get("distortion") is not None:
        dist = cam["distortion"]
        if not isinstance(dist, (list, tuple)) or not dist:
            raise _Malformed(f"camera {cid!r} 'distortion' must be a non-empty list "
                             f"(k1, k2, p1, p2, k3), got {dist!r}")
        value, what = dist[0], f"camera {cid!r} 'distortion[0]'"
    if value is None:
        return float(default)
    try:
        k1 = float(value)
    except (TypeError, ValueError):
        raise _Malformed(f"{what} must be a number, got {value!r}") from None
    if not math.isfinite(k1):
        raise _Malformed(f"{what} is not finite")
    return k1


def _parse_graph(raw: Any, estimate: str, label: str, default_k1: float = 0.0) -> ViewGraph:
    if not isinstance(raw, Mapping):
        raise _Malformed(f"graph is a {type(raw).__name__}, expected an object")
    cams = raw.get("cameras")
    if not isinstance(cams, Mapping) or len(cams) < 2:
        raise _Malformed("'cameras' must be an object with at least two cameras")
    ids = [str(k) for k in cams]
    N = len(ids)
    dets = raw.get("detections")
    if not isinstance(dets, Mapping) or "covisibility" not in dets:
        raise _Malformed("'detections.covisibility' is missing")
    if not _is_square(dets["covisibility"], N):
        raise _Malformed(f"covisibility size differs from the camera count ({N})")
    covis = _matrix(dets["covisibility"], (N, N), "'detections.covisibility'")

    c2w, Ks, sizes, paths, k1s = [], [], [], [], []
    no_pose: list[str] = []
    for cid in ids:
        cam = cams[cid]
        if not isinstance(cam, Mapping):
            raise _Malformed(f"camera {cid!r} is not an object")
        if "K" not in cam:
            raise _Malformed(f"camera {cid!r} has no 'K'")
        if cam.get("camera_to_world") is None:
            no_pose.append(cid)
        else:
            c2w.append(_rigid(cam["camera_to_world"], f"camera {cid!r} 'camera_to_world'"))
        k1s.append(_k1(cam, cid, default_k1))
        K = _matrix(cam["K"], (3, 3), f"camera {cid!r} 'K'")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise _Malformed(f"camera {cid!r} 'K' has a non-positive focal length")
        Ks.append(K)
        if "image_size" in cam:
            size = _matrix([cam["image_size"]], (1, 2), f"camera {cid!r} 'image_size'")[0]
        else:
            size = torch.stack((2 * K[0, 2], 2 * K[1, 2]))
        if bool((size <= 0).any()):
            raise _Malformed(f"camera {cid!r} has a non-positive image size")
        sizes.append(size)
        paths.append(str(cam.get("image_path", "")))
    if c2w and no_pose:
        raise _Malformed(f"camera {no_pose[0]!r} has no 'camera_to_world' while other cameras "
                         "have one (give ground-truth poses for every camera or for none)")
    pose_gt = invert_se3(torch.stack(c2w)) if c2w else None
    K = torch.stack(Ks)
    image_size = torch.stack(sizes)

    # Edges: covisible pairs, stored once as (i, j) with i < j in camera order.
    iu, ju = torch.triu_indices(N, N, offset=1)
    keep = covis[iu, ju] > 0.5
    if bool((covis > 0.5).ne((covis > 0.5).T).any()):
        raise _Malformed("'covisibility' is not symmetric")
    src, dst = iu[keep], ju[keep]
    if src.numel() == 0:
        raise _Malformed("no covisible camera pair (graph without edges)")

    rel = raw.get("relative_poses")
    if not isinstance(rel, Mapping):
        raise _Malformed("'relative_poses' is missing")
    names = [k for k in ESTIMATE_KEYS if k != "ground_truth"]
    est: dict[str, list[Tensor]] = {n: [] for n in names}
    gt: list[Tensor | None] = []
    for i, j in zip(src.tolist(), dst.tolist(), strict=True):
        a, b = ids[i], ids[j]
        entry, inverted = _rel_entry(rel, a, b)
        if entry is None:
            raise _Malformed(f"pair ({a}, {b}) is covisible but has no 'relative_poses' entry")
        for n in names:
            if n in entry:
                T = _rigid(entry[n], f"relative_poses[{a}][{b}].{n}")
                est[n].append(invert_se3(T) if inverted else T)
        T_gt = None if pose_gt is None else pose_gt[j] @ invert_se3(pose_gt[i])
        if entry.get("ground_truth") is not None:
            T = _rigid(entry["ground_truth"], f"relative_poses[{a}][{b}].ground_truth")
            T_gt = invert_se3(T) if inverted else T
        gt.append(T_gt)
    E = src.numel()
    estimates = {ESTIMATE_KEYS[n]: _unit_t(matrix_to_pose_vec(torch.stack(v)))
                 for n, v in est.items() if len(v) == E}
    with_gt = [T is not None for T in gt]
    edge_pose_gt = None
    if all(with_gt):
        edge_pose_gt = matrix_to_pose_vec(torch.stack(gt))
        estimates["gt"] = _unit_t(edge_pose_gt)
    elif any(with_gt):
        a, b = ids[int(src[with_gt.index(False)])], ids[int(dst[with_gt.index(False)])]
        raise _Malformed(f"pair ({a}, {b}) has no 'ground_truth' relative pose while other "
                         "pairs have one, and there are no camera poses to derive it from "
                         "(give ground truth for every covisible pair or for none)")
    short = ESTIMATE_KEYS.get(estimate, estimate)
    if short not in estimates:
        missing = _JSON_NAME.get(short, short)
        raise _Malformed(f"a covisible pair is missing its {missing!r} estimate")

    # Detections from the per-camera match lists (they carry the coordinates).
    det_lookup: dict[tuple[int, tuple[float, ...]], int] = {}
    det_node: list[int] = []
    det_xyxy: list[tuple[float, ...]] = []

    def det_id(node: int, box: tuple[float, ...]) -> int:
        key = (node, box)
        if key not in det_lookup:
            det_lookup[key] = len(det_node)
            det_node.append(node)
            det_xyxy.append(box)
        return det_lookup[key]

    pair_edge: list[int] = []
    pair_src: list[int] = []
    pair_dst: list[int] = []
    for e, (i, j) in enumerate(zip(src.tolist(), dst.tolist(), strict=True)):
        matches = cams[ids[i]].get("matches", {}) or {}
        listed = matches.get(ids[j]) if isinstance(matches, Mapping) else None
        swap = False
        if not listed:  # listed only from the other side
            other = cams[ids[j]].get("matches", {}) or {}
            listed = other.get(ids[i]) if isinstance(other, Mapping) else None
            swap = True
        if not listed:
            raise _Malformed(f"pair ({ids[i]}, {ids[j]}) is covisible but has no matches")
        for k, m in enumerate(listed):
            if not isinstance(m, Mapping) or "bb_i" not in m or "bb_f" not in m:
                raise _Malformed(f"match {k} of pair ({ids[i]}, {ids[j]}) lacks bb_i/bb_f")
            bi = _box(m["bb_i"], f"match {k} of pair ({ids[i]}, {ids[j]}) bb_i")
            bf = _box(m["bb_f"], f"match {k} of pair ({ids[i]}, {ids[j]}) bb_f")
            if swap:
                bi, bf = bf, bi
            pair_edge.append(e)
            pair_src.append(det_id(i, bi))
            pair_dst.append(det_id(j, bf))

    det_node_t = torch.tensor(det_node, dtype=torch.long)
    det_box = normalize_boxes(torch.tensor(det_xyxy, dtype=torch.float64),
                              image_size[det_node_t])
    edge_index = torch.stack((src, dst))
    meta: dict[str, Any] = {"name": label, "camera_ids": ids}
    scene = _scene_of(paths)
    if scene is not None:
        meta["scene"] = scene
    seqs = [m.group(1) for p in paths if (m := _SEQ_RE.search(p))]
    if seqs:
        meta["sequences"] = sorted(set(seqs))
    origin = raw.get("origin")
    if isinstance(origin, Mapping) and "file" in origin:
        meta["origin"] = f"{origin.get('file')}#{origin.get('id')}"
    return ViewGraph(
        node_attr=node_attributes(K, image_size, torch.tensor(k1s, dtype=K.dtype)),
        K=K,
        image_size=image_size,
        edge_index=edge_index,
        edge_pose=estimates[short],
        det_box=det_box,
        det_node=det_node_t,
        pair_edge=torch.tensor(pair_edge, dtype=torch.long),
        pair_src=torch.tensor(pair_src, dtype=torch.long),
        pair_dst=torch.tensor(pair_dst, dtype=torch.long),
        edge_pose_gt=edge_pose_gt,
        pose_gt=pose_gt,
        estimates=estimates,
        meta=meta,
    )


def _is_square(value: Any, n: int) -> bool:
    return (isinstance(value, (list, tuple)) and len(value) == n
            and all(isinstance(r, (list, tuple)) and len(r) == n for r in value))


def _rel_entry(rel: Mapping, a: str, b: str) -> tuple[Mapping | None, bool]:
    """The relative-pose entry of pair (a, b) and whether it was stored as (b, a)."""
    fwd = rel.get(a, {})
    if isinstance(fwd, Mapping) and isinstance(fwd.get(b), Mapping):
        return fwd[b], False
    bwd = rel.get(b, {})
    if isinstance(bwd, Mapping) and isinstance(bwd.get(a), Mapping):
        return bwd[a], True
    return None, False


def _unit_t(p: Tensor) -> Tensor:
    t = p[:, 4:]
    return torch.cat((p[:, :4], t / t.norm(dim=-1, keepdim=True).clamp_min(1e-12)), dim=-1)


def _scene_of(paths: Sequence[str]) -> str | None:
    for p in paths:
        m = _SCENE_RE.search(p)
        if m:
            return m.group(1)
    return None


def load_posernet_json(
    path: str | os.PathLike[str],
    split: str = "test",
    estimate: str = "feature_5pt",
    strict: bool = True,
    dtype: torch.dtype = torch.float32,
    default_k1: float = 0.0,
) -> list[ViewGraph]:
    """Read one split of an authors'-format graph file into :class:`ViewGraph`\\ s.

    Args:
        path: the JSON file (e.g. ``eccv_final_objectness_set.json``).
        split: ``"train"`` or ``"test"`` (any top-level list key).
        estimate: initial pose put in ``edge_pose``: ``feature_5pt`` (KP), ``bb_centre_5pt``
            (BB), ``free_keypoint`` or ``ground_truth``; short names ``kp``/``bb``/``free``/``gt``
            work too. Every estimate present for all edges is also kept in ``estimates``.
        strict: raise :class:`GraphValidationError` naming the first malformed graph (True), or
            skip malformed graphs and emit one warning with their count and reasons (False).
        dtype: floating dtype of the returned tensors.
        default_k1: radial distortion assumed for cameras without a ``k1``/``distortion``
            entry (node feature ``k1``; see the module docstring).

    Edge translations in ``edge_pose``/``estimates`` are unit vectors; ``edge_pose_gt`` keeps the
    metric translation. Without ground truth in the file (no ``camera_to_world``, no
    ``ground_truth`` relative poses) ``pose_gt`` and ``edge_pose_gt`` are ``None``. ``meta``
    holds ``name`` (``file:split:index``), ``camera_ids`` and, when an ``image_path`` reveals
    it, the 7-Scenes ``scene``.
    """
    path = Path(path)
    if estimate not in ESTIMATE_KEYS and estimate not in _JSON_NAME:
        raise ValueError(
            f"unknown estimate {estimate!r}; choose one of {sorted(ESTIMATE_KEYS)} "
            f"(or {sorted(_JSON_NAME)})"
        )
    if not path.is_file():
        raise FileNotFoundError(f"graph JSON not found: {path}")
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise GraphValidationError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(data, Mapping):
        raise GraphValidationError(f"{path}: top level must be an object with 'train'/'test'")
    if split not in data:
        raise GraphValidationError(
            f"{path}: no split {split!r}; the file has {sorted(k for k in data if k != 'meta')}"
        )
    raw_graphs = data[split]
    if not isinstance(raw_graphs, list):
        raise GraphValidationError(f"{path}: split {split!r} must be a list of graphs")
    graphs: list[ViewGraph] = []
    skipped: list[str] = []
    for gi, raw in enumerate(raw_graphs):
        label = f"{path.name}:{split}:{gi}"
        try:
            g = _parse_graph(raw, estimate, label, default_k1)
            g.validate(where=f"{path}: {split} graph {gi}")
        except (_Malformed, GraphValidationError) as exc:
            msg = f"{split} graph {gi}: {exc}"
            if strict:
                raise GraphValidationError(f"{path}: {msg}") from None
            skipped.append(msg)
            continue
        graphs.append(g.apply(lambda t: t.to(dtype) if t.is_floating_point() else t))
    if skipped:
        shown = "; ".join(skipped[:3]) + (" ..." if len(skipped) > 3 else "")
        warnings.warn(
            f"{path}: skipped {len(skipped)} of {len(raw_graphs)} malformed graphs ({shown})",
            stacklevel=2,
        )
    return graphs


def _graph_to_json(g: ViewGraph, where: str) -> dict[str, Any]:
    g = g.to("cpu").apply(lambda t: t.double() if t.is_floating_point() else t)
    N = g.num_nodes
    ids = g.meta.get("camera_ids")
    if not (isinstance(ids, list) and len(ids) == N and len(set(map(str, ids))) == N):
        ids = [str(i) for i in range(N)]
    ids = [str(c) for c in ids]
    c2w = None if g.pose_gt is None else invert_se3(g.pose_gt)
    k1 = g.node_attr[:, 3] * REF_K1
    K = g.K
    boxes = denormalize_boxes(g.det_box, g.image_size[g.det_node]).tolist()
    scene = g.meta.get("scene")
    cams: dict[str, Any] = {}
    for n, cid in enumerate(ids):
        cam: dict[str, Any] = {} if c2w is None else {"camera_to_world": c2w[n].tolist()}
        cam.update({
            "K": K[n].tolist(),
            "K_i": torch.linalg.inv(K[n]).tolist(),
            "image_size": g.image_size[n].tolist(),
            "k1": float(k1[n]),
            "matches": {},
        })
        if scene:
            cam["image_path"] = f"{scene}/{g.meta.get('split', 'synthetic')}/{g.name}/{cid}.png"
        cams[cid] = cam
    src, dst = g.edge_index.tolist()
    for e, i, j in zip(g.pair_edge.tolist(), g.pair_src.tolist(), g.pair_dst.tolist(),
                       strict=True):
        a, b = ids[src[e]], ids[dst[e]]
        cams[a]["matches"].setdefault(b, []).append({"bb_i": boxes[i], "bb_f": boxes[j]})
        cams[b]["matches"].setdefault(a, []).append({"bb_i": boxes[j], "bb_f": boxes[i]})
    covis = [[0.0] * N for _ in range(N)]
    rel: dict[str, dict[str, Any]] = {cid: {} for cid in ids}
    # Only estimates the schema has a name for; "gt" is written as ground_truth below.
    estimates = {_JSON_NAME[k]: v for k, v in (dict(g.estimates) or {"kp": g.edge_pose}).items()
                 if k in _JSON_NAME and k != "gt"}
    fwd_mats = {n: pose_vec_to_matrix(v).tolist() for n, v in estimates.items()}
    bwd_mats = {n: pose_vec_to_matrix(invert_pose_vec(v)).tolist() for n, v in estimates.items()}
    gt = g.edge_pose_gt
    if gt is None and g.pose_gt is not None:  # derive it from the absolute poses
        gt = matrix_to_pose_vec(g.pose_gt[dst] @ invert_se3(g.pose_gt[src]))
    if gt is not None:  # no ground truth: none is written (nothing is invented)
        fwd_mats["ground_truth"] = pose_vec_to_matrix(gt).tolist()
        bwd_mats["ground_truth"] = pose_vec_to_matrix(invert_pose_vec(gt)).tolist()
    for e, (i, j) in enumerate(zip(src, dst, strict=True)):
        a, b = ids[i], ids[j]
        covis[i][j] = covis[j][i] = 1.0
        rel[a][b] = {n: m[e] for n, m in fwd_mats.items()}
        rel[b][a] = {n: m[e] for n, m in bwd_mats.items()}
    det_cam = [ids[n] for n in g.det_node.tolist()]
    return {
        "cameras": cams,
        "detections": {
            "detection_bb": boxes,
            "box_matches_sparse": [[i, j] for i, j in zip(g.pair_src.tolist(),
                                                          g.pair_dst.tolist(), strict=True)],
            "detection_cam": det_cam,
            "detection_seq": [g.meta.get("sequence", 0)] * len(det_cam),
            "covisibility": covis,
        },
        "relative_poses": rel,
        "origin": {"file": "posernet", "id": g.name},
    }


def save_posernet_json(
    path: str | os.PathLike[str], splits: Mapping[str, Sequence[ViewGraph]]
) -> Path:
    """Write graphs in the authors' schema, one list per split (e.g. ``train``, ``test``).

    Estimates ``kp``/``bb``/``free`` become ``feature_5pt``/``bb_centre_5pt``/``free_keypoint``;
    a graph without ``estimates`` writes its ``edge_pose`` as ``feature_5pt``. Relative poses and
    matches are written from both sides, as in the released files; cameras gain an
    ``image_size`` and a ``k1`` entry (ignored by readers that do not know them). A graph without
    ground truth is written without ``camera_to_world`` and ``ground_truth`` entries (the
    authors' own reader needs them; :func:`load_posernet_json` does not). Written atomically.
    """
    if not splits:
        raise ValueError(f"{path}: nothing to write (no splits given)")
    out: dict[str, Any] = {}
    for split, graphs in splits.items():
        out[split] = [_graph_to_json(g, f"{split} graph {i} ({g.name!r})")
                      for i, g in enumerate(graphs)]
    return atomic_write_json(path, out, indent=None)

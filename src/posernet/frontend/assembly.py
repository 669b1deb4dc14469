"""View graphs from evaluated image pairs: one assembly for real images and the simulator.

A :class:`PairResult` is what the front end knows about two images ``a < b``: the matched box
pairs and the two 5-point estimates (KP on in-box keypoints, BB on box centres), each mapping
camera a to camera b. :func:`assemble_view_graph` turns a set of images and their pairs into a
:class:`~posernet.graph.ViewGraph`: an edge for every pair with ``status == "edge"``, stored once
as ``a -> b`` in local node order, its matched detections as ``pair_*`` rows, the KP estimate as
``edge_pose`` (both kept in ``estimates``), ground truth when the poses are known.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from ..geometry import invert_pose_vec, make_se3, matrix_to_pose_vec, relative_pose
from ..graph import ViewGraph, node_attributes, normalize_boxes
from ..metrics import relative_pose_errors

__all__ = [
    "PAIR_STATUSES",
    "GraphStats",
    "PairResult",
    "assemble_view_graph",
    "grow_connected",
    "is_connected",
]

PAIR_STATUSES = ("edge", "unmatched", "kp_failed", "bb_failed")


@dataclass
class PairResult:
    """An evaluated image pair ``a < b`` (image ids); poses map camera a to camera b.

    ``box_a, box_b (P,)`` matched detections (indices into each image's boxes), ``wrong (P,)``
    pairs known to be wrong (simulator only). ``status``: ``"edge"``, ``"unmatched"`` (fewer than
    ``min_boxes`` matched boxes), ``"kp_failed"`` or ``"bb_failed"`` (a 5-point estimate failed:
    no edge). ``n_kp`` keypoints fed the KP 5-point (``n_kp_outliers`` of them known wrong).

    The image front end may make an edge from one estimate alone (the one the graph is built
    for): the other is then ``None`` and the graph stores the available one in its place
    (``meta["substituted"]`` counts them). It also records the two-view verification:
    ``reason`` (why a pair is not an edge, or ``""``), ``rotation_only`` (the translation
    direction is meaningless: pure rotation or too small a baseline), ``inliers (I, 2)``
    keypoint index pairs the verified pose explains (for tracks), ``info`` the verification's
    counts and angles.
    """

    a: int
    b: int
    box_a: np.ndarray
    box_b: np.ndarray
    wrong: np.ndarray
    n_kp: int
    n_kp_outliers: int
    kp: tuple[np.ndarray, np.ndarray] | None
    bb: tuple[np.ndarray, np.ndarray] | None
    status: str
    reason: str = ""
    rotation_only: bool = False
    inliers: np.ndarray | None = None
    info: dict = field(default_factory=dict)

    @property
    def is_edge(self) -> bool:
        return self.status == "edge"


@dataclass
class GraphStats:
    """Book-keeping of one graph: pair outcomes among its images and per-graph mean errors."""

    pairs_checked: int = 0
    matched: int = 0  # pairs with >= min_boxes matched boxes
    dropped_kp: int = 0  # matched, but the KP 5-point failed
    dropped_bb: int = 0  # matched, but the BB 5-point failed
    wrong_box_matches: int = 0
    kp_correspondences: int = 0
    kp_outliers: int = 0
    errors: dict[str, float] = field(default_factory=dict)  # kp_rot, kp_tdir, bb_rot, bb_tdir


def is_connected(n: int, edge_index: np.ndarray) -> bool:
    """Whether ``n`` nodes with edges ``(2, E)`` form one component (union-find)."""
    parent = list(range(n))

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for a, b in np.asarray(edge_index).T.tolist():
        parent[find(a)] = find(b)
    return n > 0 and len({find(i) for i in range(n)}) == 1


def grow_connected(
    pool: np.ndarray,
    n: int,
    is_edge: Callable[[int, int], bool],
    rng: np.random.Generator,
    max_tries: int = 200,
    restarts: int = 20,
    locality: float = 0.0,
    window: int = 0,
    sequence: np.ndarray | None = None,
) -> list[int] | None:
    """Image ids of one connected ``n``-image graph drawn from ``pool``, or ``None``.

    Images are added one at a time, each candidate kept only when it has an edge to an image
    already chosen (the paper rejects graphs with isolated nodes or components; growing them
    connected is the same constraint without the waste). Candidates are uniform over the pool,
    or with probability ``locality`` within ``window`` ids of a chosen image of the same
    ``sequence`` (``sequence[id]``, needed then): neighbouring frames of a handheld sequence
    overlap, random ones rarely do. ``max_tries`` failed candidates in a row end an attempt.
    """
    pool = np.asarray(pool)
    in_pool = None
    if locality > 0 and window > 0:
        if sequence is None:
            raise ValueError("grow_connected: locality needs the sequence of every image")
        in_pool = np.zeros(len(sequence), bool)
        in_pool[pool] = True
    for _restart in range(restarts):
        nodes = [int(pool[rng.integers(pool.size)])]
        chosen = set(nodes)
        tries = 0
        while len(nodes) < n and tries < max_tries:
            tries += 1
            if in_pool is not None and rng.random() < locality:
                u = nodes[int(rng.integers(len(nodes)))]
                v = u + int(rng.integers(-window, window + 1))
                if not (0 <= v < in_pool.size and sequence[v] == sequence[u] and in_pool[v]):
                    continue
            else:
                v = int(pool[rng.integers(pool.size)])
            if v in chosen:
                continue
            if any(is_edge(u, v) for u in nodes):
                nodes.append(v)
                chosen.add(v)
                tries = 0
        if len(nodes) == n:
            return nodes
    return None


def _pose_vecs(poses: list[tuple[np.ndarray, np.ndarray]], forward: list[bool]) -> Tensor:
    """Pose vectors ``(E, 7)`` of ``(R, t)`` estimates (min id -> max id), inverted where the
    edge is stored the other way round (``forward`` False)."""
    if not poses:
        return torch.zeros(0, 7, dtype=torch.float64)
    R = torch.from_numpy(np.stack([np.asarray(r, np.float64) for r, _ in poses]))
    t = torch.from_numpy(np.stack([np.asarray(t, np.float64).reshape(3) for _, t in poses]))
    p = matrix_to_pose_vec(make_se3(R, t))
    fwd = torch.tensor(forward)
    return torch.where(fwd[:, None], p, invert_pose_vec(p))


def assemble_view_graph(
    nodes: Sequence[int],
    pair: Callable[[int, int], PairResult],
    boxes: Sequence[np.ndarray],
    K: np.ndarray,
    image_size: np.ndarray,
    k1: float | np.ndarray = 0.0,
    w2c: np.ndarray | None = None,
    meta: dict | None = None,
    candidates: Iterable[tuple[int, int]] | None = None,
) -> tuple[ViewGraph, GraphStats]:
    """Evaluate every pair of ``nodes`` (image ids) with ``pair`` and assemble the graph.

    Args:
        nodes: image ids, in the graph's node order.
        pair: ``pair(u, v)`` -> the :class:`PairResult` of images ``min(u, v) < max(u, v)``.
        boxes: per node, its detections as pixel xyxy ``(B_n, 4)``.
        K: intrinsics ``(3, 3)`` shared, or ``(N, 3, 3)`` per node.
        image_size: ``(2,)`` shared or ``(N, 2)`` per node, as (W, H).
        k1: first radial distortion coefficient, scalar or ``(N,)``.
        w2c: ground-truth world-to-camera poses ``(N, 4, 4)``, or ``None`` (no ground truth).
        meta: graph metadata (``name``, ``scene``, ...).
        candidates: only these node-index pairs ``(a, b)`` (a selected subset of pairs, e.g.
            by retrieval among many images); ``None``: every pair.

    Returns the graph (float32; unit translations renormalised) and its statistics.
    """
    n = len(nodes)
    stats = GraphStats()
    src, dst, results = [], [], []
    todo = (itertools.combinations(range(n), 2) if candidates is None
            else sorted({(min(a, b), max(a, b)) for a, b in candidates if a != b}))
    for a, b in todo:
        fa, fb = nodes[a], nodes[b]
        stats.pairs_checked += 1
        r = pair(fa, fb)
        if r.status != "unmatched":
            stats.matched += 1
            stats.dropped_kp += r.status == "kp_failed"
            stats.dropped_bb += r.status == "bb_failed"
        if r.is_edge:
            src.append(a)
            dst.append(b)
            results.append(r)

    # detections of every image, concatenated
    offsets = np.cumsum([0] + [b.shape[0] for b in boxes])
    all_boxes = np.concatenate(list(boxes)) if offsets[-1] else np.zeros((0, 4))
    det_node = np.repeat(np.arange(n), np.diff(offsets))

    pe, ps, pd, forward = [], [], [], []
    for e, (a, b, r) in enumerate(zip(src, dst, results, strict=True)):
        fwd = nodes[a] < nodes[b]  # the pair result maps min id -> max id
        box_a, box_b = (r.box_a, r.box_b) if fwd else (r.box_b, r.box_a)
        pe.append(np.full(box_a.size, e))
        ps.append(box_a + offsets[a])
        pd.append(box_b + offsets[b])
        forward.append(fwd)
        stats.wrong_box_matches += int(r.wrong.sum())
        stats.kp_correspondences += r.n_kp
        stats.kp_outliers += r.n_kp_outliers

    ei = torch.tensor([src, dst], dtype=torch.long).reshape(2, -1)
    # an edge made from one estimate alone carries it in the other's place too
    has = {"kp": [r.kp is not None for r in results], "bb": [r.bb is not None for r in results]}
    est_kp = _pose_vecs([r.kp if r.kp is not None else r.bb for r in results], forward)
    est_bb = _pose_vecs([r.bb if r.bb is not None else r.kp for r in results], forward)
    pose_gt = gt = None
    if w2c is not None:
        pose_gt = torch.from_numpy(np.asarray(w2c, dtype=np.float64))  # (N, 4, 4)
        gt = matrix_to_pose_vec(relative_pose(pose_gt[ei[0]], pose_gt[ei[1]]))
        if est_kp.shape[0]:
            for name, est in (("kp", est_kp), ("bb", est_bb)):
                own = torch.tensor(has[name], dtype=torch.bool)
                if not bool(own.any()):
                    continue
                rot, tdir = relative_pose_errors(est[own], gt[own])
                stats.errors[f"{name}_rot"] = float(rot.mean())
                stats.errors[f"{name}_tdir"] = float(tdir.mean())
    Kt = torch.from_numpy(np.asarray(K, dtype=np.float64))
    Kt = Kt.expand(n, 3, 3).clone() if Kt.dim() == 2 else Kt
    size = torch.as_tensor(np.asarray(image_size, dtype=np.float64))
    sizes = size.expand(n, 2).clone() if size.dim() == 1 else size
    cat = (
        (lambda xs: torch.from_numpy(np.concatenate(xs)).long())
        if pe
        else (lambda xs: torch.zeros(0, dtype=torch.long))
    )
    det_size = sizes[torch.from_numpy(det_node)] if size.dim() == 2 else size.expand(
        all_boxes.shape[0], 2)
    det_box = normalize_boxes(torch.from_numpy(all_boxes), det_size)
    meta = dict(meta or {})
    meta.update(num_dropped_kp=stats.dropped_kp, num_dropped_bb=stats.dropped_bb)
    missing = {k: len(v) - sum(v) for k, v in has.items() if len(v) - sum(v)}
    if missing:
        meta["substituted"] = missing
    k1t = torch.as_tensor(np.asarray(k1, dtype=np.float64)) if np.ndim(k1) else float(k1)
    g = ViewGraph(
        node_attr=node_attributes(Kt, sizes, k1t),
        K=Kt,
        image_size=sizes,
        edge_index=ei,
        edge_pose=est_kp,
        det_box=det_box,
        det_node=torch.from_numpy(det_node).long(),
        pair_edge=cat(pe),
        pair_src=cat(ps),
        pair_dst=cat(pd),
        edge_pose_gt=gt,
        pose_gt=pose_gt,
        estimates={"kp": est_kp, "bb": est_bb},
        meta=meta,
    )
    g = g.apply(lambda x: x.float() if x.is_floating_point() else x)
    # unit translations survive the float cast only approximately; renormalise
    for k, v in g.estimates.items():
        v[:, 4:] = torch.nn.functional.normalize(v[:, 4:], dim=-1)
        g.estimates[k] = v
    g.edge_pose = g.estimates["kp"]
    return g, stats

"""Sample view graphs from a simulated scene and assemble them as :class:`ViewGraph`.

* Small graphs (paper: 8 images) must form one connected view graph: images are added one at a
  time, each candidate kept only when it has an edge to an image already in the graph (the
  paper rejects graphs with isolated nodes or components; growing them connected is the same
  constraint without the waste).
* Large graphs (paper: 125 images) are a random set of images without that constraint.

An edge exists when two images share at least ``min_boxes`` matched boxes and both 5-point
estimates (KP and BB) succeeded; pairs that matched but lost an estimate are counted as dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from ...geometry import invert_pose_vec, make_se3, matrix_to_pose_vec, relative_pose
from ...graph import ViewGraph, node_attributes, normalize_boxes
from ...metrics import relative_pose_errors
from .matching import is_connected
from .world import PairResult, SceneWorld

__all__ = ["GraphStats", "SamplingError", "build_view_graph", "sample_large", "sample_small"]


class SamplingError(RuntimeError):
    """The scene cannot provide the requested graphs (too few images or connections)."""


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


def _pool_of(world: SceneWorld, split: str, need: int) -> np.ndarray:
    pool = world.pools[split].frames
    if pool.size < need:
        raise SamplingError(
            f"scene {world.scene_name!r} split {split!r} has {pool.size} images, fewer than the "
            f"{need} a graph needs; raise dataset.sequences.frames_per_sequence or lower the "
            f"graph size"
        )
    return pool


def sample_small(
    world: SceneWorld,
    split: str,
    n: int,
    rng: np.random.Generator,
    locality: float = 0.0,
    window: int = 0,
) -> list[int]:
    """Frame ids of one connected ``n``-image graph from the ``split`` pool.

    Candidates are uniform over the pool, or with probability ``locality`` within ``window``
    frames of an image already chosen (same sequence): short baselines, as when a handheld
    camera pans. Raises :class:`SamplingError` when the pool cannot give a connected graph.
    """
    pool = _pool_of(world, split, n)
    seq = world.frame_sequence
    in_pool = np.zeros(world.num_frames, bool)
    in_pool[pool] = True
    max_tries = world.options.max_tries_per_node
    for _restart in range(20):
        nodes = [int(pool[rng.integers(pool.size)])]
        chosen = set(nodes)
        tries = 0
        while len(nodes) < n and tries < max_tries:
            tries += 1
            if locality > 0 and window > 0 and rng.random() < locality:
                u = nodes[int(rng.integers(len(nodes)))]
                v = u + int(rng.integers(-window, window + 1))
                if not (0 <= v < seq.size and seq[v] == seq[u] and in_pool[v]):
                    continue
            else:
                v = int(pool[rng.integers(pool.size)])
            if v in chosen:
                continue
            if any(world.pair(u, v).is_edge for u in nodes):
                nodes.append(v)
                chosen.add(v)
                tries = 0
        if len(nodes) == n:
            return nodes
    raise SamplingError(
        f"could not grow a connected {n}-image graph in scene {world.scene_name!r} split "
        f"{split!r} ({max_tries} candidates per image, 20 restarts): too few image pairs share "
        f"{world.options.matching.min_boxes} matched boxes; lower dataset.small.graph_size or "
        f"dataset.matching.min_boxes, or raise dataset.keypoints.density"
    )


def sample_large(world: SceneWorld, split: str, n: int, rng: np.random.Generator) -> list[int]:
    """Frame ids of ``n`` random images of the ``split`` pool (no connectivity constraint)."""
    pool = _pool_of(world, split, n)
    return [int(v) for v in rng.choice(pool, size=n, replace=False)]


def _pose_vecs(poses: list[tuple[np.ndarray, np.ndarray]], forward: list[bool]) -> torch.Tensor:
    """Pose vectors ``(E, 7)`` of ``(R, t)`` estimates (min frame -> max frame), inverted where
    the edge is stored the other way round (``forward`` False)."""
    if not poses:
        return torch.zeros(0, 7, dtype=torch.float64)
    R = torch.from_numpy(np.stack([r for r, _ in poses]))
    t = torch.from_numpy(np.stack([t for _, t in poses]))
    p = matrix_to_pose_vec(make_se3(R, t))
    fwd = torch.tensor(forward)
    return torch.where(fwd[:, None], p, invert_pose_vec(p))


def build_view_graph(
    world: SceneWorld, nodes: list[int], meta: dict
) -> tuple[ViewGraph, GraphStats]:
    """Evaluate every pair of ``nodes`` (frame ids) and assemble the graph.

    Edges are stored once as ``a -> b`` with ``a < b`` in local node order; the cached pair
    result is inverted when its frames come in the other order. Returns the graph (float32) and
    its statistics.
    """
    n = len(nodes)
    cam = world.options.camera
    stats = GraphStats()
    src, dst, results = [], [], []
    for a in range(n):
        for b in range(a + 1, n):
            fa, fb = nodes[a], nodes[b]
            stats.pairs_checked += 1
            r: PairResult = world.pair(fa, fb)
            if r.status != "unmatched":
                stats.matched += 1
                stats.dropped_kp += r.status == "kp_failed"
                stats.dropped_bb += r.status == "bb_failed"
            if r.is_edge:
                src.append(a)
                dst.append(b)
                results.append(r)

    # detections of every image, concatenated
    frames = [world.frame(f) for f in nodes]
    offsets = np.cumsum([0] + [f.det.boxes.shape[0] for f in frames])
    boxes = np.concatenate([f.det.boxes for f in frames]) if offsets[-1] else np.zeros((0, 4))
    det_node = np.repeat(np.arange(n), np.diff(offsets))

    pe, ps, pd, forward = [], [], [], []
    for e, (a, b, r) in enumerate(zip(src, dst, results, strict=True)):
        fwd = nodes[a] < nodes[b]  # the pair result maps min frame -> max frame
        box_a, box_b = (r.box_a, r.box_b) if fwd else (r.box_b, r.box_a)
        pe.append(np.full(box_a.size, e))
        ps.append(box_a + offsets[a])
        pd.append(box_b + offsets[b])
        forward.append(fwd)
        stats.wrong_box_matches += int(r.wrong.sum())
        stats.kp_correspondences += r.n_kp
        stats.kp_outliers += r.n_kp_outliers

    pose_gt = torch.from_numpy(world.w2c[nodes])  # float64 (N, 4, 4)
    ei = torch.tensor([src, dst], dtype=torch.long).reshape(2, -1)
    gt = matrix_to_pose_vec(relative_pose(pose_gt[ei[0]], pose_gt[ei[1]]))
    est_kp = _pose_vecs([r.kp for r in results], forward)
    est_bb = _pose_vecs([r.bb for r in results], forward)
    if est_kp.shape[0]:
        for name, est in (("kp", est_kp), ("bb", est_bb)):
            rot, tdir = relative_pose_errors(est, gt)
            stats.errors[f"{name}_rot"] = float(rot.mean())
            stats.errors[f"{name}_tdir"] = float(tdir.mean())
    K = torch.from_numpy(world.K).expand(n, 3, 3).clone()
    size = torch.tensor([float(cam.width), float(cam.height)], dtype=torch.float64)
    image_size = size.expand(n, 2).clone()
    cat = (
        (lambda xs: torch.from_numpy(np.concatenate(xs)).long())
        if pe
        else (lambda xs: torch.zeros(0, dtype=torch.long))
    )
    det_box = normalize_boxes(torch.from_numpy(boxes), size.expand(boxes.shape[0], 2))
    meta = dict(meta)
    meta.update(
        num_dropped_kp=stats.dropped_kp,
        num_dropped_bb=stats.dropped_bb,
        frames=",".join(str(f) for f in nodes),
    )
    g = ViewGraph(
        node_attr=node_attributes(K, image_size, cam.k1),
        K=K,
        image_size=image_size,
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
    if meta.get("size") == "small" and not is_connected(n, ei.numpy()):
        raise SamplingError(f"graph {meta.get('name')!r} is not connected")  # cannot happen
    return g, stats

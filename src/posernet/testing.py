"""Small random view graphs for tests, examples and benchmarks (no simulator needed).

These graphs satisfy the data contract and have consistent ground truth (relative poses derived
from random absolute poses) but their detections are random boxes, not projections of a scene:
use :mod:`posernet.data.synthetic` for realistic data.
"""

from __future__ import annotations

import itertools
import json
import os
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from .geometry import (
    axis_angle_to_rotation_matrix,
    compose_pose_vec,
    make_se3,
    matrix_to_pose_vec,
    relative_pose,
)
from .graph import ViewGraph, node_attributes

__all__ = ["random_absolute_poses", "random_edges", "random_view_graph", "write_random_dataset"]


def random_absolute_poses(n: int, generator: torch.Generator | None = None,
                          dtype: torch.dtype = torch.float32, radius: float = 2.0) -> Tensor:
    """``n`` world-to-camera poses (n, 4, 4): cameras on a sphere-ish shell, random orientation."""
    R = axis_angle_to_rotation_matrix(
        torch.randn(n, 3, generator=generator, dtype=torch.float64) * 1.5
    )
    centres = torch.randn(n, 3, generator=generator, dtype=torch.float64) * radius
    t = -(R @ centres[..., None]).squeeze(-1)
    return make_se3(R, t).to(dtype)


def random_edges(n: int, extra: int, generator: torch.Generator | None = None) -> Tensor:
    """Connected edge set (2, E): a random spanning chain plus ``extra`` distinct random pairs."""
    perm = torch.randperm(n, generator=generator)
    pairs = {(int(min(a, b)), int(max(a, b))) for a, b in itertools.pairwise(perm)}
    max_pairs = n * (n - 1) // 2
    target = min(max_pairs, len(pairs) + extra)
    while len(pairs) < target:
        a, b = torch.randint(0, n, (2,), generator=generator).tolist()
        if a != b:
            pairs.add((min(a, b), max(a, b)))
    ei = torch.tensor(sorted(pairs), dtype=torch.long).T
    # Random stored direction: the model must not depend on which way a pair is stored.
    flip = torch.rand(ei.shape[1], generator=generator) < 0.5
    return torch.where(flip, ei.flip(0), ei)


def random_view_graph(
    num_nodes: int = 8,
    extra_edges: int = 6,
    pairs_per_edge: tuple[int, int] = (1, 8),
    dets_per_node: int = 12,
    rot_noise_deg: float = 10.0,
    trans_noise: float = 0.3,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    name: str = "random",
    edge_index: Tensor | None = None,
) -> ViewGraph:
    """A valid random :class:`ViewGraph` with ground truth and noisy initial poses.

    Initial poses are the ground truth perturbed by a random rotation of up to ``rot_noise_deg``
    and a translation perturbation, then given unit translation (as from the 5-point algorithm).
    ``edge_index [2, E]``: the edges to use (e.g. a sequence's neighbours); random ones
    (:func:`random_edges`, ``extra_edges`` beyond a spanning tree) when None.
    """
    g = generator
    pose_gt = random_absolute_poses(num_nodes, g, torch.float64)
    if edge_index is None:
        edge_index = random_edges(num_nodes, extra_edges, g)
    E = edge_index.shape[1]
    gt = matrix_to_pose_vec(relative_pose(pose_gt[edge_index[0]], pose_gt[edge_index[1]]))
    axis = torch.randn(E, 3, generator=g, dtype=torch.float64)
    axis = torch.nn.functional.normalize(axis, dim=-1)
    ang = torch.deg2rad(torch.rand(E, 1, generator=g, dtype=torch.float64) * rot_noise_deg)
    noise_q = matrix_to_pose_vec(make_se3(axis_angle_to_rotation_matrix(axis * ang),
                                          torch.zeros(E, 3, dtype=torch.float64)))
    init = compose_pose_vec(noise_q, gt)
    t = init[:, 4:] + trans_noise * torch.randn(E, 3, generator=g, dtype=torch.float64) * \
        gt[:, 4:].norm(dim=-1, keepdim=True)
    init = torch.cat((init[:, :4], torch.nn.functional.normalize(t, dim=-1)), dim=-1)

    D = num_nodes * dets_per_node
    det_node = torch.arange(num_nodes).repeat_interleave(dets_per_node)
    wh = 0.05 + 0.3 * torch.rand(D, 2, generator=g, dtype=torch.float64)
    c = (torch.rand(D, 2, generator=g, dtype=torch.float64) * 2 - 1) * (1 - wh)
    det_box = torch.cat((c, wh), dim=-1)

    lo, hi = pairs_per_edge
    counts = torch.randint(lo, hi + 1, (E,), generator=g)
    pair_edge = torch.arange(E).repeat_interleave(counts)
    local_s = torch.randint(0, dets_per_node, (pair_edge.numel(),), generator=g)
    local_d = torch.randint(0, dets_per_node, (pair_edge.numel(),), generator=g)
    pair_src = edge_index[0, pair_edge] * dets_per_node + local_s
    pair_dst = edge_index[1, pair_edge] * dets_per_node + local_d

    K = torch.tensor([[585.0, 0, 320.0], [0, 585.0, 240.0], [0, 0, 1]], dtype=torch.float64)
    K = K.expand(num_nodes, 3, 3).clone()
    image_size = torch.tensor([640.0, 480.0], dtype=torch.float64).expand(num_nodes, 2).clone()
    graph = ViewGraph(
        node_attr=node_attributes(K, image_size),
        K=K,
        image_size=image_size,
        edge_index=edge_index,
        edge_pose=init,
        det_box=det_box,
        det_node=det_node,
        pair_edge=pair_edge,
        pair_src=pair_src,
        pair_dst=pair_dst,
        edge_pose_gt=gt,
        pose_gt=pose_gt,
        meta={"name": name},
    )
    return graph.apply(lambda x: x.to(dtype) if x.is_floating_point() else x)


def write_random_dataset(root: str | os.PathLike[str], per_scene: dict[str, int],
                         scenes: tuple[str, ...] = ("chess", "fire"), seed: int = 0,
                         **graph_kwargs: Any) -> Path:
    """A small dataset of :func:`random_view_graph` graphs in ``posernet-make-data``'s layout:
    ``ROOT/manifest.json`` + ``ROOT/small/<split>/<scene>.pt`` with ``kp``/``bb`` estimates;
    ``per_scene`` maps a split to its number of graphs per scene."""
    from .graph import save_graphs

    root = Path(root)
    gen = torch.Generator().manual_seed(seed)
    counts: dict[str, dict[str, int]] = {}
    for split, n in per_scene.items():
        for scene in scenes:
            gs = []
            for i in range(n):
                g = random_view_graph(extra_edges=5, pairs_per_edge=(2, 5), generator=gen,
                                      name=f"{scene}/{split}/{i}", **graph_kwargs)
                g.estimates = {"kp": g.edge_pose, "bb": g.edge_pose.clone()}
                g.meta.update(scene=scene, split=split)
                gs.append(g)
            save_graphs(root / "small" / split / f"{scene}.pt", gs)
            counts.setdefault(split, {})[scene] = n
    manifest = {"name": "test", "splits": {"small": {s: list(scenes) for s in counts}},
                "counts": {"small": counts}}
    (root / "manifest.json").write_text(json.dumps(manifest))
    return root

"""Training on a mixture of initial-pose qualities (input-adaptive refinement).

A network trained on one input distribution (KP) learns that distribution's error floor and
maps every input onto it: ground-truth input comes out ~8 degrees off. Training on inputs whose
quality ranges from exact to very poor teaches it to keep good poses and fix bad ones. Each
training graph, every time it is drawn, gets its ``edge_pose`` from the sources

* ``kp`` / ``bb``: the stored estimates (if the dataset has them),
* ``gt``: the ground truth (unit translation) rotated by a small random angle, uniform in
  ``[0, gt_noise_deg]`` for the rotation and ``[0, 2 * gt_noise_deg]`` for the direction,
* ``recorrupt``: the ground truth re-corrupted with a fresh large perturbation, uniform in
  ``[0, recorrupt_deg]`` (rotation) and ``[0, 90]`` degrees (direction),

chosen per graph (all edges from one source) with probability ``1 - edge_fraction`` and per
edge otherwise, so the network sees homogeneous graphs (as users give them) and graphs whose
edges differ in quality (where cycle consistency tells them apart). Draws are seeded by
``(seed, graph index, visit count)``: reproducible, and new in every epoch.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor
from torch.utils.data import Dataset

from ..geometry import (
    axis_angle_to_rotation_matrix,
    quaternion_canonical,
    quaternion_multiply,
    quaternion_normalize,
    quaternion_rotate,
    rotation_matrix_to_quaternion,
)
from ..graph import ViewGraph

__all__ = ["SOURCES", "MixedInitDataset", "check_mixture", "perturb_poses"]

SOURCES = ("kp", "bb", "gt", "recorrupt")


def check_mixture(mix: Mapping[str, Any]) -> dict[str, float]:
    """Validate ``data.init_mix`` (source -> non-negative weight); returns normalised floats."""
    if not isinstance(mix, Mapping) or not mix:
        raise ValueError(f"init_mix must be a non-empty mapping of {list(SOURCES)} to weights, "
                         f"got {mix!r}")
    bad = [k for k in mix if k not in SOURCES]
    if bad:
        raise ValueError(f"init_mix: unknown source(s) {bad}; known: {list(SOURCES)}")
    w = {str(k): float(v) for k, v in mix.items()}
    if any(not math.isfinite(v) or v < 0 for v in w.values()) or sum(w.values()) <= 0:
        raise ValueError(f"init_mix weights must be finite, >= 0 and not all 0, got {w}")
    total = sum(w.values())
    return {k: v / total for k, v in w.items() if v > 0}


def _random_rotation(angle: Tensor, gen: torch.Generator) -> Tensor:
    """Unit quaternions ``[E, 4]`` of rotations by ``angle [E]`` (radians) about random axes."""
    axis = torch.randn(angle.shape[0], 3, generator=gen, dtype=angle.dtype)
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return rotation_matrix_to_quaternion(axis_angle_to_rotation_matrix(axis * angle[:, None]))


def perturb_poses(gt: Tensor, rot_deg: Tensor, dir_deg: Tensor, gen: torch.Generator) -> Tensor:
    """Ground-truth poses ``[E, 7]`` with rotations perturbed by ``rot_deg [E]`` and unit
    translation directions by ``dir_deg [E]`` (degrees, random axes). Returns ``[E, 7]``."""
    dt = gt.dtype
    q = quaternion_multiply(_random_rotation(torch.deg2rad(rot_deg.to(dt)), gen),
                            quaternion_normalize(gt[:, :4]))
    t = gt[:, 4:] / gt[:, 4:].norm(dim=-1, keepdim=True).clamp_min(1e-12)
    t = quaternion_rotate(_random_rotation(torch.deg2rad(dir_deg.to(dt)), gen), t)
    return torch.cat((quaternion_canonical(q), t), dim=-1)


class MixedInitDataset(Dataset):
    """Training graphs whose ``edge_pose`` is redrawn from a mixture of sources on each visit.

    Args:
        graphs: the training graphs (with ``edge_pose_gt`` and their stored ``estimates``).
        mix: source -> weight (:data:`SOURCES`; normalised).
        gt_noise_deg: largest rotation perturbation of the ``gt`` source (degrees).
        recorrupt_deg: largest rotation perturbation of the ``recorrupt`` source (degrees).
        edge_fraction: chance that a graph mixes sources per edge instead of per graph.
        seed: base seed of the draws.
    """

    def __init__(self, graphs: Sequence[ViewGraph], mix: Mapping[str, Any],
                 gt_noise_deg: float = 3.0, recorrupt_deg: float = 60.0,
                 edge_fraction: float = 0.5, seed: int = 0) -> None:
        self.graphs = list(graphs)
        self.mix = check_mixture(mix)
        for name, v in (("gt_noise_deg", gt_noise_deg), ("recorrupt_deg", recorrupt_deg)):
            if not math.isfinite(float(v)) or float(v) < 0:
                raise ValueError(f"{name} must be a finite angle >= 0, got {v!r}")
        if not 0.0 <= float(edge_fraction) <= 1.0:
            raise ValueError(f"edge_fraction must lie in [0, 1], got {edge_fraction!r}")
        for g in self.graphs:
            if g.edge_pose_gt is None:
                raise ValueError(f"init_mix needs ground truth: graph {g.name!r} has no "
                                 "edge_pose_gt")
            missing = [s for s in self.mix if s in ("kp", "bb") and s not in g.estimates]
            if missing:
                raise ValueError(f"init_mix uses {missing} but graph {g.name!r} has only the "
                                 f"estimates {sorted(g.estimates)}")
        self.gt_noise_deg, self.recorrupt_deg = float(gt_noise_deg), float(recorrupt_deg)
        self.edge_fraction, self.seed = float(edge_fraction), int(seed)
        self.names = list(self.mix)
        self.probs = torch.tensor([self.mix[k] for k in self.names], dtype=torch.float64)
        self._visits = [0] * len(self.graphs)

    def __len__(self) -> int:
        return len(self.graphs)

    def __getitem__(self, idx: int) -> ViewGraph:
        g = self.graphs[idx]
        visit = self._visits[idx]
        self._visits[idx] += 1
        gen = torch.Generator().manual_seed(
            (self.seed * 1_000_003 + idx) * 1_000_003 + visit)
        return dataclasses.replace(g, edge_pose=self.draw(g, gen))

    def draw(self, g: ViewGraph, gen: torch.Generator) -> Tensor:
        """A mixed initial pose ``[E, 7]`` for graph ``g``."""
        assert g.edge_pose_gt is not None
        E = g.num_edges
        gt = g.edge_pose_gt
        if float(torch.rand((), generator=gen)) < self.edge_fraction:
            choice = torch.multinomial(self.probs, E, replacement=True, generator=gen)
        else:
            choice = torch.multinomial(self.probs, 1, generator=gen).expand(E)
        cands = []
        for name in self.names:  # one candidate tensor per source (a handful), not per edge
            if name in ("kp", "bb"):
                cands.append(g.estimates[name].to(gt.dtype))
            elif name == "gt":
                scale = float(torch.rand((), generator=gen)) * self.gt_noise_deg
                rot = torch.rand(E, generator=gen, dtype=gt.dtype) * scale
                cands.append(perturb_poses(gt, rot, 2.0 * rot, gen))
            else:
                rot = torch.rand(E, generator=gen, dtype=gt.dtype) * self.recorrupt_deg
                tdir = torch.rand(E, generator=gen, dtype=gt.dtype) * 90.0
                cands.append(perturb_poses(gt, rot, tdir, gen))
        stack = torch.stack(cands)  # [S, E, 7]
        return stack[choice, torch.arange(E)]

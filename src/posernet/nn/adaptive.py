"""Input-adaptive refinement: cycle consistency, a per-edge gate and confidence.

PoserNet as published *regresses* every edge pose: it maps good and bad inputs alike to its own
error floor. The pieces here let a network know when to leave a pose alone and say how sure it
is, without changing the message-passing round (:mod:`posernet.nn.conv`):

* :func:`cycle_features`: ground-truth-free consistency of each edge's rotation with the
  two-edge paths ``i -> k -> j`` of its graph (triangles). Good inputs are cycle consistent,
  bad ones are not, whatever the scene; the network reads it as its initial hidden edge state.
* :class:`EdgeHead`: one small MLP per edge on direction-invariant features (input/output
  agreement, cycle consistency of input and output, matched-pair statistics) that predicts a
  gate ``g`` in (0, 1) between the input pose (``g = 0``) and the network's prediction
  (``g = 1``), and four heteroscedastic error scales (radians): the expected rotation and
  direction error of the output, and of the input.
* :func:`heteroscedastic_nll`: the proper scoring rule the scales are trained with,
  ``e / s + log s`` (a Laplace negative log-likelihood), whose minimum over ``s`` is at
  ``s = e``.
* :func:`blend_poses`: the gated pose.

Everything is vectorised over edges (no Python loop over edges or graphs).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn

from ..geometry import (
    angle_between_vectors,
    quaternion_angle,
    quaternion_canonical,
    quaternion_conjugate,
    quaternion_multiply,
    quaternion_normalize,
)
from ..scatter import scatter_count, scatter_mean, scatter_sum
from .mlp import MLP

__all__ = [
    "CONFIDENCE_NAMES",
    "CYCLE_DIM",
    "HEAD_IN_DIM",
    "AdaptiveOutput",
    "EdgeHead",
    "blend_poses",
    "cycle_features",
    "edge_errors",
    "heteroscedastic_nll",
    "pair_stats",
]

#: size of :func:`cycle_features` per edge: mean and min triangle discrepancy (radians), and
#: whether the edge lies on any triangle
CYCLE_DIM = 3
#: the four error scales of :class:`EdgeHead`, in this order (radians inside the network)
CONFIDENCE_NAMES = ("rot_out", "tdir_out", "rot_in", "tdir_in")
#: the smallest error scale the head can predict (radians, about 0.06 degrees): keeps the
#: likelihood finite on exact inputs
SIGMA_FLOOR = 1e-3


class AdaptiveOutput(NamedTuple):
    """What an adaptive PoserNet returns with ``return_extras=True``.

    ``pose [E, 7]`` the final (gated) pose; ``raw [E, 7]`` the message-passing prediction
    before the gate; ``gate [E, 2]`` (rotation, direction) in (0, 1) (``None`` without a
    gate); ``sigma [E, 4]`` the error scales in radians in :data:`CONFIDENCE_NAMES` order
    (``None`` without confidence).
    """

    pose: Tensor
    raw: Tensor
    gate: Tensor | None
    sigma: Tensor | None


# --------------------------------------------------------------------------- cycle consistency


def cycle_features(edge_index: Tensor, edge_pose: Tensor, num_nodes: int) -> Tensor:
    """Rotation cycle consistency of every edge over the triangles it closes.

    For edge ``e = i -> j`` with rotation ``q_e`` and every node ``k`` joined to both ends, the
    discrepancy is the angle of ``q_e^* (q_kj q_ik)`` (0 for consistent poses, either stored
    direction of the two other edges). All two-edge paths are enumerated by a join on the
    directed views (cost ``sum_k deg(k)^2``), never a dense ``N x N`` matrix.

    Shapes: ``edge_index [2, E]`` (long), ``edge_pose [E, 7]`` -> ``[E, 3]``: mean and min
    discrepancy in radians (0 where the edge is on no triangle) and the 0/1 flag "on a
    triangle". No gradient flows (a feature, not a loss).
    """
    if edge_index.ndim != 2 or edge_index.shape[0] != 2:
        raise ValueError(f"cycle_features: edge_index must be [2, E], got "
                         f"{tuple(edge_index.shape)}")
    E = edge_index.shape[1]
    if edge_pose.shape != (E, 7):
        raise ValueError(f"cycle_features: edge_pose must be [E, 7] = [{E}, 7], got "
                         f"{tuple(edge_pose.shape)}")
    dev, dt = edge_pose.device, edge_pose.dtype
    out = torch.zeros(E, CYCLE_DIM, dtype=dt, device=dev)
    if E == 0:
        return out
    with torch.no_grad():
        q = quaternion_normalize(edge_pose[:, :4].detach())
        # directed views: v < E is i -> j as stored, v >= E the reverse (conjugate rotation)
        src = torch.cat((edge_index[0], edge_index[1]))
        dst = torch.cat((edge_index[1], edge_index[0]))
        qv = torch.cat((q, quaternion_conjugate(q)))
        V = 2 * E
        order = torch.argsort(src, stable=True)
        deg = scatter_count(src, num_nodes)
        start = torch.cumsum(deg, 0) - deg
        # every path a = (i -> k) followed by b = (k -> j)
        n_next = deg[dst]  # [V] views leaving each view's end
        a = torch.repeat_interleave(torch.arange(V, device=dev), n_next)
        if a.numel() == 0:
            return out
        first = torch.repeat_interleave(torch.cumsum(n_next, 0) - n_next, n_next)
        b = order[start[dst[a]] + torch.arange(a.numel(), device=dev) - first]
        i, j = src[a], dst[b]
        keep = i != j
        a, b, i, j = a[keep], b[keep], i[keep], j[keep]
        # the view c = (i -> j) closing the triangle, if the graph has it
        key = src * num_nodes + dst
        sorted_key, key_order = torch.sort(key)
        want = i * num_nodes + j
        pos = torch.searchsorted(sorted_key, want).clamp_max(V - 1)
        found = sorted_key[pos] == want
        c = key_order[pos][found]
        a, b = a[found], b[found]
        if c.numel() == 0:
            return out
        path = quaternion_multiply(qv[b], qv[a])
        d = quaternion_multiply(quaternion_conjugate(qv[c]), path)
        ang = 2.0 * torch.atan2(d[:, 1:].norm(dim=-1), d[:, 0].abs())
        e = c % E  # both views of an edge share its features
        out[:, 0] = scatter_mean(ang[:, None], e, 0, E)[:, 0]
        big = torch.full((E,), float("inf"), dtype=dt, device=dev)
        mins = big.scatter_reduce(0, e, ang, reduce="amin")
        has = scatter_count(e, E) > 0
        out[:, 1] = torch.where(has, mins, torch.zeros_like(mins))
        out[:, 2] = has.to(dt)
    return out


# --------------------------------------------------------------------------- gate + confidence


def edge_errors(pose: Tensor, target: Tensor) -> Tensor:
    """Rotation and direction angle (radians) between two pose sets: ``[E, 7] x2 -> [E, 2]``."""
    return torch.stack((quaternion_angle(pose[:, :4], target[:, :4]),
                        angle_between_vectors(pose[:, 4:], target[:, 4:])), dim=-1)


def pair_stats(pair_edge: Tensor, box_src: Tensor, box_dst: Tensor, E: int) -> Tensor:
    """Direction-invariant matched-pair statistics per edge ``[E, 3]``: log(1 + #pairs), mean
    box area (both images) and mean centre displacement between the two boxes of a pair."""
    n = scatter_count(pair_edge, E).to(box_src.dtype)
    area = 0.5 * (box_src[:, 2] * box_src[:, 3] + box_dst[:, 2] * box_dst[:, 3])
    shift = (box_src[:, :2] - box_dst[:, :2]).norm(dim=-1)
    s = scatter_sum(torch.stack((area, shift), dim=-1), pair_edge, 0, E)
    return torch.cat((torch.log1p(n)[:, None], s / n.clamp_min(1.0)[:, None]), dim=-1)


#: input size of :class:`EdgeHead`: input/output disagreement (2), cycle features of input and
#: raw output (2 x 3), rotation magnitudes of input and output (2), pair statistics (3)
HEAD_IN_DIM = 2 + 2 * CYCLE_DIM + 2 + 3


class EdgeHead(nn.Module):
    """Per-edge gate and error scales from direction-invariant features.

    Every feature is the same for an edge and its flipped copy (angles, rotation magnitudes,
    cycle consistency, symmetric box statistics), so the gate and scales do not depend on the
    stored direction.

    Args:
        gate: predict the gates (rotation, direction).
        confidence: predict the four error scales (:data:`CONFIDENCE_NAMES`).
        hidden: MLP width (default 32); layers: MLP depth (default 3).
        gate_bias: initial bias of the gate logit (default 0: g = 0.5 at start).

    Shapes: ``forward(feats [E, HEAD_IN_DIM]) -> (gate [E, 2] | None, sigma [E, 4] | None)``;
    the gate has one column for the rotation and one for the translation direction (the
    direction carries far less information in the boxes, so it needs its own).
    """

    def __init__(self, gate: bool, confidence: bool, hidden: int = 32, layers: int = 3,
                 negative_slope: float = 0.01, gate_bias: float = 0.0) -> None:
        super().__init__()
        if not (gate or confidence):
            raise ValueError("EdgeHead needs gate=True or confidence=True")
        self.gate, self.confidence = bool(gate), bool(confidence)
        self.out_dim = 2 * int(self.gate) + (len(CONFIDENCE_NAMES) if self.confidence else 0)
        self.mlp = MLP(HEAD_IN_DIM, self.out_dim, hidden, layers, negative_slope, act_last=False)
        self.gate_bias = float(gate_bias)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        self.mlp.reset_parameters()
        last = self.mlp.net[-1]
        assert isinstance(last, nn.Linear)
        with torch.no_grad():
            if self.gate:
                last.bias[:2] = self.gate_bias

    @staticmethod
    def features(pose_in: Tensor, raw: Tensor, cyc_in: Tensor, cyc_raw: Tensor,
                 pair_stats: Tensor) -> Tensor:
        """The head's input ``[E, HEAD_IN_DIM]`` (angles in radians)."""
        ident = torch.zeros_like(pose_in[:, :4])
        ident[:, 0] = 1.0
        mags = torch.stack((quaternion_angle(pose_in[:, :4], ident),
                            quaternion_angle(raw[:, :4], ident)), dim=-1)
        return torch.cat((edge_errors(raw, pose_in), cyc_in, cyc_raw, mags, pair_stats), dim=-1)

    def forward(self, feats: Tensor) -> tuple[Tensor | None, Tensor | None]:
        out = self.mlp(feats)
        gate = torch.sigmoid(out[:, :2]) if self.gate else None
        sigma = None
        if self.confidence:
            # s = floor + exp(raw): smooth, positive, and e / s + log s is minimised at s = e
            sigma = SIGMA_FLOOR + torch.exp(out[:, 2 * int(self.gate):].clamp(max=3.0))
        return gate, sigma


def blend_poses(pose_in: Tensor, pred: Tensor, gate: Tensor) -> Tensor:
    """``(1 - g) * input + g * prediction`` on unit quaternions (sign-aligned, normalised) and
    unit translation directions. Shapes: ``[E, 7], [E, 7], gate [E] or [E, 2]`` (rotation,
    direction) ``-> [E, 7]``."""
    g2 = gate[:, None].expand(-1, 2) if gate.ndim == 1 else gate
    q_in = quaternion_normalize(pose_in[:, :4])
    q_pr = quaternion_normalize(pred[:, :4])
    sign = torch.where((q_in * q_pr).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(q_in.dtype)
    g = g2[:, :1]
    q = quaternion_normalize((1.0 - g) * q_in * sign + g * q_pr)
    g = g2[:, 1:]
    t_in = nn.functional.normalize(pose_in[:, 4:], dim=-1, eps=1e-12)
    t_pr = nn.functional.normalize(pred[:, 4:], dim=-1, eps=1e-12)
    t = nn.functional.normalize((1.0 - g) * t_in + g * t_pr, dim=-1, eps=1e-12)
    return torch.cat((quaternion_canonical(q), t), dim=-1)


def heteroscedastic_nll(err: Tensor, sigma: Tensor) -> Tensor:
    """Laplace negative log-likelihood ``err / sigma + log sigma`` (element-wise).

    A proper scoring rule for a scale: for a fixed ``err >= 0`` it is minimised exactly at
    ``sigma = err``, so the head learns to predict its expected error. ``err`` is treated as
    data (detach it when the pose should not be trained through this term). Shapes: any,
    broadcast.
    """
    return err / sigma + torch.log(sigma)

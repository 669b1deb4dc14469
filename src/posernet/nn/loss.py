"""PoserNet's training loss (paper Sec. 3.2, "Loss function").

.. math::

    \\mathcal L = \\mathcal L_{orient} + \\mathcal L_{tr\\_dir}
                 + \\alpha (\\mathcal L_{q||} + \\mathcal L_{tr||})

    \\mathcal L_{orient} = \\angle(q_{gt}^* \\circ q_{est}), \\quad
    \\mathcal L_{tr\\_dir} = \\angle(t_{gt}, t_{est}), \\quad
    \\mathcal L_{q||} = \\big| \\|q_{est}\\| - 1 \\big|, \\quad
    \\mathcal L_{tr||} = \\big| \\|t_{est}\\| - 1 \\big|

Angles are in radians, each term is averaged over edges. The orientation angle is sign
invariant (``q`` and ``-q`` are one rotation) and computed with ``atan2`` so its gradient is
finite at 0 and 180 degrees (``acos`` has an infinite derivative at 1).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from ..geometry import angle_between_vectors, quaternion_angle
from .adaptive import blend_poses, edge_errors, heteroscedastic_nll

__all__ = ["PoserLoss", "PoserNetLoss", "posernet_loss", "relative_objective"]


class PoserLoss(NamedTuple):
    """Total loss and its four terms (scalars, radians for the angles)."""

    loss: Tensor
    orient: Tensor
    tr_dir: Tensor
    q_norm: Tensor
    t_norm: Tensor


def _safe_norm(x: Tensor) -> Tensor:
    """Euclidean norm over the last dim with a zero (not NaN) gradient at the origin."""
    sq = (x * x).sum(-1)
    pos = sq > 0
    return torch.where(pos, torch.where(pos, sq, torch.ones_like(sq)).sqrt(), torch.zeros_like(sq))


def posernet_loss(pred: Tensor, target: Tensor, alpha: float = 0.1,
                  weight: Tensor | None = None) -> PoserLoss:
    """PoserNet loss between predicted and ground-truth edge poses.

    Args:
        pred: ``[E, 7]`` predicted ``[q, t]`` (need not be unit).
        target: ``[E, 7]`` ground truth (its translation may be metric; only its direction is
            used).
        alpha: weight of the two normalisation terms (default 0.1, the paper's value).
        weight: optional ``[E]`` non-negative per-edge weights (e.g. to average per graph);
            default uniform.

    Returns:
        :class:`PoserLoss` of scalars. With no edges every term is 0 (still attached to
        ``pred``'s graph, so ``backward`` works).
    """
    if pred.ndim != 2 or pred.shape[-1] != 7 or target.shape != pred.shape:
        raise ValueError(f"posernet_loss: pred and target must both be [E, 7], got "
                         f"{tuple(pred.shape)} and {tuple(target.shape)}")
    orient = quaternion_angle(pred[:, :4], target[:, :4])
    tr_dir = angle_between_vectors(pred[:, 4:], target[:, 4:])
    q_norm = (_safe_norm(pred[:, :4]) - 1.0).abs()
    t_norm = (_safe_norm(pred[:, 4:]) - 1.0).abs()
    if weight is None:
        weight = torch.ones_like(orient)
    elif weight.shape != orient.shape:
        raise ValueError(f"posernet_loss: weight must be [E] = [{orient.shape[0]}], got "
                         f"{tuple(weight.shape)}")
    total_w = weight.sum()

    def mean(v: Tensor) -> Tensor:
        if v.numel() == 0:
            return pred.sum() * 0.0
        return (v * weight).sum() / total_w.clamp_min(torch.finfo(v.dtype).tiny)

    o, d, qn, tn = mean(orient), mean(tr_dir), mean(q_norm), mean(t_norm)
    return PoserLoss(o + d + alpha * (qn + tn), o, d, qn, tn)


class PoserNetLoss(nn.Module):
    """Module wrapper of :func:`posernet_loss` with a fixed ``alpha`` (default 0.1)."""

    def __init__(self, alpha: float = 0.1) -> None:
        super().__init__()
        self.alpha = float(alpha)

    def forward(self, pred: Tensor, target: Tensor, weight: Tensor | None = None) -> PoserLoss:
        return posernet_loss(pred, target, self.alpha, weight)

    def extra_repr(self) -> str:
        return f"alpha={self.alpha}"


def relative_objective(pred: Tensor, gt: Tensor, edge_pose: Tensor, extras: Any,
                       weights: Mapping[str, Any]) -> tuple[Tensor, PoserLoss, dict[str, Tensor]]:
    """The training objective on relative poses: the paper's loss (:func:`posernet_loss`) plus
    the input-adaptive terms that ``weights`` switches on.

    ``pred, gt, edge_pose [E, 7]`` refined, true and input edge poses; ``extras`` the model's
    :class:`~posernet.nn.adaptive.AdaptiveOutput` (``None`` for the paper's model);
    ``weights`` the ``loss`` hyper-parameters: ``alpha`` and the weights of ``raw`` (the
    un-gated prediction), ``confidence`` (Gaussian NLL of the error scales), ``correction``
    (how far the prediction moves from its input) and ``harm`` (a hinge on getting worse than
    the input, relative when ``harm_scale`` > 0). Returns ``(total, the paper's terms, the
    other terms by name)``.
    """
    lh = weights
    out = posernet_loss(pred, gt, lh["alpha"])
    total = out.loss
    terms: dict[str, Tensor] = {}
    if extras is not None and extras.gate is not None and lh.get("raw", 0.0):
        terms["raw"] = posernet_loss(extras.raw, gt, lh["alpha"]).loss
        total = total + lh["raw"] * terms["raw"]
    if extras is not None and extras.sigma is not None and lh.get("confidence", 0.0):
        # the scales learn the errors; the errors are data here (no gradient to the pose)
        err = torch.cat((edge_errors(pred, gt), edge_errors(edge_pose, gt)), dim=-1)
        terms["confidence"] = heteroscedastic_nll(err.detach(), extras.sigma).mean()
        total = total + lh["confidence"] * terms["confidence"]
    if lh.get("correction", 0.0):
        terms["correction"] = quaternion_angle(pred[:, :4], edge_pose[:, :4]).mean()
        total = total + lh["correction"] * terms["correction"]
    if lh.get("harm", 0.0):
        # absolute hinge, with a gate: it trains the decision only (the prediction is data
        # here): through the prediction it would pull every estimate towards its input.
        # Relative hinge (harm_scale > 0): the pull on poor inputs is negligible, so it
        # trains the whole network to keep good inputs good (measured: better than gate-only)
        scale = lh.get("harm_scale", 0.0)
        judged = pred if extras is None or extras.gate is None or scale else blend_poses(
            edge_pose, extras.raw.detach(), extras.gate)
        e_in = edge_errors(edge_pose, gt).detach()
        worse = (edge_errors(judged, gt) - e_in).clamp_min(0.0)
        if scale:
            worse = worse / (e_in + scale)
        terms["harm"] = worse.sum(-1).mean()
        total = total + lh["harm"] * terms["harm"]
    return total, out, terms

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

from typing import NamedTuple

import torch
from torch import Tensor, nn

from ..geometry import angle_between_vectors, quaternion_angle

__all__ = ["PoserLoss", "PoserNetLoss", "posernet_loss"]


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

"""Robust IRLS weights with a MAD threshold (Cauchy and Huber), per padded component."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["batch_median", "mad_cauchy_weights", "mad_huber_weights"]


def batch_median(x: Tensor, mask: Tensor) -> Tensor:
    """Median of the masked entries along the last dim (mean of the two middle values for an
    even count, numpy/MATLAB convention). ``x, mask [..., m] -> [...]``; NaN where empty."""
    big = torch.finfo(x.dtype).max
    s = torch.sort(torch.where(mask, x, torch.full_like(x, big)), dim=-1).values
    k = mask.sum(-1)
    lo = ((k - 1).clamp_min(0) // 2)[..., None]
    hi = (k // 2).clamp_max(x.shape[-1] - 1)[..., None]
    med = 0.5 * (s.gather(-1, lo) + s.gather(-1, hi)).squeeze(-1)
    return torch.where(k > 0, med, torch.full_like(med, float("nan")))


def mad_cauchy_weights(res: Tensor, mask: Tensor, theta: float,
                       floor: float = 1e-9) -> Tensor:
    """Cauchy IRLS weights ``1 / (1 + (r / th)^2)`` with ``th = theta / 0.6745 * MAD(r)``
    per row. ``res, mask [G, m]``; ``MAD = median(|r - median(r)|)`` over the row's edges.

    ``floor`` keeps ``th`` positive for exact data (all residuals ~0), where the weights would
    otherwise be 0/0 round-off noise; it only acts when ``th < floor``.
    """
    med = batch_median(res, mask)
    mad = batch_median((res - med[:, None]).abs(), mask)
    th = (theta / 0.6745 * mad).clamp_min(floor)
    w = 1.0 / (1.0 + (res / th[:, None]) ** 2)
    return torch.where(mask, w, torch.zeros_like(w))


def mad_huber_weights(res: Tensor, mask: Tensor, theta: float,
                      floor: float = 1e-9) -> Tensor:
    """Huber IRLS weights ``min(1, th / r)`` with the same MAD threshold as
    :func:`mad_cauchy_weights`. ``res, mask [G, m]``."""
    med = batch_median(res, mask)
    mad = batch_median((res - med[:, None]).abs(), mask)
    th = (theta / 0.6745 * mad).clamp_min(floor)[:, None]
    w = torch.where(res <= th, torch.ones_like(res), th / res.clamp_min(1e-300))
    return torch.where(mask, w, torch.zeros_like(w))

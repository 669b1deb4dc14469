"""Confidence-weighted start of the spectral rotation IRLS, and the per-edge weight rule.

PoserNet's confidence head predicts, per edge, how far its refined pose is likely to be from
the truth. Motion averaging can use it: the IRLS of EIG-SE3 (and of ``rotation_translation``)
starts from these weights instead of uniform ones, so the first eigen-solve already trusts the
good edges and the Cauchy re-weighting starts from a better solution.

``mode``:

* ``start``: the first solve uses the given weights, the following ones EIG-SE3's Cauchy
  weights as published (the prior only picks the starting point).
* ``prior``: every solve multiplies the Cauchy weights by the given weights (the prior stays).

The backends pass the weights as ``w0`` (and ``prior`` for that mode) to the one spectral
IRLS, :func:`posernet.sync.irls.rotation_irls`; with uniform weights both modes are exactly
the published IRLS (tested). Weighted problems take the same eigen-solver as unweighted ones
(dense on small components, block Krylov on large ones: a 3072x3072 ``eigh`` per IRLS round
made a 1024-camera graph take minutes).

**Weight rule** (``edge_weight`` given to :meth:`~posernet.sync.backend.SyncBackend.solve`):
``[E]`` (one weight for both parts) or ``[E, 2]`` (rotation, translation), finite. Weights are
relative confidences (e.g. ``sigma^-2`` of the error head; only ratios within a component
matter, and the smallest positive one is floored at :data:`MIN_PRIOR` times the largest).

* rotation weight: ``> 0``; an edge always takes part in rotation averaging (remove it from
  the graph to ignore it);
* translation weight: ``>= 0``; exactly ``0`` means "this edge has no usable direction" (e.g. a
  pair with a tiny baseline, near pure rotation): ``rotation_translation`` leaves it out of the
  translation stage entirely (it cannot influence any position) but still uses its rotation.
  EIG-SE3 reads only the rotation column.
"""


from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ..options import option
from .padding import PaddedProblem

__all__ = ["WEIGHT_MODES", "padded_weights", "weight_mode_option"]

WEIGHT_MODES = ("start", "prior")


def weight_mode_option() -> Any:
    """The ``weight_mode`` field of the backends that take per-edge weights."""
    return option("start", choices=WEIGHT_MODES,
                  help="per-edge confidence weights (posernet-refine with an adaptive "
                       "checkpoint): start = the first solve uses them, then the published "
                       "Cauchy IRLS; prior = they multiply every Cauchy weight")

#: smallest prior weight relative to the graph's largest: an edge is never switched off (a
#: zero weight on a bridge would disconnect the graph)
MIN_PRIOR = 1e-3


def padded_weights(prob: PaddedProblem, w: Tensor, keep_zero: bool = False) -> Tensor:
    """Per-edge weights ``w [E]`` laid out as the problem's ``[G, m]`` (0 on pads), scaled so
    each component's largest weight is 1 and floored at :data:`MIN_PRIOR`; with ``keep_zero``
    a weight of exactly 0 stays 0 (translation weights: "no usable direction")."""
    wp = torch.where(prob.edge_mask, w.to(prob.R.dtype)[prob.edge.clamp_min(0)],
                     torch.zeros((), dtype=prob.R.dtype, device=prob.R.device))
    top = wp.amax(dim=1, keepdim=True).clamp_min(torch.finfo(wp.dtype).tiny)
    keep = prob.edge_mask & (wp > 0) if keep_zero else prob.edge_mask
    wp = (wp / top).clamp_min(MIN_PRIOR)
    return torch.where(keep, wp, torch.zeros_like(wp))

"""The spectral rotation IRLS the backends call: the robust dense case by Chebyshev-filtered
subspaces (:func:`posernet.sync.filtered.dense_irls`, no ``eigh`` per iteration, the same
result), every other case by the reference loop :func:`posernet.sync.spectral.rotation_irls`.

A module of its own so that :mod:`~posernet.sync.spectral` (the loop and the operators) and
:mod:`~posernet.sync.filtered` (which builds on them) do not import each other.
"""

from __future__ import annotations

from torch import Tensor

from .filtered import dense_irls
from .padding import PaddedProblem
from .spectral import RotationSolution, start_weights
from .spectral import rotation_irls as rotation_irls_loop

__all__ = ["rotation_irls"]


def rotation_irls(prob: PaddedProblem, robust: bool, max_iters: int, tol: float, theta: float,
                  krylov: bool, krylov_tol: float = 1e-12, krylov_max_cycles: int = 500,
                  seed: int = 0, w0: Tensor | None = None,
                  prior: bool = False) -> RotationSolution:
    """:func:`posernet.sync.spectral.rotation_irls` (same arguments, same result), with the
    robust dense solve by filtered subspaces."""
    if robust and not krylov:
        w_edge, w_diag = start_weights(prob, w0)
        w_prior = w_edge.clone() if prior and w0 is not None else None
        return dense_irls(prob, w_edge, w_diag, max_iters, tol, theta, seed, w_prior)
    return rotation_irls_loop(prob, robust, max_iters, tol, theta, krylov, krylov_tol,
                              krylov_max_cycles, seed, w0, prior)

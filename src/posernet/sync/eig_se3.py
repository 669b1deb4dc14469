"""EIG-SE3 (Arrigoni, Rossi, Fusiello, SIAM J. Imaging Sci. 2016), batched in torch.

**The published algorithm** (as in the SIIMS paper). Stack the absolute poses ``M_i`` into
``M [4n, 4]``; build ``X [4n, 4n]`` with block ``X_ab = M_a M_b^{-1}`` for measured pairs
(identity on the diagonal; with world-to-camera ``M`` that block is the pose of edge ``b -> a``,
so stored edge ``i -> j`` with pose ``P`` fills ``X_ji = P`` and ``X_ij = P^{-1}``), weights
``W`` (adjacency plus identity), ``D = diag(W 1) (x) I4``. The 4 leading eigenvectors ``U`` of
``D^{-1} X`` span the poses; a change of basis makes every 4th row ``[0 0 0 1]``
(``alpha = null(B)``, ``beta = B \\ 1``, ``B`` = every 4th row of ``U``), each 3x3 block is
projected onto SO(3) and each translation divided by its (4, 4) entry. The robust variant
(IRLS) re-solves with Cauchy weights ``1 / (1 + (r / th)^2)``,
``r_ab = |R_a R_b^T - X_ab[:3,:3]|_F``, ``th = 2 / 0.6745 * MAD(r)``, diagonal weights
``max(w)``, until ``|W_old - W|_F / (|W|_F n) < 1e-5`` or 50 solves.

**What is computed here -- the same thing, faster.** Reorder the coordinates of ``X`` as
(the 3n rotation rows | the n homogeneous rows). Every block's 4th row is ``[0 0 0 w]``, so

    D^{-1} X = [[D3^{-1} X_RR, D3^{-1} X_Rh],
                [0,            D^{-1} W    ]]

is block upper triangular: its eigenvalues are those of ``D3^{-1} X_RR`` (the SO(3)
synchronisation matrix; ``X_RR`` is *symmetric* because ``R_ba = R_ab^T``) and those of the
random walk ``D^{-1} W`` (largest exactly 1, eigenvector ``1``). All are real. The leading
eigenspace is therefore spanned by

* ``[r_k; 0]``, ``r_k = D3^{-1/2} v_k`` with ``v_1..3`` the top eigenvectors of the symmetric
  ``N = D3^{-1/2} X_RR D3^{-1/2}`` (one ``eigh``), and
* ``[x; 1]`` with ``(D3 - X_RR) x = X_Rh 1`` (a linear system).

Every 4th row of this basis is already ``[0 0 0 1]`` (rank one), so the published change of
basis keeps ``span{r_k}`` for the rotations and picks the representative of ``x`` orthogonal
to ``span{r_k}`` for the translations. Numerically stable form: with ``V3 = [v_1 v_2 v_3]``,
solve the SPD system ``(I - N + V3 V3^T) z = (I - V3 V3^T) D3^{-1/2} b`` (``b = X_Rh 1``), then
``x = D3^{-1/2} z`` and remove its component in ``span{r_k}``. The IRLS residuals use the
rotations only, so the translations are solved once, with the weights of the last solve
(exactly what the published loop returns). This is exact, not an approximation: the tests
check it against the literal 4n x 4n implementation in :mod:`posernet.sync.reference`.

It differs from a literal run only where the literal run is ill-defined: its eigenvector basis
(LAPACK/ARPACK normalisation, complex phases) is replaced by an orthonormal one, which makes the
result unique up to the gauge; and the handedness test uses the sign of the sum of all blocks'
determinants instead of the first block's (identical unless that block is degenerate). If the
random walk's second eigenvalue exceeded the third rotation eigenvalue (extreme noise on a
graph with a tiny spectral gap) the literal algorithm would mix a non-pose direction into ``U``;
here the rotation eigenvectors are always used.

**Batching.** Components (:mod:`posernet.sync.components`) are padded to ``[G, n]``
(:mod:`posernet.sync.padding`). Small ones (``<= dense_max_nodes``) use dense ``[G, 3n, 3n]``
matrices: the IRLS iterations take the span of the top-3 eigenvectors from a Chebyshev filter
(:mod:`posernet.sync.filtered`; the span is all an iteration's weights depend on), the last
solve of each component a batched ``eigh``, the translations a batched Cholesky solve; large
ones a batched restarted block-Krylov (Lanczos with full reorthogonalisation) for the top 3
eigenvectors, warm-started across IRLS iterations, and conjugate gradients for the
translations, applying ``N`` through the edges (O(E) per product); the rotation part is shared
with ``rotation_translation`` (:mod:`posernet.sync.spectral`). IRLS iterates only the graphs
that have not converged.
Everything runs in float64 internally (eigenvectors of nearly degenerate clusters need it) on
the input's device; results are cast back to the input dtype.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..options import option
from .backend import SyncBackend, SyncResult, apply_scale_policy, scale_option
from .components import Components
from .irls import rotation_irls
from .padding import PaddedProblem, assemble, build_padded, edge_rotations
from .spectral import (
    RotationSolution,
    SpectralOptions,
    conjugate_gradient,
    degrees,
    dense_N,
    sparse_apply,
    sparse_N,
    split_by_size,
)
from .weighted import padded_weights, weight_mode_option

__all__ = ["EigSE3", "EigSE3Options", "eig_translations", "solve_padded"]


@dataclass(frozen=True)
class EigSE3Options(SpectralOptions):
    """:class:`SpectralOptions` plus ``krylov_tol`` (eigen-residual tolerance) and
    ``krylov_max_cycles`` (restarts per solve); default scale ``unit``."""

    scale: str = scale_option("unit")
    krylov_tol: float = option(1e-12, gt=0, help="Krylov: eigen-residual tolerance")
    krylov_max_cycles: int = option(500, ge=1, help="Krylov: restarts per solve")
    weight_mode: str = weight_mode_option()


# --------------------------------------------------------------------------- translations


def eig_translations(prob: PaddedProblem, sol: RotationSolution, krylov: bool) -> Tensor:
    """EIG-SE3 translations ``[G, n, 3]``: the representative of ``x`` orthogonal to the
    rotation eigenvectors, where ``[x; 1]`` is the homogeneous eigenvector of ``D^{-1} X``
    (see the module docstring). Uses the weights and eigenvectors of the last rotation solve.
    """
    G, n, m = prob.G, prob.n, prob.m
    we, wd = sol.w_edge[:, :m], sol.w_diag
    s = degrees(prob, we, wd).rsqrt()
    # b = X_Rh 1: block (j, i) holds t_e, block (i, j) the inverse's translation -R_e^T t_e.
    b = torch.zeros(G * n, 3, dtype=prob.t.dtype, device=prob.t.device)
    base = torch.arange(G, device=b.device)[:, None] * n
    wt = we[..., None] * prob.t
    b.index_add_(0, (base + prob.dst).flatten(), wt.reshape(-1, 3))
    b.index_add_(0, (base + prob.src).flatten(),
                 -(prob.R.mT @ wt[..., None]).squeeze(-1).reshape(-1, 3))
    y = (b.view(G, n, 3) * s[..., None]).reshape(G, 3 * n)
    V3 = sol.V3[:, :3 * n]
    y = y - (V3 @ (V3.mT @ y[..., None])).squeeze(-1)
    if krylov:
        Sp = sparse_N(prob, we, wd, s, sol.pattern)

        def op(z: Tensor) -> Tensor:
            Nz = sparse_apply(Sp, z[..., None]).squeeze(-1)
            return z - Nz + (V3 @ (V3.mT @ z[..., None])).squeeze(-1)

        z, _ = conjugate_gradient(op, y)
    else:
        S = torch.eye(3 * n, dtype=y.dtype, device=y.device) - dense_N(prob, we, wd, s)
        S = S + V3 @ V3.mT
        L, info = torch.linalg.cholesky_ex(S)
        z = torch.cholesky_solve(y[..., None], L).squeeze(-1)
        bad = info != 0
        if bool(bad.any()):  # numerically singular (tiny spectral gap): fall back to LU
            z[bad] = torch.linalg.solve(S[bad], y[bad])
    x = (z.view(G, n, 3) * s[..., None]).reshape(G, 3 * n)
    Rh = sol.Rh[:, :3 * n]
    x = x - (Rh @ (Rh.mT @ x[..., None])).squeeze(-1)
    return x.view(G, n, 3) * prob.node_mask[..., None]


# --------------------------------------------------------------------------- backend


def solve_padded(prob: PaddedProblem, opts: EigSE3Options,
                 w0: Tensor | None = None) -> tuple[Tensor, Tensor, dict]:
    """EIG-SE3 on every component of ``prob``: ``(R [G, n, 3, 3], t [G, n, 3], info)``.

    ``w0 [G, m]``: optional starting weights of the IRLS (:mod:`posernet.sync.weighted`)."""
    G, n, m = prob.G, prob.n, prob.m
    dt, dev = prob.R.dtype, prob.R.device
    R = torch.eye(3, dtype=dt, device=dev).expand(G, n, 3, 3).clone()
    t = torch.zeros(G, n, 3, dtype=dt, device=dev)
    w_edge = torch.zeros(G, m, dtype=dt, device=dev)
    iters = torch.zeros(G, dtype=torch.long, device=dev)
    conv = torch.zeros(G, dtype=torch.bool, device=dev)
    eig_ok = torch.ones(G, dtype=torch.bool, device=dev)
    for idx, krylov in split_by_size(prob, opts.solver, opts.dense_max_nodes):
        sub = prob.select(idx) if idx.numel() < G else prob
        sol = rotation_irls(sub, opts.robust, opts.max_iters, opts.tol, opts.theta, krylov,
                            opts.krylov_tol, opts.krylov_max_cycles, opts.seed,
                            w0=None if w0 is None else w0[idx, :sub.m],
                            prior=opts.weight_mode == "prior")
        ts = eig_translations(sub, sol, krylov)
        R[idx, :sub.n], t[idx, :sub.n] = sol.R, ts
        w_edge[idx, :sub.m] = sol.w_edge
        iters[idx], conv[idx], eig_ok[idx] = sol.iterations, sol.converged, sol.eig_converged
    return R, t, {"w_edge": w_edge, "iterations": iters, "converged": conv,
                  "eig_converged": eig_ok}


class EigSE3(SyncBackend):
    """EIG-SE3 spectral SE(3) synchronisation with IRLS (default), batched.

    ``scale`` must be ``unit`` (default), ``given`` or ``oracle``: EIG-SE3 needs all relative
    translations in one metric; scale-free averaging is the ``rotation_translation`` backend.
    """

    name = "eig_se3"
    Options = EigSE3Options
    scales = ("unit", "given", "oracle")

    def _solve(self, struct: dict[str, Any], edge_pose: Tensor, edge_pose_gt: Tensor | None,
               comps: Components) -> SyncResult:
        o: EigSE3Options = self.options  # type: ignore[assignment]
        R_e = edge_rotations(edge_pose)
        t_e = apply_scale_policy(edge_pose[:, 4:], o.scale, edge_pose_gt)
        prob = build_padded(struct["edge_index"], R_e, t_e, comps)
        w = struct.get("edge_weight")
        R, t, info = solve_padded(prob, o, None if w is None else padded_weights(prob, w[:, 0]))
        if not bool(info["eig_converged"].all()):
            warnings.warn(
                f"eig_se3: the Krylov eigen-solver did not reach krylov_tol={o.krylov_tol} in "
                f"{o.krylov_max_cycles} cycles for {int((~info['eig_converged']).sum())} "
                "component(s) (tiny spectral gap?); their poses may be inaccurate. Try "
                "solver='dense' or a larger krylov_max_cycles.", RuntimeWarning, stacklevel=3)
        poses, solved, w, it, conv = assemble(struct, comps, prob, R, t, info["w_edge"],
                                              info["iterations"], info["converged"],
                                              edge_pose.dtype, edge_pose.device)
        return SyncResult(poses=poses, component=comps.comp, solved=solved, edge_weight=w,
                          iterations=it, converged=conv, scale=o.scale, metric=self.metric,
                          backend=self.name,
                          info={"eig_converged": bool(info["eig_converged"].all())})

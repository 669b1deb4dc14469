"""Rotation averaging followed by translation averaging, batched over components.

**Rotations.** (1) Robust spectral rotation synchronisation: the top-3 eigenvectors of
``N = D3^{-1/2} X_RR D3^{-1/2}`` re-weighted with EIG-SE3's IRLS (Cauchy weights, MAD
threshold) -- exactly the rotation part of EIG-SE3 (:mod:`posernet.sync.spectral`). (2) Geodesic
refinement (Lie-algebraic IRLS, Chatterjee & Govindu style): with ``E_e = R_j^T R_e R_i``
(identity when edge ``e = i -> j`` agrees) and ``w_e = log(E_e)``, solve the weighted least
squares ``min sum_e c_e |d_j - d_i - w_e|^2`` (``sum_i d_i = 0``) for the right perturbations
``R_i <- R_i exp([d_i]_x)``, with Cauchy weights ``c_e`` on ``|w_e|``; repeat until the update
is below ``1e-12`` rad or ``refine_iters`` times.

**Translations** from the synchronised rotations. With ``c_i = -R_i^T t_i`` and the edge
convention ``t_e = t_j - R_j R_i^T t_i = -R_j (c_j - c_i)``, edge ``e`` says
``c_j - c_i = u_e := -R_j^T t_e`` (world frame).

* ``scale="free"`` (default; scale-free, only the directions ``d_e = u_e / |u_e|`` are used):
  minimise ``sum_e a_e |P_e (c_j - c_i)|^2`` with ``P_e = I - d_e d_e^T`` (the component of
  the baseline orthogonal to its measured direction) subject to the gauge ``sum_i c_i = 0``
  and ``sum_e a_e d_e . (c_j - c_i) = sum_e a_e`` (fixes scale *and* sign: baselines point
  along their directions on average). One linear KKT system per component (a tiny ridge
  makes tree-like, non-parallel-rigid graphs return the minimum-norm solution instead of
  failing; their relative baseline lengths are genuinely undetermined). IRLS:
  ``a_e = huber(theta_e) / |c_j - c_i|^2`` (normalised), ``theta_e`` the angle between
  ``c_j - c_i`` and ``d_e`` -- Govindu's reweighting makes the linear cost approximate the sum
  of squared sines, the Huber factor (MAD threshold) bounds the influence of outliers. Huber,
  not Cauchy: on small graphs a redescending loss can switch off enough edges to lose parallel
  rigidity (measured: worse medians on noisy 8-node graphs). The output gauge is centroid 0
  and RMS distance 1 to the centroid: evaluate with a similarity alignment.
* ``scale`` in ``unit`` / ``given`` / ``oracle``: metric least squares
  ``min sum_e a_e |c_j - c_i - u_e|^2``, ``sum_i c_i = 0`` (weighted graph Laplacian), with the
  same Cauchy IRLS on ``|c_j - c_i - u_e|``.

Dense batched linear algebra on padded ``[G, n, n]`` / ``[G, 3n + 4, 3n + 4]`` systems; large
components use the Krylov eigen-solver of :mod:`posernet.sync.spectral` for the rotations.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..geometry import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle
from .backend import SyncBackend, SyncResult, apply_scale_policy, check_positive
from .components import Components
from .padding import PaddedProblem, assemble, build_padded, edge_rotations
from .robust import mad_cauchy_weights, mad_huber_weights
from .spectral import SpectralOptions, rotation_irls, split_by_size
from .weighted import WEIGHT_MODES, padded_weights, weighted_rotation_irls

__all__ = ["RotationTranslation", "RotationTranslationOptions", "refine_rotations",
           "translations_from_directions", "translations_metric"]


@dataclass(frozen=True)
class RotationTranslationOptions(SpectralOptions):
    """:class:`~posernet.sync.spectral.SpectralOptions` for the spectral rotation IRLS (as
    EIG-SE3), plus ``refine_iters``: geodesic refinement steps (0 = off) and
    ``translation_iters``: IRLS steps of the translation stage; default scale ``free``."""

    scale: str = "free"
    refine_iters: int = 20
    translation_iters: int = 20
    weight_mode: str = "start"  # per-edge weights given to solve(): start | prior (weighted.py)

    def check(self) -> None:
        super().check()
        if self.weight_mode not in WEIGHT_MODES:
            raise ValueError(f"weight_mode={self.weight_mode!r}; choose one of "
                             f"{list(WEIGHT_MODES)}")
        check_positive("translation_iters", self.translation_iters, integer=True)
        if not isinstance(self.refine_iters, int) or self.refine_iters < 0:
            raise ValueError(f"refine_iters must be an integer >= 0, got {self.refine_iters!r}")


# Robust weights are floored at this value on real edges: a Cauchy weight can underflow to 0
# on a bridge edge, which would disconnect the weighted graph and make its Laplacian singular.
WEIGHT_FLOOR = 1e-6


def _laplacian(prob: PaddedProblem, w: Tensor) -> Tensor:
    """Weighted graph Laplacian ``[G, n, n]`` plus ``11^T / n`` on the valid block (gauge:
    the solution has zero mean) and the identity on padded nodes (their unknowns stay 0).
    ``w`` must already be floored (:data:`WEIGHT_FLOOR`) on real edges."""
    G, n = prob.G, prob.n
    L = torch.zeros(G, n, n, dtype=w.dtype, device=w.device)
    gi = torch.arange(G, device=w.device)[:, None].expand(G, prob.m)
    L.index_put_((gi, prob.src, prob.dst), -w, accumulate=True)
    L.index_put_((gi, prob.dst, prob.src), -w, accumulate=True)
    deg = -L.sum(-1)
    L = L + torch.diag_embed(deg)
    vm = prob.node_mask.to(w.dtype)
    L = L + vm[:, :, None] * vm[:, None, :] / prob.count.to(w.dtype)[:, None, None]
    return L + torch.diag_embed(1.0 - vm)


def _incidence_rhs(prob: PaddedProblem, w: Tensor, v: Tensor) -> Tensor:
    """``B^T W v``: for each edge ``e = i -> j`` add ``w v`` at ``j`` and subtract at ``i``."""
    G, n = prob.G, prob.n
    out = torch.zeros(G * n, v.shape[-1], dtype=v.dtype, device=v.device)
    base = torch.arange(G, device=v.device)[:, None] * n
    wv = (w[..., None] * v).reshape(-1, v.shape[-1])
    out.index_add_(0, (base + prob.dst).flatten(), wv)
    out.index_add_(0, (base + prob.src).flatten(), -wv)
    return out.view(G, n, -1)


def _gather(x: Tensor, idx: Tensor) -> Tensor:
    """``x[g, idx[g, e]]`` for ``x [G, n, ...]``, ``idx [G, m]``."""
    gi = torch.arange(x.shape[0], device=x.device)[:, None].expand_as(idx)
    return x[gi, idx]


def refine_rotations(prob: PaddedProblem, R: Tensor, iters: int, robust: bool,
                     theta: float) -> Tensor:
    """Geodesic (Lie-algebraic) IRLS refinement of absolute rotations ``R [G, n, 3, 3]``."""
    if iters <= 0:
        return R
    for _ in range(iters):
        E = _gather(R, prob.dst).mT @ prob.R @ _gather(R, prob.src)
        w_e = rotation_matrix_to_axis_angle(E) * prob.edge_mask[..., None]
        ang = w_e.norm(dim=-1)
        c = (mad_cauchy_weights(ang, prob.edge_mask, theta) if robust
             else prob.edge_mask.to(R.dtype))
        c = torch.maximum(c, WEIGHT_FLOOR * prob.edge_mask.to(c.dtype))
        L = _laplacian(prob, c)
        d = torch.linalg.solve(L, _incidence_rhs(prob, c, w_e))
        d = d * prob.node_mask[..., None]
        R = R @ axis_angle_to_rotation_matrix(d)
        if float(d.norm(dim=-1).max()) < 1e-12:
            break
    return R


def _world_baselines(prob: PaddedProblem, R: Tensor) -> Tensor:
    """``u_e = -R_j^T t_e [G, m, 3]``: world-frame baseline ``c_j - c_i`` of edge ``i -> j``."""
    return -(_gather(R, prob.dst).mT @ prob.t[..., None]).squeeze(-1)


def translations_metric(prob: PaddedProblem, R: Tensor, iters: int, robust: bool,
                        theta: float) -> Tensor:
    """Camera centres ``[G, n, 3]`` (mean 0) from metric world baselines; Cauchy IRLS."""
    u = _world_baselines(prob, R)
    w = prob.edge_mask.to(R.dtype)
    c = torch.zeros(prob.G, prob.n, 3, dtype=R.dtype, device=R.device)
    for _ in range(iters if robust else 1):
        c_new = torch.linalg.solve(_laplacian(prob, w), _incidence_rhs(prob, w, u))
        c_new = c_new * prob.node_mask[..., None]
        change = float((c_new - c).abs().max())
        c = c_new
        if not robust:
            break
        r = (_gather(c, prob.dst) - _gather(c, prob.src) - u).norm(dim=-1)
        w = mad_cauchy_weights(r, prob.edge_mask, theta)
        w = torch.maximum(w, WEIGHT_FLOOR * prob.edge_mask.to(w.dtype))
        if change < 1e-12 * max(1.0, float(c.abs().max())):
            break
    return c


def translations_from_directions(prob: PaddedProblem, R: Tensor, iters: int, robust: bool,
                                 theta: float, ridge_rel: float = 1e-10,
                                 w0: Tensor | None = None) -> Tensor:
    """Scale-free camera centres ``[G, n, 3]`` (centroid 0, RMS radius 1) from directions.

    See the module docstring for the objective, constraints and reweighting. ``w0 [G, m]``:
    optional starting edge weights (per-edge confidence; uniform when omitted).
    """
    G, n, m = prob.G, prob.n, prob.m
    dt, dev = R.dtype, R.device
    u = _world_baselines(prob, R)
    un = u.norm(dim=-1, keepdim=True)
    d = torch.where(un > 0, u / un.clamp_min(1e-300), torch.zeros_like(u))
    emask = prob.edge_mask & (un.squeeze(-1) > 0)
    P = torch.eye(3, dtype=dt, device=dev) - d[..., :, None] * d[..., None, :]
    gi = torch.arange(G, device=dev)[:, None].expand(G, m)
    vm = prob.node_mask.to(dt)
    size = 3 * n + 4
    a = emask.to(dt) if w0 is None else torch.where(emask, w0.to(dt), torch.zeros_like(w0))
    c = torch.zeros(G, n, 3, dtype=dt, device=dev)
    for it in range(iters if robust else 1):
        K = torch.zeros(G, n, n, 3, 3, dtype=dt, device=dev)
        aP = a[..., None, None] * P
        K.index_put_((gi, prob.src, prob.src), aP, accumulate=True)
        K.index_put_((gi, prob.dst, prob.dst), aP, accumulate=True)
        K.index_put_((gi, prob.src, prob.dst), -aP, accumulate=True)
        K.index_put_((gi, prob.dst, prob.src), -aP, accumulate=True)
        K = K.permute(0, 1, 3, 2, 4).reshape(G, 3 * n, 3 * n)
        scale = K.diagonal(dim1=-2, dim2=-1).mean(-1).clamp_min(1e-300)
        A = torch.zeros(G, size, size, dtype=dt, device=dev)
        A[:, :3 * n, :3 * n] = 2.0 * K
        # Constraint rows: sum_i c_i = 0 (3 rows), sum_e a_e d_e . (c_j - c_i) = sum_e a_e.
        C = torch.zeros(G, 4, n, 3, dtype=dt, device=dev)
        C[:, :3] = (torch.eye(3, dtype=dt, device=dev)[None, :, None, :]
                    * vm[:, None, :, None])
        C[:, 3] = _incidence_rhs(prob, a, d)  # sum_e a_e d_e, added at j, subtracted at i
        C = C.reshape(G, 4, 3 * n)
        A[:, 3 * n:, :3 * n] = C
        A[:, :3 * n, 3 * n:] = C.mT
        # Padded unknowns: identity rows keep them at 0.
        A[:, :3 * n, :3 * n] += torch.diag_embed(1.0 - vm.repeat_interleave(3, dim=1))
        rhs = torch.zeros(G, size, 1, dtype=dt, device=dev)
        rhs[:, -1, 0] = a.sum(1)
        # A small ridge keeps non-parallel-rigid graphs solvable (minimum-norm-like answer);
        # two steps of iterative refinement against the unridged system remove its bias.
        ridge = torch.zeros(G, size, dtype=dt, device=dev)
        ridge[:, :3 * n] = (ridge_rel * scale)[:, None] * vm.repeat_interleave(3, dim=1)
        LU, piv = torch.linalg.lu_factor(A + torch.diag_embed(ridge))
        sol = torch.linalg.lu_solve(LU, piv, rhs)
        for _ in range(2):
            sol = sol + torch.linalg.lu_solve(LU, piv, rhs - A @ sol)
        sol = sol.squeeze(-1)
        c_new = sol[:, :3 * n].view(G, n, 3) * vm[..., None]
        change = float((c_new - c).abs().max())
        c = c_new
        if not robust:
            break
        base = _gather(c, prob.dst) - _gather(c, prob.src)
        bl2 = (base * base).sum(-1)
        cosang = (base * d).sum(-1) / bl2.sqrt().clamp_min(1e-300)
        ang = torch.arccos(cosang.clamp(-1.0, 1.0))
        cw = mad_huber_weights(ang, emask, theta)
        mean_bl2 = (bl2 * emask).sum(1) / emask.sum(1).clamp_min(1)
        bl2 = torch.maximum(bl2, 1e-6 * mean_bl2[:, None])
        a_new = cw * mean_bl2[:, None] / bl2.clamp_min(1e-300)
        a = torch.where(emask, a_new, torch.zeros_like(a_new))
        if it > 0 and change < 1e-12:
            break
    rms = ((c * c).sum(-1) * vm).sum(1) / vm.sum(1)
    return c / rms.sqrt().clamp_min(1e-300)[:, None, None]


class RotationTranslation(SyncBackend):
    """Robust rotation averaging, then translation averaging (scale-free by default)."""

    name = "rotation_translation"
    Options = RotationTranslationOptions

    def _solve(self, struct: dict[str, Any], edge_pose: Tensor, edge_pose_gt: Tensor | None,
               comps: Components) -> SyncResult:
        o: RotationTranslationOptions = self.options  # type: ignore[assignment]
        R_e = edge_rotations(edge_pose)
        t_e = apply_scale_policy(edge_pose[:, 4:], o.scale, edge_pose_gt)
        prob = build_padded(struct["edge_index"], R_e, t_e, comps)
        G, n, m = prob.G, prob.n, prob.m
        dt, dev = prob.R.dtype, prob.R.device
        R = torch.eye(3, dtype=dt, device=dev).expand(G, n, 3, 3).clone()
        w_edge = torch.zeros(G, m, dtype=dt, device=dev)
        iters = torch.zeros(G, dtype=torch.long, device=dev)
        conv = torch.zeros(G, dtype=torch.bool, device=dev)
        w = struct.get("edge_weight")
        w_rot = None if w is None else padded_weights(prob, w[:, 0])
        groups = (split_by_size(prob, o.solver, o.dense_max_nodes) if w_rot is None
                  else [(torch.arange(G, device=dev), False)])
        for idx, krylov in groups:
            sub = prob.select(idx) if idx.numel() < G else prob
            if w_rot is not None:
                sol = weighted_rotation_irls(sub, w_rot[idx, :sub.m], o.robust, o.max_iters,
                                             o.tol, o.theta, o.weight_mode)
            else:
                sol = rotation_irls(sub, o.robust, o.max_iters, o.tol, o.theta, krylov,
                                    seed=o.seed)
            R[idx, :sub.n] = sol.R
            w_edge[idx, :sub.m] = sol.w_edge
            iters[idx], conv[idx] = sol.iterations, sol.converged
        R = refine_rotations(prob, R, o.refine_iters, o.robust, o.theta)
        if o.scale == "free":
            c = translations_from_directions(
                prob, R, o.translation_iters, o.robust, o.theta,
                w0=None if w is None else padded_weights(prob, w[:, 1]))
        else:
            c = translations_metric(prob, R, o.translation_iters, o.robust, o.theta)
        t = -(R @ c[..., None]).squeeze(-1)
        poses, solved, w, it, cv = assemble(struct, comps, prob, R, t, w_edge, iters, conv,
                                            edge_pose.dtype, edge_pose.device)
        return SyncResult(poses=poses, component=comps.comp, solved=solved, edge_weight=w,
                          iterations=it, converged=cv, scale=o.scale, metric=self.metric,
                          backend=self.name)

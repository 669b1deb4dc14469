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
  the translation stage (:func:`translation_stage`) drops edges without a usable direction
  (zero translation, or a translation weight of 0) and rotation outliers (residual above
  ``max_rotation_residual_deg``), solves the positions with ``translation`` = ``bata``
  (default) / ``lud`` (:mod:`posernet.sync.translation`; started from triangle-consistency
  weights) or ``linear`` (below), keeps the linear solution per component where it fits the
  kept directions better in summed angle, then drops edges whose baseline is more than
  ``max_direction_residual_deg`` off their direction and re-solves. Prunings that would cost a
  component its parallel rigidity are skipped there; ``SyncResult.info`` reports all of it.
  The ``linear`` solver:
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
  and RMS distance 1 to the centroid, axes those of each component's first camera: evaluate
  with a similarity alignment.
* ``scale`` in ``unit`` / ``given`` / ``oracle``: metric least squares
  ``min sum_e a_e |c_j - c_i - u_e|^2``, ``sum_i c_i = 0`` (weighted graph Laplacian), with the
  same Cauchy IRLS on ``|c_j - c_i - u_e|``.

Dense batched linear algebra on padded ``[G, n, n]`` / ``[G, 3n + 4, 3n + 4]`` systems; large
components use the Krylov eigen-solver of :mod:`posernet.sync.spectral` for the rotations,
and on the CPU (over ``posernet.sync.translation.SPARSE_MIN_NODES`` cameras) scipy's sparse
solvers for the linear KKT system and the parallel-rigidity test, whose dense forms grow as
``n^3``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..geometry import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle
from ..options import option
from ..scatter import scatter_all, scatter_any
from .backend import SyncBackend, SyncResult, apply_scale_policy, scale_option
from .components import Components
from .irls import rotation_irls
from .padding import PaddedProblem, assemble, build_padded, edge_rotations
from .robust import mad_cauchy_weights, mad_huber_weights
from .spectral import SpectralOptions, split_by_size
from .translation import (
    block_laplacian_dense,
    block_laplacian_sparse,
    direction_residual_deg,
    gather,
    incidence_rhs,
    laplacian_solve,
    mad_threshold,
    parallel_rigid,
    rotation_residual_deg,
    translations_bata,
    translations_lud,
    triangle_weights,
    use_sparse,
)
from .weighted import padded_weights, weight_mode_option

__all__ = ["TRANSLATION_METHODS", "RotationTranslation", "RotationTranslationOptions",
           "TranslationStage", "refine_rotations", "translation_stage",
           "translations_from_directions", "translations_metric"]

TRANSLATION_METHODS: tuple[str, ...] = ("bata", "lud", "linear")
#: largest component (cameras) that gets triangle-consistency start weights (dense n^3 work)
TRIANGLE_MAX_NODES = 96


@dataclass(frozen=True)
class RotationTranslationOptions(SpectralOptions):
    """:class:`~posernet.sync.spectral.SpectralOptions` for the spectral rotation IRLS (as
    EIG-SE3), plus

    * ``refine_iters``: geodesic refinement steps (0 = off);
    * ``translation``: the scale-free position solver, ``bata`` (default), ``lud`` or
      ``linear`` (the bearing least squares with Huber IRLS used before ``bata``);
    * ``translation_iters``: IRLS steps of the translation stage (``lud`` runs 5x as many: its
      alternation converges more slowly);
    * ``max_rotation_residual_deg``: edges whose residual ``|log(R_j^T R_e R_i)|`` after the
      rotation solve exceeds ``max(this, median + outlier_mad * 1.4826 * MAD)`` are left out of
      the translation stage (``None`` or 0 = keep all);
    * ``max_direction_residual_deg``: after the position solve, edges whose baseline is more
      than ``max(this, median + outlier_mad * 1.4826 * MAD)`` degrees from their direction are
      dropped and the positions re-solved (``None`` or 0 = off);
    * ``outlier_mad``: the MAD multiplier of both thresholds (noisy graphs raise them);
    * ``triangle_weights``: start the position solve from triangle-consistency weights
      (:func:`~posernet.sync.translation.triangle_weights`; components of up to
      :data:`TRIANGLE_MAX_NODES` cameras) -- the robust solvers only reach the right basin
      when wrong directions are already down-weighted at the start;
    * ``linear_fallback``: per component, keep the ``linear`` solution instead of the
      ``bata``/``lud`` one where it has the smaller summed angle between baselines and kept
      directions (guards sparse graphs against a redescending loss switching off needed edges);

    default scale ``free``. Both prunings are undone for a component where they would cost
    parallel rigidity (the positions would no longer be determined).
    """

    scale: str = scale_option("free")
    refine_iters: int = option(20, ge=0, help="Lie-algebraic IRLS steps after the spectral "
                               "solution (0 = off)")
    translation_iters: int = option(20, ge=1, help="IRLS steps of the translation stage (lud: "
                                    "5x)")
    weight_mode: str = weight_mode_option()
    translation: str = option("bata", choices=TRANSLATION_METHODS,
                              help="scale: free only -- position solver: bata "
                                   "(baseline-desensitised), lud (least unsquared deviations), "
                                   "linear (bearing least squares with Huber IRLS)")
    max_rotation_residual_deg: float | None = option(
        5.0, ge=0, le=180, help="edges with |log(R_j^T R_ij R_i)| above this after rotation "
        "averaging are left out of the translation stage (null: off)")
    max_direction_residual_deg: float | None = option(
        30.0, ge=0, le=180, help="edges with angle(c_j - c_i, direction) above this after the "
        "first position solve are dropped (null: off)")
    outlier_mad: float = option(3.0, ge=0, help="both thresholds are raised to median + this x "
                                "1.4826 x MAD on noisy graphs")
    triangle_weights: bool = option(True, help="start from triangle-consistency weights "
                                    "(components <= 96 cameras)")
    linear_fallback: bool = option(True, help="per component keep the linear solution where its "
                                   "summed angle is lower")


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


# shared with the robust translation solvers (:mod:`posernet.sync.translation`)
_incidence_rhs = incidence_rhs
_gather = gather


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
                        theta: float, keep: Tensor | None = None) -> Tensor:
    """Camera centres ``[G, n, 3]`` (mean 0) from metric world baselines; Cauchy IRLS.

    ``keep [G, m]``: edges to use (all when omitted); the others have no influence at all (a
    graph they split gets the tiny ridge of :func:`~posernet.sync.translation.laplacian_solve`).
    """
    u = _world_baselines(prob, R)
    mask = prob.edge_mask if keep is None else prob.edge_mask & keep
    w = mask.to(R.dtype)
    c = torch.zeros(prob.G, prob.n, 3, dtype=R.dtype, device=R.device)
    for _ in range(iters if robust else 1):
        if keep is None:
            c_new = torch.linalg.solve(_laplacian(prob, w), _incidence_rhs(prob, w, u))
        else:
            c_new = laplacian_solve(prob, w, u)
        c_new = c_new * prob.node_mask[..., None]
        change = float((c_new - c).abs().max())
        c = c_new
        if not robust:
            break
        r = (_gather(c, prob.dst) - _gather(c, prob.src) - u).norm(dim=-1)
        w = mad_cauchy_weights(r, mask, theta)
        w = torch.maximum(w, WEIGHT_FLOOR * mask.to(w.dtype))
        if change < 1e-12 * max(1.0, float(c.abs().max())):
            break
    return c


def translations_from_directions(prob: PaddedProblem, R: Tensor, iters: int, robust: bool,
                                 theta: float, ridge_rel: float = 1e-10,
                                 w0: Tensor | None = None,
                                 rigid: Callable[[Tensor], Tensor] | None = None) -> Tensor:
    """Scale-free camera centres ``[G, n, 3]`` (centroid 0, RMS radius 1) from directions.

    See the module docstring for the objective, constraints and reweighting. ``w0 [G, m]``:
    optional starting edge weights (per-edge confidence; uniform when omitted); an edge with
    ``w0 = 0`` is left out entirely (it has no usable direction or was pruned). A component left
    without any edge gets all its centres at 0. ``rigid``: :func:`parallel_rigid` of an edge
    mask ``[G, m]`` (e.g. a :func:`rigidity_memo`; computed here when omitted).
    """
    G, n = prob.G, prob.n
    dt, dev = R.dtype, R.device
    u = _world_baselines(prob, R)
    un = u.norm(dim=-1, keepdim=True)
    d = torch.where(un > 0, u / un.clamp_min(1e-300), torch.zeros_like(u))
    emask = prob.edge_mask & (un.squeeze(-1) > 0)
    if w0 is not None:
        emask = emask & (w0 > 0)
    empty = ~emask.any(1)
    P = torch.eye(3, dtype=dt, device=dev) - d[..., :, None] * d[..., None, :]
    vm = prob.node_mask.to(dt)
    a = emask.to(dt) if w0 is None else torch.where(emask, w0.to(dt), torch.zeros_like(w0))
    c = torch.zeros(G, n, 3, dtype=dt, device=dev)
    sparse = use_sparse(n, dev)
    # The ridge's bias is refined away only where the edges fix the positions: elsewhere the
    # refinement walks along the null space by round-off / ridge, so the answer would depend on
    # the device's arithmetic instead of being the ridge's (minimum-norm-like) choice.
    exact = None if sparse else (rigid or rigidity_memo(prob))(emask)
    for it in range(iters if robust else 1):
        aP = a[..., None, None] * P
        if sparse:
            C = _constraint_rows(prob, a, d, vm)
            # large components come one per group (split_by_size): a loop of one or few
            c_new = torch.stack([
                _kkt_solve_sparse(prob.src[g], prob.dst[g], aP[g], C[g], bool(empty[g]),
                                  float(a[g].sum()), ridge_rel, vm[g]) for g in range(G)])
        else:
            c_new = _kkt_solve_dense(prob, aP, a, d, vm, empty, ridge_rel, exact)
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


#: relative ridge of a component whose edges do not fix its positions
NONRIGID_RIDGE = 1e-10


def _constraint_rows(prob: PaddedProblem, a: Tensor, d: Tensor, vm: Tensor) -> Tensor:
    """``[G, 4, 3n]``: sum_i c_i = 0 (3 rows) and sum_e a_e d_e . (c_j - c_i) = sum_e a_e."""
    G, n = prob.G, prob.n
    C = torch.zeros(G, 4, n, 3, dtype=a.dtype, device=a.device)
    C[:, :3] = (torch.eye(3, dtype=a.dtype, device=a.device)[None, :, None, :]
                * vm[:, None, :, None])
    C[:, 3] = _incidence_rhs(prob, a, d)  # sum_e a_e d_e, added at j, subtracted at i
    return C.reshape(G, 4, 3 * n)


def _kkt_solve_dense(prob: PaddedProblem, aP: Tensor, a: Tensor, d: Tensor, vm: Tensor,
                     empty: Tensor, ridge_rel: float, exact: Tensor) -> Tensor:
    """One weighted solve of :func:`translations_from_directions`, dense and batched
    (``aP [G, m, 3, 3]``: each edge's weight times its projector): the centres ``[G, n, 3]``.
    ``exact [G]`` bool: remove the ridge's bias (components whose edges fix the positions)."""
    G, n = prob.G, prob.n
    dt, dev = a.dtype, a.device
    size = 3 * n + 4
    K = block_laplacian_dense(prob, aP)
    scale = K.diagonal(dim1=-2, dim2=-1).mean(-1)
    scale = torch.where(empty, torch.ones_like(scale), scale.clamp_min(1e-300))
    A = torch.zeros(G, size, size, dtype=dt, device=dev)
    A[:, :3 * n, :3 * n] = 2.0 * K
    C = _constraint_rows(prob, a, d, vm)
    A[:, 3 * n:, :3 * n] = C
    A[:, :3 * n, 3 * n:] = C.mT
    # No edge at all: the scale row is empty; a unit multiplier keeps the system regular.
    A[:, -1, -1] = empty.to(dt)
    # Padded unknowns: identity rows keep them at 0.
    A[:, :3 * n, :3 * n] += torch.diag_embed(1.0 - vm.repeat_interleave(3, dim=1))
    rhs = torch.zeros(G, size, 1, dtype=dt, device=dev)
    rhs[:, -1, 0] = a.sum(1)
    # A small ridge keeps non-parallel-rigid graphs solvable (minimum-norm-like answer);
    # two steps of iterative refinement against the unridged system remove its bias where the
    # graph is rigid.
    ridge = torch.zeros(G, size, dtype=dt, device=dev)
    # where the positions are not fixed, a ridge well above round-off makes that choice one
    # answer on every device (its bias, 1e-6 of the scale, is below any position's accuracy)
    rel = torch.where(exact, torch.full_like(scale, ridge_rel),
                      torch.full_like(scale, max(ridge_rel, NONRIGID_RIDGE)))
    ridge[:, :3 * n] = (rel * scale)[:, None] * vm.repeat_interleave(3, dim=1)
    LU, piv = torch.linalg.lu_factor(A + torch.diag_embed(ridge))
    sol = torch.linalg.lu_solve(LU, piv, rhs)
    step = exact.to(dt)[:, None, None]
    for _ in range(2):
        sol = sol + step * torch.linalg.lu_solve(LU, piv, rhs - A @ sol)
    return sol.squeeze(-1)[:, :3 * n].view(G, n, 3) * vm[..., None]


def _kkt_solve_sparse(src: Tensor, dst: Tensor, aP: Tensor, C: Tensor, empty: bool,
                      total: float, ridge_rel: float, vm: Tensor) -> Tensor:
    """The solve of :func:`_kkt_solve_dense` for one large component, as a sparse system
    (scipy's LU; the block structure of the graph Laplacian): the centres ``[n, 3]``."""
    import numpy as np
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    n = vm.shape[0]
    size = 3 * n + 4
    K2 = block_laplacian_sparse(src, dst, 2.0 * aP, n).tocoo()
    rows, cols, vals = [K2.row], [K2.col], [K2.data]
    Cn = C.detach().cpu().numpy()
    cr, cc = np.nonzero(Cn)
    rows += [cr + 3 * n, cc]
    cols += [cc, cr + 3 * n]
    vals += [Cn[cr, cc], Cn[cr, cc]]
    pad = 1.0 - vm.detach().cpu().numpy().repeat(3)
    diag = np.concatenate([pad, np.zeros(3), [1.0 if empty else 0.0]])
    A = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(size, size)).tocsc() + sp.diags(diag)
    # the dense solve's ridge scale: the mean diagonal of K over all 3n unknowns
    scale = 1.0 if empty else max(float((A.diagonal()[:3 * n] - pad).sum()) / (6 * n), 1e-300)
    ridge = np.zeros(size)
    ridge[:3 * n] = ridge_rel * scale * (pad == 0)
    rhs = np.zeros(size)
    rhs[-1] = total
    # a symmetric fill-reducing order (the system is symmetric; its 4 dense constraint rows
    # and columns go last) and a preference for diagonal pivots
    lu = splu((A + sp.diags(ridge)).tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.1)
    sol = lu.solve(rhs)
    for _ in range(2):  # iterative refinement against the unridged system, as the dense solve
        sol = sol + lu.solve(rhs - A @ sol)
    out = torch.from_numpy(sol[:3 * n].reshape(n, 3)).to(dtype=aP.dtype, device=aP.device)
    return out * vm[:, None]


@dataclass
class TranslationStage:
    """What the scale-free translation stage did, per padded edge ``[G, m]`` / component
    ``[G]``: ``c [G, n, 3]`` centres (centroid 0, RMS 1); ``usable`` edges with a direction
    (non-zero translation and translation weight); ``rotation_outlier`` / ``direction_outlier``
    edges the prunings dropped; ``used`` the edges of the final solve; ``weight`` their final
    translation weights (0 elsewhere); ``rotation_residual`` / ``direction_residual`` in degrees;
    ``rigid`` whether the used edges make the component parallel rigid (if not, some relative
    positions are undetermined and the answer is only one finite choice among many);
    ``fallback [G]`` the linear solution was kept (``linear_fallback``)."""

    c: Tensor
    usable: Tensor
    rotation_outlier: Tensor
    direction_outlier: Tensor
    used: Tensor
    weight: Tensor
    rotation_residual: Tensor
    direction_residual: Tensor
    rigid: Tensor
    fallback: Tensor


def rigidity_memo(prob: PaddedProblem) -> Callable[[Tensor], Tensor]:
    """:func:`parallel_rigid` of ``prob`` for an edge mask ``[G, m]`` -> ``[G]``, computed once
    per distinct mask: a translation stage asks about the same edge sets several times (an
    eigen-solve of every component each time)."""
    seen: dict[bytes, Tensor] = {}

    def rigid(mask: Tensor) -> Tensor:
        key = mask.detach().cpu().numpy().tobytes()
        if key not in seen:
            seen[key] = parallel_rigid(prob, mask)
        return seen[key]

    return rigid


def _solve_positions(prob: PaddedProblem, R: Tensor, d: Tensor, keep: Tensor, w_start: Tensor,
                     w_prior: Tensor, c0: Tensor | None, o: RotationTranslationOptions,
                     rigid: Callable[[Tensor], Tensor]) -> tuple[Tensor, Tensor]:
    """Centres ``[G, n, 3]`` and final weights ``[G, m]`` from the edges ``keep`` with the
    chosen method; ``c0`` a start (``None``: the linear solution); ``rigid`` as in
    :func:`translations_from_directions`."""
    km = keep.to(R.dtype)
    if o.translation == "linear":
        c = translations_from_directions(prob, R, o.translation_iters, o.robust, o.theta,
                                         w0=w_start * km, rigid=rigid)
        return c, km
    if c0 is None:
        # One weighted bearing solve, no re-weighting: the Huber IRLS of the linear method
        # forgets the start weights and lets edges collapse onto wrong directions (its 1 / l^2
        # factor rewards short baselines), a worse start than the plain weighted solution.
        c0 = translations_from_directions(prob, R, 1, False, o.theta, w0=w_start * km,
                                          rigid=rigid)
    if o.translation == "bata":
        return translations_bata(prob, d, keep, w_prior * km, c0, o.translation_iters, o.theta)
    return translations_lud(prob, d, keep, w_prior * km, c0, 5 * o.translation_iters)


def translation_stage(prob: PaddedProblem, R: Tensor, o: RotationTranslationOptions,
                      w_t: Tensor | None = None) -> TranslationStage:
    """Scale-free positions from the edge directions and the averaged rotations ``R``.

    1. usable edges: a non-zero translation and, when given, a translation weight ``w_t > 0``
       (``w_t [G, m]`` from :func:`~posernet.sync.weighted.padded_weights` with zeros kept);
    2. rotation outliers (residual above ``max_rotation_residual_deg``, MAD-aware) are dropped:
       a bad relative rotation usually comes with a bad direction, and the IRLS of the rotation
       stage has already named them;
    3. positions by ``o.translation`` (``bata``/``lud`` start from the one-shot weighted linear
       solution, weighted by triangle consistency when ``o.triangle_weights``), or the linear
       IRLS solution where that fits better in summed angle (``o.linear_fallback``);
    4. direction outliers (angle between ``c_j - c_i`` and ``d_e`` above
       ``max_direction_residual_deg``, MAD-aware) are dropped and the positions re-solved.

    A pruning that would cost a component its parallel rigidity is not applied there. A
    component that the kept edges leave non-rigid has no direction pruning and gets the one
    weighted linear solve: its positions are then one choice among many, the same on every
    device.
    """
    u = _world_baselines(prob, R)
    un = u.norm(dim=-1)
    d = u / un.clamp_min(1e-300)[..., None]
    usable = prob.edge_mask & (un > 0)
    if w_t is not None:
        usable = usable & (w_t > 0)
    ones = prob.edge_mask.to(R.dtype)
    w_start = w_user = ones if w_t is None else w_t
    w_prior = w_start if o.weight_mode == "prior" else ones
    rot_res = rotation_residual_deg(prob, R)
    none = torch.zeros_like(usable)
    rigid_of = rigidity_memo(prob)
    keep, rot_out = usable, none
    if o.max_rotation_residual_deg:
        th = mad_threshold(rot_res, prob.edge_mask, float(o.max_rotation_residual_deg),
                           o.outlier_mad)
        rot_out = usable & (rot_res > th[:, None])
        if bool(rot_out.any()):
            ok = rigid_of(usable & ~rot_out) | ~rigid_of(usable)
            rot_out = rot_out & ok[:, None]
            keep = usable & ~rot_out
    if o.triangle_weights and prob.n <= TRIANGLE_MAX_NODES:
        w_start = w_start * triangle_weights(prob, d, keep, 3.0, 2.0)
    c, w = _solve_positions(prob, R, d, keep, w_start, w_prior, None, o, rigid_of)
    fallback = torch.zeros(prob.G, dtype=torch.bool, device=R.device)
    if o.linear_fallback and o.translation != "linear":
        # A redescending loss can switch off edges a sparse graph needs, and a bad start can
        # leave the robust solvers in a wrong basin; where the linear solution fits the kept
        # directions better in summed angle (an L1 criterion neither solver minimises), it is
        # kept. Measured: removes the regression on sparse, outlier-free 8-camera graphs and
        # keeps the gains on graphs with wrong directions.
        c_lin = translations_from_directions(prob, R, o.translation_iters, o.robust, o.theta,
                                             w0=w_user * keep.to(R.dtype), rigid=rigid_of)
        km = keep.to(R.dtype)
        l1_lin = (direction_residual_deg(prob, c_lin, d) * km).sum(1)
        l1_rob = (direction_residual_deg(prob, c, d) * km).sum(1)
        fallback = l1_lin < l1_rob
        c = torch.where(fallback[:, None, None], c_lin, c)
        w = torch.where(fallback[:, None], km, w)
    dir_out = none
    if o.max_direction_residual_deg:
        ang = direction_residual_deg(prob, c, d)
        th = mad_threshold(ang, keep, float(o.max_direction_residual_deg), o.outlier_mad)
        cand = keep & (ang > th[:, None])
        if bool(cand.any()):
            # only where the rest still fixes the positions: where the kept edges never did,
            # the robust residuals measure one arbitrary choice among many (round-off picks
            # it, so CPU and CUDA would prune different edges)
            ok = cand.any(1) & rigid_of(keep & ~cand)
            if bool(ok.any()):
                dir_out = cand & ok[:, None]
                keep2 = keep & ~dir_out
                c2, w2 = _solve_positions(prob, R, d, keep2, w_start, w_prior, c, o, rigid_of)
                c = torch.where(ok[:, None, None], c2, c)
                w = torch.where(ok[:, None], w2, w)
                keep = keep2
    rigid = rigid_of(keep)
    if not bool(rigid.all()):
        # Where the kept edges leave positions free, every reweighting reads lengths the data
        # do not fix (1 / |b|^2, residual angles of free edges), so the robust answers go
        # wherever round-off sends them (float32 confidence weights on CPU vs CUDA: cameras
        # 1.5 apart). Such a component gets the one linear solve: one answer, the ridge's.
        km = keep.to(R.dtype)
        c_lin = translations_from_directions(prob, R, 1, False, o.theta, w0=w_start * km,
                                             rigid=rigid_of)
        c = torch.where(rigid[:, None, None], c, c_lin)
        w = torch.where(rigid[:, None], w, km * w_start)
    return TranslationStage(
        c=c, usable=usable, rotation_outlier=rot_out, direction_outlier=dir_out, used=keep,
        weight=torch.where(keep, w, torch.zeros_like(w)), rotation_residual=rot_res,
        direction_residual=direction_residual_deg(prob, c, d), rigid=rigid, fallback=fallback)


class RotationTranslation(SyncBackend):
    """Robust rotation averaging, then translation averaging (scale-free by default).

    With ``scale="free"``, ``SyncResult.info`` holds the translation stage's report: per edge
    ``[E]`` ``rotation_residual_deg``, ``direction_residual_deg``, ``rotation_outlier`` and
    ``direction_outlier`` (dropped by the prunings), ``translation_usable`` (has a direction),
    ``translation_used`` (in the final position solve) and ``translation_weight`` (its final
    weight, 0 where not used); per graph ``[B]`` ``parallel_rigid`` (False: the used edges leave
    some relative positions undetermined, the positions returned are one finite choice) and
    ``linear_fallback`` (some component kept the linear solution).
    ``SyncResult.edge_weight`` stays the rotation stage's robust weights.
    """

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
        for idx, krylov in split_by_size(prob, o.solver, o.dense_max_nodes):
            sub = prob.select(idx) if idx.numel() < G else prob
            sol = rotation_irls(sub, o.robust, o.max_iters, o.tol, o.theta, krylov, seed=o.seed,
                                w0=None if w_rot is None else w_rot[idx, :sub.m],
                                prior=o.weight_mode == "prior")
            R[idx, :sub.n] = sol.R
            w_edge[idx, :sub.m] = sol.w_edge
            iters[idx], conv[idx] = sol.iterations, sol.converged
        R = refine_rotations(prob, R, o.refine_iters, o.robust, o.theta)
        info: dict[str, Any] = {}
        w_t = None if w is None else padded_weights(prob, w[:, 1], keep_zero=True)
        if o.scale == "free":
            st = translation_stage(prob, R, o, w_t)
            c = st.c
            info = self._stage_info(struct, comps, prob, st)
        else:
            keep = None if w_t is None else w_t > 0
            c = translations_metric(prob, R, o.translation_iters, o.robust, o.theta, keep)
        # One gauge on every device: the world axes are those of each component's first camera.
        # The spectral rotations' gauge is an eigenbasis, which round-off alone can turn (a
        # 1e-13 move of the input turned every camera by 90+ deg, residuals unchanged).
        R0 = R[:, :1]
        R = R @ R0.mT
        c = (R0 @ c[..., None]).squeeze(-1)
        t = -(R @ c[..., None]).squeeze(-1)
        poses, solved, w, it, cv = assemble(struct, comps, prob, R, t, w_edge, iters, conv,
                                            edge_pose.dtype, edge_pose.device)
        return SyncResult(poses=poses, component=comps.comp, solved=solved, edge_weight=w,
                          iterations=it, converged=cv, scale=o.scale, metric=self.metric,
                          backend=self.name, info=info)

    @staticmethod
    def _stage_info(struct: dict[str, Any], comps: Components, prob: PaddedProblem,
                    st: TranslationStage) -> dict[str, Any]:
        """The translation stage's per-edge ``[E]`` and per-graph ``[B]`` report (see
        :class:`RotationTranslation`)."""
        E, B = struct["edge_index"].shape[1], struct["num_graphs"]
        dev = struct["edge_index"].device
        sel, ids = prob.edge_mask, prob.edge[prob.edge_mask]

        def per_edge(x: Tensor, fill: float | bool) -> Tensor:
            out = torch.full((E,), fill, dtype=x.dtype, device=dev)
            out[ids] = x[sel]
            return out

        # per graph: all its components rigid / any fell back (no bool scatter_reduce on CUDA)
        graph = comps.graph[prob.comp_id]
        rigid = scatter_all(st.rigid, graph, B)
        fallback = scatter_any(st.fallback, graph, B)
        return {
            "rotation_residual_deg": per_edge(st.rotation_residual, 0.0),
            "direction_residual_deg": per_edge(st.direction_residual, 0.0),
            "rotation_outlier": per_edge(st.rotation_outlier, False),
            "direction_outlier": per_edge(st.direction_outlier, False),
            "translation_usable": per_edge(st.usable, False),
            "translation_used": per_edge(st.used, False),
            "translation_weight": per_edge(st.weight, 0.0),
            "parallel_rigid": rigid,
            "linear_fallback": fallback,
        }

"""Robust translation (camera-position) averaging from unit directions, and the edge pruning
around it, batched over the padded components of :mod:`posernet.sync.padding`.

Notation: edge ``e = i -> j`` of a component, ``c_i`` camera centres (world), ``d_e`` the unit
world-frame direction of ``c_j - c_i`` measured by the edge (after rotation averaging),
``b_e = c_j - c_i`` the current baseline. ``keep [G, m]`` marks the edges the stage may use.

Solvers (all IRLS on one weighted graph Laplacian per component, i.e. three independent
``n x n`` systems that share a matrix; nothing loops over edges):

* :func:`translations_bata` -- baseline-desensitised averaging (after Zhuang, Cheong & Lee,
  CVPR 2018): minimise ``sum_e rho(|s_e b_e - d_e|)`` with ``s_e = 1 / |b_e|`` taken from the
  previous iterate, so the residual is the chord between the unit vectors ``b_e / |b_e|`` and
  ``d_e`` (at most 2) whatever the baseline length; ``rho`` is redescending (Cauchy, MAD
  threshold), so a direction that is 30+ degrees off ends with a weight near 0 instead of the
  bounded-but-constant pull it keeps under a Huber loss.
* :func:`translations_lud` -- least unsquared deviations (after Ozyesil & Singer, CVPR 2015):
  ``min sum_e |c_j - c_i - s_e d_e|`` with ``s_e >= 1`` (which also fixes the scale), by IRLS on
  ``c`` alternated with the closed-form ``s_e = max(1, b_e . d_e)``.

Start weights: :func:`triangle_weights` (direction consistency of the graph's triangles).
Pruning helpers: :func:`rotation_residual_deg` (angle of ``R_j^T R_e R_i``),
:func:`direction_residual_deg` (angle between ``b_e`` and ``d_e``), :func:`mad_threshold`
(a fixed floor raised to ``median + k * 1.4826 * MAD`` on noisy graphs) and
:func:`parallel_rigid`, which tells whether the kept edges still fix every camera position up
to one global translation and scale.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ..geometry import rotation_matrix_to_axis_angle
from .padding import PaddedProblem
from .robust import batch_median, mad_cauchy_weights

__all__ = [
    "block_laplacian_dense",
    "block_laplacian_sparse",
    "direction_residual_deg",
    "laplacian_solve",
    "mad_threshold",
    "parallel_rigid",
    "rotation_residual_deg",
    "translations_bata",
    "translations_lud",
    "triangle_residuals",
    "triangle_weights",
    "unit_rms",
]

#: relative ridge of :func:`laplacian_solve`: keeps a kept-edge graph that fell apart solvable
RIDGE = 1e-10
#: entries of the ``[G, n, n, n]`` triangle tensors per chunk of components (memory bound)
TRIANGLE_CHUNK = 1 << 21


def gather(x: Tensor, idx: Tensor) -> Tensor:
    """``x[g, idx[g, e]]`` for ``x [G, n, ...]``, ``idx [G, m]``."""
    gi = torch.arange(x.shape[0], device=x.device)[:, None].expand_as(idx)
    return x[gi, idx]


def incidence_rhs(prob: PaddedProblem, w: Tensor, v: Tensor) -> Tensor:
    """``B^T W v [G, n, k]``: for each edge ``e = i -> j`` add ``w v`` at ``j``, subtract at
    ``i`` (``w [G, m]``, ``v [G, m, k]``)."""
    G, n = prob.G, prob.n
    out = torch.zeros(G * n, v.shape[-1], dtype=v.dtype, device=v.device)
    base = torch.arange(G, device=v.device)[:, None] * n
    wv = (w[..., None] * v).reshape(-1, v.shape[-1])
    out.index_add_(0, (base + prob.dst).flatten(), wv)
    out.index_add_(0, (base + prob.src).flatten(), -wv)
    return out.view(G, n, -1)


def baselines(prob: PaddedProblem, c: Tensor) -> Tensor:
    """``b_e = c_j - c_i [G, m, 3]`` for centres ``c [G, n, 3]``."""
    return gather(c, prob.dst) - gather(c, prob.src)


def unit_rms(prob: PaddedProblem, c: Tensor) -> Tensor:
    """Centres ``c [G, n, 3]`` moved to centroid 0 and scaled to RMS radius 1 (pads stay 0)."""
    vm = prob.node_mask.to(c.dtype)[..., None]
    cnt = prob.count.to(c.dtype)[:, None, None]
    c = (c - (c * vm).sum(1, keepdim=True) / cnt) * vm
    rms = ((c * c).sum((1, 2)) / prob.count.to(c.dtype)).sqrt()
    return c / rms.clamp_min(1e-300)[:, None, None]


def laplacian_solve(prob: PaddedProblem, w: Tensor, target: Tensor) -> Tensor:
    """``argmin_c sum_e w_e |c_j - c_i - target_e|^2`` with ``sum_i c_i = 0`` ``[G, n, 3]``.

    ``w [G, m]`` (0 = edge unused), ``target [G, m, 3]``. Edges of weight 0 may split the
    component: a tiny ridge (:data:`RIDGE` times the mean degree) keeps the system regular and
    puts each piece near the origin (their relative placement is undetermined; the caller
    flags it); one step of iterative refinement against the unridged matrix removes the
    ridge's bias where the graph is connected.
    """
    G, n = prob.G, prob.n
    dt, dev = w.dtype, w.device
    vm = prob.node_mask.to(dt)
    deg = _mean_degree(prob, w)
    if use_sparse(n, dev) and not (w.requires_grad or target.requires_grad):
        return _laplacian_solve_sparse(prob, w, incidence_rhs(prob, w, target), deg) \
            * vm[..., None]
    gi = torch.arange(G, device=dev)[:, None].expand(G, prob.m)
    L = torch.zeros(G, n, n, dtype=dt, device=dev)
    L.index_put_((gi, prob.src, prob.dst), -w, accumulate=True)
    L.index_put_((gi, prob.dst, prob.src), -w, accumulate=True)
    L = L + torch.diag_embed(-L.sum(-1))
    cnt = prob.count.to(dt)
    # gauge (mean 0) with the strength of a typical node, identity on padded nodes
    L = L + deg.clamp_min(1e-300)[:, None, None] * vm[:, :, None] * vm[:, None, :] / cnt[:, None,
                                                                                       None]
    L = L + torch.diag_embed(1.0 - vm)
    Lr = L + torch.diag_embed((RIDGE * deg.clamp_min(1e-300))[:, None] * vm)
    rhs = incidence_rhs(prob, w, target)
    LU, piv = torch.linalg.lu_factor(Lr)
    c = torch.linalg.lu_solve(LU, piv, rhs)
    c = c + torch.linalg.lu_solve(LU, piv, rhs - L @ c)
    return c * vm[..., None]


def _mean_degree(prob: PaddedProblem, w: Tensor) -> Tensor:
    """``[G]``: the mean weighted degree of each component, the scale of
    :func:`laplacian_solve`'s gauge and ridge (1 where no edge is left: any scale will do)."""
    total = 2 * torch.where(prob.edge_mask, w, torch.zeros_like(w)).sum(1)
    deg = total / prob.count.to(w.dtype)
    return torch.where(deg > 0, deg, torch.ones_like(deg))


def _laplacian_solve_sparse(prob: PaddedProblem, w: Tensor, rhs: Tensor, deg: Tensor) -> Tensor:
    """The system of :func:`laplacian_solve` (same gauge, ridge and refinement step) for large
    components on the CPU, one component at a time: scipy's sparse LU of the Laplacian with
    its rank-one gauge term as one bordered row and column (``[L_r, a^1/2 v; a^1/2 v^T, -1]``
    eliminates to ``L_r + a v v^T``), where the dense form is an ``n^3`` LU."""
    import numpy as np
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    out = torch.zeros_like(rhs)
    for g in range(prob.G):
        em, vm = prob.edge_mask[g], prob.node_mask[g].to(w.dtype)
        i, j, ww = prob.src[g, em].numpy(), prob.dst[g, em].numpy(), w[g, em].numpy()
        n, a = prob.n, float(deg[g]) / float(prob.count[g])
        v = vm.numpy()
        L = sp.coo_matrix((np.concatenate([-ww, -ww, ww, ww]),
                           (np.concatenate([i, j, i, j]), np.concatenate([j, i, i, j]))),
                          shape=(n, n)).tocsc()
        L = L + sp.diags(1.0 - v)  # identity on padded nodes
        ridge = sp.diags(RIDGE * float(deg[g]) * v)
        border = sp.csc_matrix(np.sqrt(a) * v[:, None])
        K = sp.bmat([[L + ridge, border], [border.T, sp.csc_matrix([[-1.0]])]], format="csc")
        lu = splu(K, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.1)
        b = rhs[g].numpy()

        def solve(r: np.ndarray, lu=lu, n=n) -> np.ndarray:
            return lu.solve(np.vstack([r, np.zeros((1, r.shape[1]))]))[:n]

        c = solve(b)
        c = c + solve(b - (L @ c + a * np.outer(v, v @ c)))  # refine against the unridged one
        out[g] = torch.from_numpy(c)
    return out


def mad_threshold(x: Tensor, mask: Tensor, floor: float, k: float) -> Tensor:
    """Per-row outlier threshold ``max(floor, median + k * 1.4826 * MAD)`` ``[G]`` of the masked
    entries of ``x [G, m]``: the fixed ``floor`` on clean graphs, higher where the inliers
    themselves are noisy (so a noisy graph is not stripped of most of its edges)."""
    med = batch_median(x, mask)
    mad = batch_median((x - med[:, None]).abs(), mask)
    th = torch.nan_to_num(med + k * 1.4826 * mad, nan=floor)
    return th.clamp_min(floor)


def rotation_residual_deg(prob: PaddedProblem, R: Tensor) -> Tensor:
    """Angle of ``R_j^T R_e R_i`` in degrees ``[G, m]`` (0 on pads) for absolute rotations
    ``R [G, n, 3, 3]``: how far edge ``e`` disagrees with the averaged rotations."""
    E = gather(R, prob.dst).mT @ prob.R @ gather(R, prob.src)
    ang = torch.rad2deg(rotation_matrix_to_axis_angle(E).norm(dim=-1))
    return torch.where(prob.edge_mask, ang, torch.zeros_like(ang))


def direction_residual_deg(prob: PaddedProblem, c: Tensor, d: Tensor) -> Tensor:
    """Angle between the baseline ``c_j - c_i`` and the measured direction ``d_e`` in degrees
    ``[G, m]`` (0 on pads; 180 where the two centres coincide)."""
    b = baselines(prob, c)
    cos = (b * d).sum(-1) / b.norm(dim=-1).clamp_min(1e-300)
    ang = torch.rad2deg(torch.arccos(cos.clamp(-1.0, 1.0)))
    return torch.where(prob.edge_mask, ang, torch.zeros_like(ang))


#: components with more cameras than this take the sparse CPU paths (the dense 3n x 3n
#: eigen- and LU solves grow as n^3: seconds per call at 1024 cameras)
SPARSE_MIN_NODES = 128


def use_sparse(n: int, device: torch.device) -> bool:
    """Whether components padded to ``n`` cameras on ``device`` are solved sparsely."""
    return n > SPARSE_MIN_NODES and device.type == "cpu"


def block_laplacian_dense(prob: PaddedProblem, blocks: Tensor) -> Tensor:
    """``[G, 3n, 3n]``: per component, ``sum_e`` of ``blocks [G, m, 3, 3]`` on each edge's
    incidence (``+B`` at ``(i, i)`` and ``(j, j)``, ``-B`` at ``(i, j)`` and ``(j, i)``)."""
    G, n = prob.G, prob.n
    gi = torch.arange(G, device=blocks.device)[:, None].expand(G, prob.m)
    K = torch.zeros(G, n, n, 3, 3, dtype=blocks.dtype, device=blocks.device)
    K.index_put_((gi, prob.src, prob.src), blocks, accumulate=True)
    K.index_put_((gi, prob.dst, prob.dst), blocks, accumulate=True)
    K.index_put_((gi, prob.src, prob.dst), -blocks, accumulate=True)
    K.index_put_((gi, prob.dst, prob.src), -blocks, accumulate=True)
    return K.permute(0, 1, 3, 2, 4).reshape(G, 3 * n, 3 * n)


def block_laplacian_sparse(src: Tensor, dst: Tensor, blocks: Tensor, n: int) -> Any:
    """The ``3n x 3n`` scipy CSC matrix ``sum_e`` of ``blocks [m, 3, 3]`` on each edge's
    incidence (``+B`` at ``(i, i)`` and ``(j, j)``, ``-B`` at ``(i, j)`` and ``(j, i)``, for
    ``src``/``dst [m]``): the sparse form of the dense ``[3n, 3n]`` matrices built here."""
    import numpy as np
    import scipy.sparse as sp

    i, j = src.cpu().numpy(), dst.cpu().numpy()
    blk = blocks.detach().cpu().numpy()
    r3 = np.arange(3)
    rows, cols, vals = [], [], []
    for p, q, sign in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
        rows.append((3 * p[:, None, None] + r3[None, :, None]).repeat(3, 2).ravel())
        cols.append((3 * q[:, None, None] + r3[None, None, :]).repeat(3, 1).ravel())
        vals.append((sign * blk).ravel())
    return sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(3 * n, 3 * n)).tocsc()


def _null_dims_sparse(K: Any, top: float, k: int = 5) -> int:
    """How many eigenvalues of the PSD scipy matrix ``K`` are below ``1e-9 * top`` (counting
    at most ``k``): its ``k`` smallest, by shift-invert just below 0."""
    from scipy.sparse.linalg import eigsh

    k = min(k, K.shape[0] - 1)
    ev = eigsh(K, k=k, sigma=-1e-6 * top, which="LM", return_eigenvectors=False)
    return int((ev < 1e-9 * top).sum())


def parallel_rigid(prob: PaddedProblem, keep: Tensor, seed: int = 0) -> Tensor:
    """Whether the edges ``keep [G, m]`` make each component parallel rigid ``[G]`` bool.

    Parallel rigidity (a generic property of the graph) means directions on these edges fix
    every centre up to one global translation and scale. Test: exact directions of a random
    generic configuration; the bearing matrix ``sum_e P_e`` (``P_e = I - d_e d_e^T`` on the
    edge's incidence) then has a null space of dimension exactly 4 (3 translations + scale)
    iff the graph is rigid; a graph that fell apart or hangs on a chain has more.
    """
    G, n = prob.G, prob.n
    dt, dev = torch.float64, prob.R.device
    gen = torch.Generator().manual_seed(seed)
    X = torch.randn(G, n, 3, generator=gen, dtype=dt).to(dev)
    d = torch.nn.functional.normalize(baselines(prob, X), dim=-1)
    P = torch.eye(3, dtype=dt, device=dev) - d[..., :, None] * d[..., None, :]
    P = P * keep.to(dt)[..., None, None]
    if use_sparse(n, torch.device(dev)):
        return _parallel_rigid_sparse(prob, P)
    K = block_laplacian_dense(prob, P)
    pad = 1.0 - prob.node_mask.to(dt).repeat_interleave(3, dim=1)
    top = K.diagonal(dim1=-2, dim2=-1).amax(-1).clamp_min(1.0)
    K = K + torch.diag_embed(pad * top[:, None])  # padded unknowns: eigenvalue >= the scale
    ev = torch.linalg.eigvalsh(K)
    null = (ev < 1e-9 * ev[:, -1:].clamp_min(1e-300)).sum(-1)
    return null == 4


def _parallel_rigid_sparse(prob: PaddedProblem, P: Tensor) -> Tensor:
    """:func:`parallel_rigid` for large components, one at a time: the null space of the
    sparse bearing matrix from its 5 smallest eigenvalues (``P [G, m, 3, 3]``: the edges'
    projectors, zero on edges left out). The threshold is relative to the largest diagonal
    entry (within 2x of the largest eigenvalue, which sets the dense test's threshold)."""
    import numpy as np
    import scipy.sparse as sp

    out = torch.zeros(prob.G, dtype=torch.bool)
    for g in range(prob.G):
        K = block_laplacian_sparse(prob.src[g], prob.dst[g], P[g], prob.n)
        diag = K.diagonal()
        top = max(float(diag.max()), 1.0)
        pad = 1.0 - prob.node_mask[g].cpu().numpy().repeat(3).astype(np.float64)
        K = (K + sp.diags(pad * top)).tocsc()
        out[g] = _null_dims_sparse(K, top) == 4
    return out.to(prob.R.device)


def _chord_weights(prob: PaddedProblem, b: Tensor, d: Tensor, keep: Tensor,
                   theta: float) -> Tensor:
    """Cauchy weights (MAD threshold) on the chord ``|b / |b| - d|`` ``[G, m]``."""
    u = b / b.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    r = (u - d).norm(dim=-1)
    return mad_cauchy_weights(r, keep, theta)


def translations_bata(prob: PaddedProblem, d: Tensor, keep: Tensor, w0: Tensor, c0: Tensor,
                      iters: int, theta: float, tol: float = 1e-10) -> tuple[Tensor, Tensor]:
    """Baseline-desensitised robust centres ``[G, n, 3]`` (centroid 0, RMS 1) and the final
    weights ``[G, m]``.

    ``d [G, m, 3]`` unit directions; ``keep [G, m]`` usable edges; ``w0 [G, m]`` prior
    (confidence) weights, kept as a factor of every robust weight; ``c0 [G, n, 3]`` the start
    (e.g. the linear solution). Each step fixes ``s_e = 1 / |b_e|`` and the Cauchy weight
    ``k_e`` of the chord residual, and solves ``min sum_e w0_e k_e |s_e b_e - d_e|^2``, i.e. the
    Laplacian system with weights ``w0 k / l^2`` and targets ``l d`` (``l = |b|``).
    """
    c = unit_rms(prob, c0)
    km = keep.to(c.dtype)
    w = km
    for _ in range(iters):
        b = baselines(prob, c)
        ln = b.norm(dim=-1)
        mean_l = (ln * km).sum(1) / km.sum(1).clamp_min(1)
        # Centres that (nearly) coincide would get an unbounded weight 1 / l^2; a floor at a
        # small fraction of the typical baseline bounds it.
        ln = torch.maximum(ln, 1e-3 * mean_l[:, None]).clamp_min(1e-150)  # 1/l^2 finite
        w = w0 * _chord_weights(prob, b, d, keep, theta) * km
        c_new = unit_rms(prob, laplacian_solve(prob, w / ln ** 2, ln[..., None] * d))
        change = float((c_new - c).abs().max()) if c.numel() else 0.0
        c = c_new
        if change < tol:
            break
    return c, w


def translations_lud(prob: PaddedProblem, d: Tensor, keep: Tensor, w0: Tensor, c0: Tensor,
                     iters: int, tol: float = 1e-10) -> tuple[Tensor, Tensor]:
    """Least-unsquared-deviation centres ``[G, n, 3]`` (centroid 0, RMS 1) and the final IRLS
    weights ``[G, m]``; arguments as :func:`translations_bata`.

    ``min sum_e w0_e |c_j - c_i - s_e d_e|`` s.t. ``s_e >= 1``: IRLS weights
    ``w0 / max(|r_e|, delta)`` alternate with ``s_e = max(1, b_e . d_e)``. The start is scaled so
    that the median projected baseline is 1 (the constraint's natural unit).
    """
    km = keep.to(c0.dtype)
    proj = (baselines(prob, unit_rms(prob, c0)) * d).sum(-1)
    med = batch_median(proj, keep)
    med = torch.where(torch.isfinite(med) & (med > 0), med, torch.ones_like(med))
    c = unit_rms(prob, c0) / med[:, None, None]
    w = km
    for _ in range(iters):
        b = baselines(prob, c)
        s = ((b * d).sum(-1)).clamp_min(1.0)
        r = (b - s[..., None] * d).norm(dim=-1)
        mean_s = (s * km).sum(1) / km.sum(1).clamp_min(1)
        # delta: the usual IRLS smoothing of |r| near 0, relative to the problem's scale
        w = w0 * km / torch.maximum(r, 1e-6 * mean_s[:, None])
        c_new = laplacian_solve(prob, w, s[..., None] * d)
        change = float((c_new - c).abs().max() / c.abs().max().clamp_min(1e-300))
        c = c_new
        if change < tol:
            break
    return unit_rms(prob, c), w


def triangle_residuals(prob: PaddedProblem, d: Tensor, keep: Tensor) -> tuple[Tensor, Tensor]:
    """Direction consistency of every triangle of kept edges, seen from each edge.

    In a triangle ``a, b, c`` the baseline ``c_c - c_a`` is the sum of ``c_b - c_a`` and
    ``c_c - c_b``, so its direction lies in the planar cone spanned by the other two. The
    triangle's residual is the angle (degrees) from that direction to the cone (the
    out-of-plane angle if it projects inside, else the angle to the nearer side). Returns
    ``res [G, m, n]``: for edge ``e`` and third vertex ``k`` the residual of triangle
    ``(src_e, dst_e, k)``, and its mask ``[G, m, n]`` (the triangle exists). Dense
    ``[G, n, n, n]`` work: meant for components of up to about a hundred cameras.
    """
    G, n = prob.G, prob.n
    dt, dev = d.dtype, d.device
    gi = torch.arange(G, device=dev)[:, None].expand(G, prob.m)
    D = torch.zeros(G, n, n, 3, dtype=dt, device=dev)
    A = torch.zeros(G, n, n, dtype=torch.bool, device=dev)
    dk = d * keep[..., None].to(dt)
    D[gi, prob.src, prob.dst] = dk
    D[gi, prob.dst, prob.src] = -dk
    A[gi, prob.src, prob.dst] = keep
    A[gi, prob.dst, prob.src] = keep
    # triangle (a < b < c): x = a->b, y = b->c, z = a->c
    x = D[:, :, :, None, :].expand(G, n, n, n, 3)
    y = D[:, None, :, :, :].expand(G, n, n, n, 3)
    z = D[:, :, None, :, :].expand(G, n, n, n, 3)
    ar = torch.arange(n, device=dev)
    order = (ar[:, None, None] < ar[None, :, None]) & (ar[None, :, None] < ar[None, None, :])
    tri = A[:, :, :, None] & A[:, None, :, :] & A[:, :, None, :] & order
    nrm = torch.linalg.cross(x, y)
    nrm = nrm / nrm.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    off = torch.asin((z * nrm).sum(-1).abs().clamp(max=1.0))
    inside = ((torch.linalg.cross(x, z) * nrm).sum(-1) >= 0) & (
        (torch.linalg.cross(z, y) * nrm).sum(-1) >= 0)

    def ang(u: Tensor, v: Tensor) -> Tensor:
        return torch.arccos((u * v).sum(-1).clamp(-1.0, 1.0))

    res = torch.where(inside, off, torch.minimum(ang(z, x), ang(z, y)))
    res = torch.where(tri, torch.rad2deg(res), torch.zeros_like(res))
    # the same triangle seen from each of its three edges: symmetrise over vertex orders
    perms = ((0, 1, 2, 3), (0, 1, 3, 2), (0, 2, 1, 3), (0, 2, 3, 1), (0, 3, 1, 2), (0, 3, 2, 1))
    T = sum(res.permute(*p) for p in perms)
    M = torch.stack([tri.permute(*p) for p in perms]).any(0)
    return T[gi, prob.src, prob.dst], M[gi, prob.src, prob.dst]


def triangle_weights(prob: PaddedProblem, d: Tensor, keep: Tensor, floor_deg: float = 5.0,
                     k: float = 3.0) -> Tensor:
    """Start weights ``[G, m]`` from triangle consistency (:func:`triangle_residuals`).

    A triangle is called bad when its residual exceeds ``tau = max(floor_deg, k * median of
    the edges' median triangle residuals)`` (the typical residual of a good edge, so noisy
    graphs get a looser test); an edge's weight is ``(1 - bad fraction)^2`` of its triangles
    (floored at 1e-3; 1 for an edge in no triangle). A wrong direction spoils every triangle
    it is in, a good one only those holding a wrong edge, so wrong edges start near 0. Only a
    starting point: the robust solve re-weights every edge afterwards.
    """
    out = torch.zeros_like(keep, dtype=d.dtype)
    # The work is [G, n, n, n]: components go in chunks of about TRIANGLE_CHUNK entries.
    step = max(1, TRIANGLE_CHUNK // max(1, prob.n) ** 3)
    for start in range(0, prob.G, step):
        idx = torch.arange(start, min(start + step, prob.G), device=d.device)
        sub = prob.select(idx) if idx.numel() < prob.G else prob
        ms = sub.m
        dk, kk = d[idx, :ms], keep[idx, :ms]
        T, M = triangle_residuals(sub, dk, kk)
        score = batch_median(T, M)
        has = kk & (M.sum(-1) > 0)
        typical = torch.nan_to_num(batch_median(torch.nan_to_num(score), has), nan=0.0)
        tau = (k * typical).clamp_min(floor_deg)
        bad = ((T > tau[:, None, None]) & M).sum(-1).to(d.dtype)
        frac = bad / M.sum(-1).clamp_min(1).to(d.dtype)
        w = ((1.0 - frac) ** 2).clamp_min(1e-3)
        out[idx, :ms] = torch.where(kk, w, torch.zeros_like(w))
    return out

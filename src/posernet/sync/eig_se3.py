"""EIG-SE3 (Arrigoni, Rossi, Fusiello, SIAM J. Imaging Sci. 2016), batched in torch.

**The published algorithm** (``DESIGN.md`` section 8). Stack the absolute poses ``M_i`` into
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

**Batching.** Components (see :mod:`posernet.sync.base`) are padded to ``[G, n]``. Small ones
(``<= dense_max_nodes``) use batched dense ``eigh`` on ``[G, 3n, 3n]`` and a batched Cholesky
solve; large ones a batched restarted block-Krylov (Lanczos with full reorthogonalisation) for
the top 3 eigenvectors, warm-started across IRLS iterations, and conjugate gradients for the
translations, applying ``N`` through the edges (O(E) per product). IRLS iterates only the
graphs that have not converged. Everything runs in float64 internally (eigenvectors of nearly
degenerate clusters need it) on the input's device; results are cast back to the input dtype.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..geometry import make_se3
from .base import (
    Components,
    PaddedProblem,
    SyncBackend,
    SyncOptions,
    SyncResult,
    apply_scale_policy,
    build_padded,
    check_positive,
    det3,
    edge_rotations,
    mad_cauchy_weights,
    project_to_so3,
)

__all__ = ["EigSE3", "EigSE3Options", "RotationSolution", "rotation_irls", "solve_padded"]

SOLVERS = ("auto", "dense", "krylov")
_PAD_EIG = -2.0  # eigenvalue given to padded rows of N (N's spectrum lies in [-1, 1])


@dataclass(frozen=True)
class SpectralOptions(SyncOptions):
    """Options of the robust spectral (rotation) solve shared by EIG-SE3 and
    ``rotation_translation``: ``robust``: IRLS on (Cauchy weights, MAD threshold);
    ``max_iters``: most eigen-solves; ``tol``: IRLS stop on the relative weight change;
    ``theta``: MAD multiplier (2 as in the SIIMS paper); ``solver``: ``auto`` (dense up to
    ``dense_max_nodes`` nodes per component, block Krylov above), ``dense`` or ``krylov``;
    ``seed``: Krylov start vectors."""

    robust: bool = True
    max_iters: int = 50
    tol: float = 1e-5
    theta: float = 2.0
    solver: str = "auto"
    dense_max_nodes: int = 64
    seed: int = 0

    def check(self) -> None:
        super().check()
        if not isinstance(self.robust, bool):
            raise ValueError(f"robust must be true/false, got {self.robust!r}")
        check_positive("max_iters", self.max_iters, integer=True)
        check_positive("tol", self.tol)
        check_positive("theta", self.theta)
        check_positive("dense_max_nodes", self.dense_max_nodes, integer=True)
        if self.solver not in SOLVERS:
            raise ValueError(f"solver={self.solver!r}; choose one of {list(SOLVERS)}")
        if not isinstance(self.seed, int):
            raise ValueError(f"seed must be an integer, got {self.seed!r}")


@dataclass(frozen=True)
class EigSE3Options(SpectralOptions):
    """:class:`SpectralOptions` plus ``krylov_tol`` (eigen-residual tolerance) and
    ``krylov_max_cycles`` (restarts per solve); default scale ``unit``."""

    scale: str = "unit"
    krylov_tol: float = 1e-12
    krylov_max_cycles: int = 500

    def check(self) -> None:
        super().check()
        check_positive("krylov_tol", self.krylov_tol)
        check_positive("krylov_max_cycles", self.krylov_max_cycles, integer=True)


# --------------------------------------------------------------------------- the operator


def _gi(prob: PaddedProblem) -> Tensor:
    return torch.arange(prob.G, device=prob.node.device)[:, None].expand(prob.G, prob.m)


def degrees(prob: PaddedProblem, w_edge: Tensor, w_diag: Tensor) -> Tensor:
    """Weighted degree (row sums of ``W`` incl. the diagonal) ``[G, n]``; 1 on padded nodes."""
    G, n = prob.G, prob.n
    deg = torch.zeros(G * n, dtype=w_edge.dtype, device=w_edge.device)
    base = torch.arange(G, device=w_edge.device)[:, None] * n
    deg.index_add_(0, (base + prob.src).flatten(), w_edge.flatten())
    deg.index_add_(0, (base + prob.dst).flatten(), w_edge.flatten())
    deg = deg.view(G, n) + w_diag[:, None]
    return torch.where(prob.node_mask, deg, torch.ones_like(deg))


def dense_N(prob: PaddedProblem, w_edge: Tensor, w_diag: Tensor, s: Tensor) -> Tensor:
    """``N = D3^{-1/2} X_RR D3^{-1/2}`` as ``[G, 3n, 3n]`` (``s = deg^{-1/2} [G, n]``).

    Block (j, i) of ``X_RR`` is ``w_e R_e`` for stored edge ``e = i -> j``, block (i, j) its
    transpose, block (a, a) ``w_aa I``. Padded nodes get ``_PAD_EIG * I`` so that they never
    enter the top-3 eigenvectors.
    """
    G, n = prob.G, prob.n
    em = prob.edge_mask
    g = torch.arange(G, device=em.device)[:, None].expand(G, prob.m)[em]
    src, dst = prob.src[em], prob.dst[em]
    blk = (s[g, src] * s[g, dst] * w_edge[em])[:, None, None] * prob.R[em]
    X = torch.zeros(G, n, 3, n, 3, dtype=prob.R.dtype, device=prob.R.device)
    X[g, dst, :, src, :] = blk  # each (component, ordered pair) occurs once
    X[g, src, :, dst, :] = blk.mT
    diag = torch.where(prob.node_mask, w_diag[:, None] * s * s, torch.full_like(s, _PAD_EIG))
    X = X.view(G, 3 * n, 3 * n)
    X.diagonal(dim1=-2, dim2=-1).add_(diag.repeat_interleave(3, dim=1))
    return X


def _raw_coords(prob: PaddedProblem) -> tuple[Tensor, Tensor]:
    """Row/column of every stored entry of :func:`sparse_N`, in its raw (unsorted) order:
    the 9 entries of each block ``(dst, src)``, then of each ``(src, dst)``, then 3 diagonal
    entries per valid node. No position occurs twice."""
    G, n, dev = prob.G, prob.n, prob.R.device
    gidx = torch.arange(G, device=dev)[:, None].expand(G, prob.m)[prob.edge_mask]
    src, dst = prob.src[prob.edge_mask], prob.dst[prob.edge_mask]
    gn = torch.arange(G, device=dev)[:, None].expand(G, n)[prob.node_mask]
    an = torch.arange(n, device=dev)[None, :].expand(G, n)[prob.node_mask]
    r3 = torch.arange(3, device=dev)

    def coords(g: Tensor, a: Tensor) -> Tensor:
        return (g * (3 * n) + 3 * a)[:, None] + r3[None, :]  # [K, 3]

    rows = torch.cat((coords(gidx, dst)[:, :, None].expand(-1, 3, 3).reshape(-1),
                      coords(gidx, src)[:, :, None].expand(-1, 3, 3).reshape(-1),
                      coords(gn, an).reshape(-1)))
    cols = torch.cat((coords(gidx, src)[:, None, :].expand(-1, 3, 3).reshape(-1),
                      coords(gidx, dst)[:, None, :].expand(-1, 3, 3).reshape(-1),
                      coords(gn, an).reshape(-1)))
    return rows, cols


@dataclass
class CSRPattern:
    """Sparsity pattern of :func:`sparse_N` for one problem (fixed across IRLS iterations,
    where only the weights change): CSR row pointers, column indices and the permutation
    that sorts the raw entries into CSR order."""

    crow: Tensor
    col: Tensor
    perm: Tensor
    size: int

    @classmethod
    def of(cls, prob: PaddedProblem) -> CSRPattern:
        rows, cols = _raw_coords(prob)
        size = prob.G * 3 * prob.n
        perm = torch.argsort(rows * size + cols)
        counts = torch.bincount(rows, minlength=size)
        crow = torch.cat((counts.new_zeros(1), torch.cumsum(counts, 0)))
        return cls(crow=crow, col=cols[perm], perm=perm, size=size)


def sparse_N(prob: PaddedProblem, w_edge: Tensor, w_diag: Tensor, s: Tensor,
             pattern: CSRPattern | None = None) -> Tensor:
    """``N`` of every component as one block-diagonal sparse CSR matrix ``[G 3n, G 3n]``.

    Same entries as :func:`dense_N` (padded nodes are left empty, not given ``_PAD_EIG``:
    Krylov vectors are kept zero there). Products cost O(E), on CPU and CUDA. Pass the
    problem's :class:`CSRPattern` to skip re-sorting the pattern.
    """
    if pattern is None:
        pattern = CSRPattern.of(prob)
    G = prob.G
    em, nm = prob.edge_mask, prob.node_mask
    gidx = torch.arange(G, device=em.device)[:, None].expand(G, prob.m)[em]
    src, dst = prob.src[em], prob.dst[em]
    blk = (s[gidx, src] * s[gidx, dst] * w_edge[em])[:, None, None] * prob.R[em]
    dval = (w_diag[:, None] * s * s)[nm]
    vals = torch.cat((blk.reshape(-1), blk.mT.reshape(-1), dval[:, None].expand(-1, 3).reshape(-1)))
    with warnings.catch_warnings():  # "sparse CSR support is in beta": we only use S @ dense
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(pattern.crow, pattern.col, vals[pattern.perm],
                                       (pattern.size, pattern.size), check_invariants=False)


def sparse_apply(S: Tensor, V: Tensor) -> Tensor:
    """``S @ V`` for the block-diagonal ``S`` and ``V [G, M, k]``."""
    G, M, k = V.shape
    return (S @ V.reshape(G * M, k)).view(G, M, k)


# --------------------------------------------------------------------------- eigen-solvers


def _orthonormalize(W: Tensor, Q: Tensor | None, row_mask: Tensor,
                    generator: torch.Generator) -> Tensor:
    """Orthonormal columns spanning ``W [G, M, p]`` orthogonally to ``Q [G, M, q]``.

    Block classical Gram-Schmidt twice against ``Q``, then a Householder QR of the block and
    one more projection + QR pass (restores orthogonality lost to cancellation). A column that
    lies (to 1e-13) in ``span Q`` already is replaced by a random one: Krylov breakdown, e.g.
    on exact data whose operator has few distinct eigenvalues.
    """
    nrm0 = W.norm(dim=1).clamp_min(1e-300)

    def proj(Y: Tensor) -> Tensor:
        return Y if Q is None else Y - Q @ (Q.mT @ Y)

    W = proj(proj(W))
    bad = W.norm(dim=1) <= 1e-13 * nrm0
    if bool(bad.any()):
        r = torch.randn(W.shape, generator=generator, dtype=W.dtype,
                        device=W.device) * row_mask[..., None]
        W = torch.where(bad[:, None, :], proj(proj(r)), W)
    W = torch.linalg.qr(W).Q
    if Q is not None:
        W = torch.linalg.qr(proj(W)).Q
    return W


def top3_dense(N: Tensor) -> Tensor:
    """Top-3 eigenvectors ``[G, 3n, 3]`` of the symmetric ``N [G, 3n, 3n]`` (batched eigh)."""
    _, vec = torch.linalg.eigh(N)
    return vec[..., -3:]


def top3_krylov(apply, V0: Tensor, row_mask: Tensor, generator: torch.Generator,
                tol: float, max_cycles: int, guard: int = 3,
                steps: int = 8) -> tuple[Tensor, Tensor, Tensor, int]:
    """Top-3 eigenvectors of a symmetric operator by restarted block Lanczos.

    Each cycle builds the block Krylov space ``[V, NV, ..., N^steps V]`` of the ``p = 3 +
    guard`` warm vectors with full reorthogonalisation, takes the Rayleigh-Ritz pairs of
    ``H = Q^T N Q`` (a small ``eigh``) and restarts from the top ``p`` Ritz vectors until the
    top-3 residual ``|N u - theta u|`` is below ``tol`` for every graph.
    Returns ``(U [G, M, 3], V_next [G, M, p], converged [G], cycles)``.
    """
    V = _orthonormalize(V0, None, row_mask, generator)
    G = V.shape[0]
    U_out = torch.zeros(G, V.shape[1], 3, dtype=V.dtype, device=V.device)
    done = torch.zeros(G, dtype=torch.bool, device=V.device)
    p = V.shape[-1]
    for cycle in range(1, max_cycles + 1):
        blocks, images = [V], [apply(V)]
        for _ in range(steps):
            Q = torch.cat(blocks, dim=-1)
            W = _orthonormalize(images[-1], Q, row_mask, generator)
            blocks.append(W)
            images.append(apply(W))
        Q, AQ = torch.cat(blocks, dim=-1), torch.cat(images, dim=-1)
        H = Q.mT @ AQ
        theta, Y = torch.linalg.eigh(0.5 * (H + H.mT))
        Y3 = Y[..., -3:]
        U, AU = Q @ Y3, AQ @ Y3
        res = (AU - U * theta[:, None, -3:]).norm(dim=1).amax(dim=1)
        newly = (res <= tol) & ~done
        U_out[newly] = U[newly]
        done |= newly
        V = Q @ Y[..., -p:]
        if bool(done.all()):
            return U_out, V, done, cycle
    U_out[~done] = U[~done]
    return U_out, V, done, max_cycles


def conjugate_gradient(apply, b: Tensor, tol: float = 1e-13,
                       max_iter: int = 20000) -> tuple[Tensor, Tensor]:
    """Batched CG for SPD operators: ``b [G, M] -> (x, converged [G])``; per-graph steps."""
    x = torch.zeros_like(b)
    r = b.clone()
    p = r.clone()
    rs = (r * r).sum(1)
    bn = b.norm(dim=1).clamp_min(1e-300)
    done = rs.sqrt() <= tol * bn
    for _ in range(max_iter):
        if bool(done.all()):
            break
        Ap = apply(p)
        pAp = (p * Ap).sum(1)
        alpha = torch.where(done, torch.zeros_like(rs), rs / pAp.clamp_min(1e-300))
        x = x + alpha[:, None] * p
        r = r - alpha[:, None] * Ap
        rs_new = (r * r).sum(1)
        beta = torch.where(done, torch.zeros_like(rs), rs_new / rs.clamp_min(1e-300))
        p = r + beta[:, None] * p
        rs = rs_new
        done = done | (rs.sqrt() <= tol * bn)
    return x, done


# --------------------------------------------------------------------------- rotations


def _orthonormal_columns(Y: Tensor) -> Tensor:
    """Euclidean-orthonormal basis of the columns of ``Y [G, M, k]`` (Gram-Schmidt, twice)."""
    cols: list[Tensor] = []
    for w in Y.mT.contiguous().unbind(1):
        for _ in range(2):
            for q in cols:
                w = w - q * (q * w).sum(1, keepdim=True)
        cols.append(w / (w * w).sum(1, keepdim=True).sqrt().clamp_min(1e-300))
    return torch.stack(cols, dim=-1)


def rotations_from_eigvecs(V3: Tensor, s: Tensor, node_mask: Tensor) -> tuple[Tensor, Tensor]:
    """Absolute rotations ``[G, n, 3, 3]`` and the basis ``Rh [G, 3n, 3]`` from the top-3
    eigenvectors ``V3`` of ``N``: ``r_k = D3^{-1/2} v_k``, orthonormalised (the published
    ``U alpha`` is an orthonormal basis of the same span), handedness fixed, blocks projected
    onto SO(3). Padded nodes get the identity."""
    G, M, _ = V3.shape
    n = M // 3
    rmask = node_mask.repeat_interleave(3, dim=1)[..., None]
    R3 = V3 * s.repeat_interleave(3, dim=1)[..., None] * rmask
    Rh = _orthonormal_columns(R3)
    blocks = Rh.view(G, n, 3, 3)
    flip = (det3(blocks) * node_mask).sum(1) < 0
    sign = torch.ones(G, 3, dtype=Rh.dtype, device=Rh.device)
    sign[:, 0] = torch.where(flip, -1.0, 1.0)
    Rh = Rh * sign[:, None, :]
    blocks = Rh.view(G, n, 3, 3)
    R = project_to_so3(blocks)
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    return torch.where(node_mask[..., None, None], R, eye), Rh


def rotation_residuals(prob: PaddedProblem, R: Tensor) -> Tensor:
    """``|R_j R_i^T - R_e|_F`` per edge ``e = i -> j`` ``[G, m]`` (0 on pads)."""
    gi = _gi(prob)
    est = R[gi, prob.dst] @ R[gi, prob.src].mT
    diff = (est - prob.R).flatten(-2)
    res = (diff * diff).sum(-1).sqrt()
    return torch.where(prob.edge_mask, res, torch.zeros_like(res))


@dataclass
class RotationSolution:
    """Result of :func:`rotation_irls` for the components of a :class:`PaddedProblem`."""

    R: Tensor  # [G, n, 3, 3] absolute rotations (world-to-camera)
    V3: Tensor  # [G, 3n, 3] top eigenvectors of N for the weights below
    Rh: Tensor  # [G, 3n, 3] orthonormal basis of span D3^{-1/2} V3 (after the handedness fix)
    w_edge: Tensor  # [G, m] weights used by the last solve
    w_diag: Tensor  # [G]
    iterations: Tensor  # [G] eigen-solves
    converged: Tensor  # [G] IRLS converged (True when not robust)
    eig_converged: Tensor  # [G] Krylov converged (True for dense)
    pattern: CSRPattern | None = None  # sparse pattern of the whole problem, if one was built


def rotation_irls(prob: PaddedProblem, robust: bool, max_iters: int, tol: float, theta: float,
                  krylov: bool, krylov_tol: float = 1e-12, krylov_max_cycles: int = 500,
                  seed: int = 0) -> RotationSolution:
    """Spectral rotation synchronisation with EIG-SE3's IRLS, batched over components.

    Only components whose weights are still changing are re-solved (masking). With
    ``robust=False`` this is a single solve with unit weights.
    """
    G, n, dev, dt = prob.G, prob.n, prob.R.device, prob.R.dtype
    w_edge = prob.edge_mask.to(dt)
    w_diag = torch.ones(G, dtype=dt, device=dev)
    R = torch.eye(3, dtype=dt, device=dev).expand(G, n, 3, 3).clone()
    V3 = torch.zeros(G, 3 * n, 3, dtype=dt, device=dev)
    Rh = torch.zeros_like(V3)
    used_edge, used_diag = w_edge.clone(), w_diag.clone()
    iters = torch.zeros(G, dtype=torch.long, device=dev)
    converged = torch.zeros(G, dtype=torch.bool, device=dev)
    eig_ok = torch.ones(G, dtype=torch.bool, device=dev)
    active = torch.ones(G, dtype=torch.bool, device=dev)
    gen = torch.Generator(device=dev).manual_seed(seed)
    warm = None
    pattern: CSRPattern | None = None
    pattern_idx: Tensor | None = None
    if krylov:
        rows = prob.node_mask.repeat_interleave(3, dim=1)[..., None].to(dt)
        warm = torch.randn(G, 3 * n, 6, generator=gen, dtype=dt, device=dev) * rows
    for k in range(1, (max_iters if robust else 1) + 1):
        idx = active.nonzero().squeeze(1)
        sub = prob.select(idx) if idx.numel() < G else prob
        ns, ms = sub.n, sub.m
        we, wd = w_edge[idx, :ms], w_diag[idx]
        s = degrees(sub, we, wd).rsqrt()
        if krylov:
            rows = sub.node_mask.repeat_interleave(3, dim=1).to(dt)

            if pattern_idx is None or not torch.equal(pattern_idx, idx):
                pattern, pattern_idx = CSRPattern.of(sub), idx  # rebuilt only when it shrinks
            S = sparse_N(sub, we, wd, s, pattern)

            def op(V: Tensor, S=S) -> Tensor:
                return sparse_apply(S, V)

            V3s, warm_s, ok, _ = top3_krylov(op, warm[idx, :3 * ns], rows, gen, krylov_tol,
                                             krylov_max_cycles)
            warm[idx, :3 * ns] = warm_s
            eig_ok[idx] = ok
        else:
            V3s = top3_dense(dense_N(sub, we, wd, s))
        Rs, Rhs = rotations_from_eigvecs(V3s, s, sub.node_mask)
        R[idx, :ns], V3[idx, :3 * ns], Rh[idx, :3 * ns] = Rs, V3s, Rhs
        used_edge[idx, :ms], used_diag[idx] = we, wd
        iters[idx] = k
        if not robust:
            converged[:] = True
            break
        res = rotation_residuals(sub, Rs)
        w_new = mad_cauchy_weights(res, sub.edge_mask, theta)
        wd_new = w_new.amax(dim=1)
        cnt = sub.count.to(dt)
        # |W_old - W|_F / (|W|_F n) over the full symmetric n x n weight matrix.
        num = (2 * ((we - w_new) ** 2).sum(1) + cnt * (wd - wd_new) ** 2).sqrt()
        den = (2 * (w_new ** 2).sum(1) + cnt * wd_new ** 2).sqrt() * cnt
        delta = num / den.clamp_min(1e-300)
        w_edge[idx, :ms], w_diag[idx] = w_new, wd_new
        stop = delta <= tol
        converged[idx[stop]] = True
        active[idx[stop]] = False
        if not bool(active.any()):
            break
    full = pattern if pattern_idx is not None and pattern_idx.numel() == G else None
    return RotationSolution(R=R, V3=V3, Rh=Rh, w_edge=used_edge, w_diag=used_diag,
                            iterations=iters, converged=converged, eig_converged=eig_ok,
                            pattern=full)


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


def split_by_size(prob: PaddedProblem, solver: str, dense_max_nodes: int,
                  min_krylov_nodes: int = 40) -> list[tuple[Tensor, bool]]:
    """Component groups ``(indices, use_krylov)``: small ones dense, large ones Krylov.

    Components below ``min_krylov_nodes`` always go dense (a Krylov space of 54 vectors needs
    enough rows).
    """
    if solver == "dense":
        krylov = torch.zeros_like(prob.count, dtype=torch.bool)
    elif solver == "krylov":
        krylov = prob.count >= min_krylov_nodes
    else:
        krylov = (prob.count > dense_max_nodes) & (prob.count >= min_krylov_nodes)
    out = []
    for flag in (False, True):
        idx = (krylov == flag).nonzero().squeeze(1)
        if idx.numel():
            out.append((idx, flag))
    return out


def solve_padded(prob: PaddedProblem, opts: EigSE3Options) -> tuple[Tensor, Tensor, dict]:
    """EIG-SE3 on every component of ``prob``: ``(R [G, n, 3, 3], t [G, n, 3], info)``."""
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
                            opts.krylov_tol, opts.krylov_max_cycles, opts.seed)
        ts = eig_translations(sub, sol, krylov)
        R[idx, :sub.n], t[idx, :sub.n] = sol.R, ts
        w_edge[idx, :sub.m] = sol.w_edge
        iters[idx], conv[idx], eig_ok[idx] = sol.iterations, sol.converged, sol.eig_converged
    return R, t, {"w_edge": w_edge, "iterations": iters, "converged": conv,
                  "eig_converged": eig_ok}


def assemble(struct: dict[str, Any], comps: Components, prob: PaddedProblem | None, R: Tensor,
             t: Tensor, w_edge: Tensor, iters: Tensor, conv: Tensor, dtype: torch.dtype,
             device: torch.device) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Scatter padded per-component results back to nodes/edges/graphs.

    Returns ``poses [N, 4, 4]``, ``solved [N]``, ``edge_weight [E]``, ``iterations [B]``,
    ``converged [B]``.
    """
    N, B = struct["num_nodes"], struct["num_graphs"]
    E = struct["edge_index"].shape[1]
    poses = torch.eye(4, dtype=dtype, device=device).expand(N, 4, 4).clone()
    solved = torch.zeros(N, dtype=torch.bool, device=device)
    edge_weight = torch.ones(E, dtype=dtype, device=device)
    it_g = torch.zeros(B, dtype=torch.long, device=device)
    conv_g = torch.ones(B, dtype=torch.bool, device=device)
    if prob is not None and prob.G:
        sel = prob.node_mask
        nodes = prob.node[sel]
        poses[nodes] = make_se3(R[sel], t[sel])
        solved[nodes] = True
        edge_weight[prob.edge[prob.edge_mask]] = w_edge[prob.edge_mask]
        graph = comps.graph[prob.comp_id]
        it_g.scatter_reduce_(0, graph, iters, reduce="amax")
        conv_g.scatter_reduce_(0, graph, conv, reduce="amin")
    return poses, solved, edge_weight, it_g, conv_g


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
        R, t, info = solve_padded(prob, o)
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

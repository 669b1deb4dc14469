"""Robust spectral rotation synchronisation, shared by EIG-SE3 and ``rotation_translation``.

The top-3 eigenvectors of ``N = D3^{-1/2} X_RR D3^{-1/2}`` (``X_RR`` the symmetric 3n x 3n
matrix of weighted relative rotations, identity-weighted diagonal; ``D3`` its weighted degrees)
span the absolute rotations; IRLS re-weights the edges with EIG-SE3's Cauchy weights and MAD
threshold until the weights settle (:func:`rotation_irls`). Small components use dense
matrices: the backends run the IRLS iterations in :mod:`posernet.sync.filtered` (a
Chebyshev-filtered subspace per iteration instead of an ``eigh``, the eigenvectors of the last
solve by batched ``eigh``: the same result); large ones a batched restarted block-Krylov
(Lanczos with full reorthogonalisation) applying ``N`` as a sparse block-diagonal matrix
(O(E) per product), warm-started across IRLS iterations; on the CPU, components over
``posernet.sync.translation.SPARSE_MIN_NODES`` cameras that plain Lanczos does not settle in
:data:`PLAIN_KRYLOV_CYCLES` cycles run it on the shifted inverse ``(sigma I - N)^-1`` (one
sparse LU per iteration), whose top-3 eigenvalues stand far apart where ``N``'s do not (a long
chain of cameras); not above a mean degree of :data:`SHIFT_INVERT_MAX_DEGREE`, where the LU
fills in and costs far more than the plain cycles. Also the operators themselves
(:func:`dense_N`, :func:`sparse_N`), batched conjugate gradients and the dense/Krylov split by
component size (:func:`split_by_size`).
"""

from __future__ import annotations

import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import torch
from torch import Tensor

from ..geometry import det3, project_to_so3
from ..options import option
from ..scatter import scatter_count
from .backend import SyncOptions
from .padding import PaddedProblem
from .robust import mad_cauchy_weights
from .translation import use_sparse

__all__ = [
    "SOLVERS",
    "CSRPattern",
    "RotationSolution",
    "SpectralOptions",
    "batched_eigh",
    "conjugate_gradient",
    "degrees",
    "dense_N",
    "rotation_irls",
    "rotation_residuals",
    "rotations_from_eigvecs",
    "sparse_N",
    "sparse_apply",
    "split_by_size",
    "top3_dense",
    "top3_krylov",
]

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

    robust: bool = option(True, help="IRLS with Cauchy weights and a MAD threshold")
    max_iters: int = option(50, ge=1, help="most eigen-solves (published: 50)")
    tol: float = option(1e-5, gt=0, help="stop when |W_old - W|_F / (|W|_F n) <= tol "
                        "(published: 1e-5)")
    theta: float = option(2.0, gt=0, help="threshold = theta / 0.6745 * MAD (published SIIMS "
                          "value: 2)")
    solver: str = option("auto", choices=SOLVERS, help="eigen-solver; auto: dense up to "
                         "dense_max_nodes nodes per component, Krylov above")
    dense_max_nodes: int = option(64, ge=1, help="auto: dense eigh up to this many nodes per "
                                  "component")
    seed: int = option(0, help="Krylov start vectors")


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
        counts = scatter_count(rows, size)  # not bincount, as everywhere (posernet.scatter)
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
        # drawn on the CPU generator: the same vectors on every device
        r = torch.randn(W.shape, generator=generator, dtype=W.dtype).to(W.device) \
            * row_mask[..., None]
        W = torch.where(bad[:, None, :], proj(proj(r)), W)
    W = torch.linalg.qr(W).Q
    if Q is not None:
        W = torch.linalg.qr(proj(W)).Q
    return W


#: fewest matrices per thread for :func:`batched_eigh` to split a batch
_EIGH_PER_THREAD = 64


def batched_eigh(A: Tensor) -> tuple[Tensor, Tensor]:
    """``torch.linalg.eigh`` of the symmetric ``A [G, M, M]``: eigenvalues ``[G, M]`` and
    eigenvectors ``[G, M, M]``. On the CPU torch solves a batch one matrix after another on
    one thread; here the batch is split between ``torch.get_num_threads()`` threads (each
    matrix is still solved alone, so the result is the same bit for bit). Inputs that need a
    gradient go to ``torch.linalg.eigh`` whole."""
    k = min(torch.get_num_threads(), A.shape[0] // _EIGH_PER_THREAD)
    if k <= 1 or A.device.type != "cpu" or (A.requires_grad and torch.is_grad_enabled()):
        return torch.linalg.eigh(A)
    parts = A.tensor_split(k)
    with ThreadPoolExecutor(k) as pool:  # a pool per call: nothing is left to a fork
        done = list(pool.map(torch.linalg.eigh, parts))
    return torch.cat([d[0] for d in done]), torch.cat([d[1] for d in done])


def top3_dense(N: Tensor) -> Tensor:
    """Top-3 eigenvectors ``[G, 3n, 3]`` of the symmetric ``N [G, 3n, 3n]`` (batched eigh)."""
    _, vec = batched_eigh(N)
    return vec[..., -3:]


def top3_krylov(apply, V0: Tensor, row_mask: Tensor, generator: torch.Generator,
                tol: float, max_cycles: int, guard: int = 3, steps: int = 8,
                check=None) -> tuple[Tensor, Tensor, Tensor, int]:
    """Top-3 eigenvectors of a symmetric operator by restarted block Lanczos.

    Each cycle builds the block Krylov space ``[V, NV, ..., N^steps V]`` of the ``p = 3 +
    guard`` warm vectors with full reorthogonalisation, takes the Rayleigh-Ritz pairs of
    ``H = Q^T N Q`` (a small ``eigh``) and restarts from the top ``p`` Ritz vectors until the
    top-3 residual ``|N u - theta u|`` is below ``tol`` for every graph. ``check``: the
    operator whose residual decides instead (``N`` itself where ``apply`` is a function of
    ``N`` such as its shifted inverse; ``theta`` then its Rayleigh quotients).
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
        if check is not None:
            NU = check(U)
            res = (NU - U * (U * NU).sum(1, keepdim=True)).norm(dim=1).amax(dim=1)
        newly = (res <= tol) & ~done
        U_out[newly] = U[newly]
        done |= newly
        V = Q @ Y[..., -p:]
        if bool(done.all()):
            return U_out, V, done, cycle
    U_out[~done] = U[~done]
    return U_out, V, done, max_cycles


#: shift of the inverted operator ``(sigma I - N)^-1`` above ``N``'s spectrum (which ends at 1):
#: small against the spectral gap, so the top-3 eigenvalues stand far apart from the rest
SHIFT_INVERT_DELTA = 1e-6

#: Lanczos cycles on ``N`` itself before large CPU components switch to the shifted inverse:
#: well-connected graphs converge in a few (2 at 1000 cameras of degree 72, 8 at degree 4),
#: where the sparse LU fills in (seconds); long chains would take thousands, the inverse one
PLAIN_KRYLOV_CYCLES = 12
#: ... and only where the mean degree is at most this: the LU of a well-connected graph fills in
#: (a 2000-camera graph of degree 72 with random edge rotations, where Lanczos is slow too:
#: over 15 minutes and 4 GB in the LU, 6-7 s in plain Lanczos)
SHIFT_INVERT_MAX_DEGREE = 32.0


def shift_invert_apply(S: Tensor, rows: Tensor):
    """``V -> (sigma I - N)^-1 V`` for the block-diagonal sparse ``S = N`` (from
    :func:`sparse_N`; ``rows [G, M]`` its valid rows), ``sigma = 1 +``
    :data:`SHIFT_INVERT_DELTA`, by one sparse LU (scipy, on the CPU) of all components.

    Its top-3 eigenvectors are ``N``'s, but the relative gap to the 4th grows from the graph
    Laplacian's (about ``(pi / n)^2`` on a chain of ``n`` cameras: thousands of Lanczos steps
    at 1024 cameras) to nearly 1. Padded rows stay 0. Returns the operator on ``[G, M, k]``.
    """
    import scipy.sparse
    import scipy.sparse.linalg

    size = S.shape[0]
    Sc = S.to("cpu")
    N = scipy.sparse.csr_matrix((Sc.values().numpy(), Sc.col_indices().numpy(),
                                 Sc.crow_indices().numpy()), shape=(size, size))
    A = scipy.sparse.identity(size, format="csr") * (1.0 + SHIFT_INVERT_DELTA) - N
    lu = scipy.sparse.linalg.splu(A.tocsc())
    keep = rows.reshape(-1, 1).to("cpu", torch.float64).numpy()

    def apply(V: Tensor) -> Tensor:
        G, M, k = V.shape
        x = lu.solve(V.detach().to("cpu", torch.float64).reshape(G * M, k).numpy()) * keep
        return torch.from_numpy(x).to(V.device, V.dtype).view(G, M, k)

    return apply


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


def start_weights(prob: PaddedProblem, w0: Tensor | None) -> tuple[Tensor, Tensor]:
    """Edge ``[G, m]`` and diagonal ``[G]`` weights of the first solve (unit, or ``w0``)."""
    dt, dev = prob.R.dtype, prob.R.device
    if w0 is None:
        return prob.edge_mask.to(dt), torch.ones(prob.G, dtype=dt, device=dev)
    w_edge = torch.where(prob.edge_mask, w0.to(dt), torch.zeros((), dtype=dt, device=dev))
    return w_edge, w_edge.amax(dim=1)


def rotation_irls(prob: PaddedProblem, robust: bool, max_iters: int, tol: float, theta: float,
                  krylov: bool, krylov_tol: float = 1e-12, krylov_max_cycles: int = 500,
                  seed: int = 0, w0: Tensor | None = None,
                  prior: bool = False) -> RotationSolution:
    """Spectral rotation synchronisation with EIG-SE3's IRLS, batched over components.

    Only components whose weights are still changing are re-solved (masking). With
    ``robust=False`` this is a single solve. The first solve uses unit weights, or ``w0
    [G, m]`` (0 on pads; e.g. per-edge confidence, :mod:`posernet.sync.weighted`); with
    ``prior=True`` every later solve multiplies the Cauchy weights by ``w0`` too.

    This is the reference loop (an ``eigh`` or Krylov solve per iteration); the backends call
    :func:`posernet.sync.irls.rotation_irls`, which runs the robust dense case by filtered
    subspaces (:mod:`posernet.sync.filtered`) to the same result.
    """
    w_edge, w_diag = start_weights(prob, w0)
    w_prior = w_edge.clone() if prior and w0 is not None else None
    G, n, dev, dt = prob.G, prob.n, prob.R.device, prob.R.dtype
    R = torch.eye(3, dtype=dt, device=dev).expand(G, n, 3, 3).clone()
    V3 = torch.zeros(G, 3 * n, 3, dtype=dt, device=dev)
    Rh = torch.zeros_like(V3)
    used_edge, used_diag = w_edge.clone(), w_diag.clone()
    iters = torch.zeros(G, dtype=torch.long, device=dev)
    converged = torch.zeros(G, dtype=torch.bool, device=dev)
    eig_ok = torch.ones(G, dtype=torch.bool, device=dev)
    active = torch.ones(G, dtype=torch.bool, device=dev)
    # a CPU generator: the Krylov start is the same on every device, so CUDA and CPU agree
    gen = torch.Generator().manual_seed(seed)
    warm = None
    # large CPU components: Lanczos on the shifted inverse (see below); 0 plain cycles: at once
    invert = PLAIN_KRYLOV_CYCLES <= 0
    pattern: CSRPattern | None = None
    pattern_idx: Tensor | None = None
    if krylov:
        rows = prob.node_mask.repeat_interleave(3, dim=1)[..., None].to(dt)
        warm = torch.randn(G, 3 * n, 6, generator=gen, dtype=dt).to(dev) * rows
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

            # may factor: large CPU components whose graph is sparse enough for a sparse LU
            factorable = use_sparse(ns, S.device) and (
                2.0 * float(sub.edge_mask.sum()) / max(1.0, float(sub.node_mask.sum()))
                <= SHIFT_INVERT_MAX_DEGREE)
            warm_s = warm[idx, :3 * ns]
            if not (factorable and invert):
                budget = min(PLAIN_KRYLOV_CYCLES, krylov_max_cycles) if factorable else \
                    krylov_max_cycles
                V3s, warm_s, ok, _ = top3_krylov(op, warm_s, rows, gen, krylov_tol, budget)
                invert = factorable and not bool(ok.all())
            if factorable and invert:
                # large components on the CPU that plain Lanczos did not settle in its budget
                # (a long chain: tiny spectral gap): Lanczos on the shifted inverse, one
                # sparse LU per IRLS round from now on, converged when N's own residual is
                # small
                inv = shift_invert_apply(S, rows)
                V3s, warm_s, ok, _ = top3_krylov(inv, warm_s, rows, gen, krylov_tol,
                                                 krylov_max_cycles, check=op)
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
        if w_prior is not None:
            w_new = w_new * w_prior[idx, :ms]
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


# --------------------------------------------------------------------------- dense / Krylov split


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

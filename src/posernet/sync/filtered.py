"""The robust dense rotation IRLS of :func:`posernet.sync.irls.rotation_irls`, fast.

Every IRLS iteration of EIG-SE3 (and of ``rotation_translation``) solves the top-3
eigenproblem of ``N = D3^{-1/2} X_RR D3^{-1/2}`` ``[3n, 3n]`` of each component, turns the
eigenvectors into rotations and re-weights the edges by their residuals. With a batched dense
``eigh`` per iteration (~50 us for a 24 x 24 matrix, 8 nodes, on one core) the eigen-solves
are two thirds of a 7000-graph solve. But an iteration only needs the *span* of the top-3
eigenvectors: rotations built from any orthonormal basis of it differ by one global rotation
(a gauge), and the residuals and weights do not see it. So each iteration here:

* builds ``N`` from a fixed unit-weight pattern (:func:`_pattern`, coordinates in
  component-major order, a symmetric permutation: same spectrum) and the new weights, one
  elementwise product;
* takes the span from :func:`top3_filtered` (a Chebyshev filter by repeated squaring and a
  few products, started from the previous iteration's basis; batched matrix products only,
  no LAPACK call per matrix), with :func:`~posernet.sync.spectral.top3_dense` where its
  residual test fails;
* orthonormalises by Cholesky QR with closed-form 3 x 3 factors (:func:`orth_rows`), projects
  the 3 x 3 blocks onto SO(3) by Newton's polar iteration with closed-form inverses
  (:func:`polar9`) and forms the residuals in the same entry-major layout
  (:func:`edge_residuals`);
* re-weights and stops by the published rules (:func:`~posernet.sync.robust.mad_cauchy_weights`,
  the relative weight change); stopped components are dropped from the batch in bulk.

The filter runs on chunks of components (:func:`_chunk`), so that its work arrays stay in the
cache; the rotations, residuals and weights run on the whole batch at once (elementwise
operations that large are split between threads; per chunk they would run on one).
When every component has stopped, the eigenvectors of its *last* solve come from
:func:`~posernet.sync.spectral.top3_dense` on exactly the matrix the eigh-per-iteration loop
solved then (:func:`~posernet.sync.spectral.dense_N` of the same weights, padded to the size
of the batch it was in), and the rotations from
:func:`~posernet.sync.spectral.rotations_from_eigvecs`: the ``V3``, ``Rh`` and rotations (gauge
included) of that loop, up to the round-off of the weights. Where the top-3 eigenvalues are
(nearly) degenerate, ``eigh``'s eigenvectors, hence the gauge, are not determined by ``N`` to
round-off (the loop's output could turn by a global rotation under a round-off change of its
input as well); the gauge-free result (relative poses) is unaffected.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..geometry import project_to_so3
from .padding import PaddedProblem
from .robust import mad_cauchy_weights
from .spectral import RotationSolution, degrees, dense_N, rotations_from_eigvecs, top3_dense

__all__ = ["dense_irls", "edge_residuals", "orth_rows", "polar9", "top3_filtered"]

#: The rest of ``N``'s spectrum (below the top 3, which lie near 1) is assumed in
#: ``[_LO, _HI]`` by :func:`top3_filtered`: ``-1`` is a bound (``|lambda| <= 1`` for
#: non-negative weights); a fourth eigenvalue above ``_HI`` slows the filter down (the residual
#: test and the dense fallback catch it), the top three must exceed ``_HI``.
_LO, _HI = -1.0, 0.9
_SQUARINGS = 4  # Chebyshev polynomial of degree 2^4: more than 700x per product
_FIRST = 5  # products before the first test (from the previous iteration's basis)
_PASSES = 5  # most refinement passes (two products each) before the dense fallback
_CHUNK = 2048 * 24 * 24  # entries of a chunk's [C, 3n, 3n] work array (2048 8-node graphs)
_POLAR_ITERS = 4  # Newton steps of the polar factor before its test
#: steps tried first on an IRLS iteration's blocks (within ~1 % of a rotation: 2 scaled steps
#: and the last one reach round-off); the blocks that fail the test get ``_POLAR_ITERS``
_POLAR_FIRST = 2
_TOL = 1e-15  # accepted invariance residual |N Q - Q Q^T N Q|_F, times sqrt(3n)


# --------------------------------------------------------------------------- small closed forms


def orth_rows(V: Tensor, passes: int = 2) -> Tensor:
    """Orthonormal rows ``[G, 3, M]`` spanning the rows of ``V [G, 3, M]`` (each row a
    vector), in order (row ``k`` spans rows ``0..k`` of ``V``: Gram-Schmidt's basis).

    Cholesky QR ``passes`` times, the 3 x 3 Cholesky factor in closed form and applied by
    forward substitution (a few ``[G]`` operations, one tiny batched product and a few row
    operations per pass, instead of a loop of vector operations). One pass leaves an
    orthogonality error of about ``eps * cond(V)^2``, two passes round-off for condition
    numbers up to ~1e7; worse ones give NaN or a non-orthonormal result, which
    :func:`top3_filtered`'s residual test rejects.
    """
    for _ in range(passes):
        g = (V @ V.mT).view(-1, 9)
        g00, g10, g11, g20, g21, g22 = g[:, 0], g[:, 3], g[:, 4], g[:, 6], g[:, 7], g[:, 8]
        l00 = g00.sqrt()
        l10, l20 = g10 / l00, g20 / l00
        l11 = (g11 - l10 * l10).sqrt()
        l21 = (g21 - l20 * l10) / l11
        l22 = (g22 - l20 * l20 - l21 * l21).sqrt()
        Q = torch.empty_like(V)
        v0, v1, v2 = V.unbind(1)
        q0, q1, q2 = Q.unbind(1)
        torch.div(v0, l00[:, None], out=q0)
        torch.sub(v1, l10[:, None] * q0, out=q1).div_(l11[:, None])
        torch.sub(v2, l20[:, None] * q0, out=q2).sub_(l21[:, None] * q1).div_(l22[:, None])
        V = Q
    return V


def _cof(y: Tensor) -> Tensor:
    """Cofactor matrices of ``y [9, K]`` (entry-major, row-major entries): ``[9, K]`` with
    ``y^{-T} = cof / det``."""
    y0, y1, y2, y3, y4, y5, y6, y7, y8 = y.unbind(0)
    cof = torch.empty_like(y)
    for o, (p, q, r, t) in zip(cof.unbind(0), (
            (y4, y8, y5, y7), (y5, y6, y3, y8), (y3, y7, y4, y6),
            (y2, y7, y1, y8), (y0, y8, y2, y6), (y1, y6, y0, y7),
            (y1, y5, y2, y4), (y2, y3, y0, y5), (y0, y4, y1, y3)), strict=True):
        torch.mul(p, q, out=o).addcmul_(r, t, value=-1.0)
    return cof


def _det(y: Tensor, cof: Tensor) -> Tensor:
    """Determinants ``[K]`` from the entries and cofactors ``[9, K]`` (first row)."""
    return (y[0] * cof[0]).addcmul_(y[1], cof[1]).addcmul_(y[2], cof[2])


def _rowsum3(x: Tensor) -> Tensor:
    """``x[0] + x[1] + x[2]`` (faster than ``sum(0)`` over a short leading axis)."""
    return x[0] + x[1] + x[2]


def polar9(a: Tensor, iters: int = _POLAR_ITERS) -> tuple[Tensor, Tensor]:
    """Nearest rotations of the 3 x 3 matrices ``a [9, K]`` (entry-major, row-major entries):
    ``(R [9, K], ok [K])``.

    ``iters`` steps of the Newton iteration for the polar factor, ``X <- (g X + X^{-T} / g) /
    2`` (inverse from the cofactors; determinant scaling ``g = det(X)^{-1/3}`` in the first
    two steps, ``g = 1`` after), then one more unscaled step; it converges quadratically to
    the same limit as :func:`posernet.geometry.project_to_so3` (no test per step: from the
    blocks of an eigenvector basis, a few percent off a rotation, four steps reach
    round-off). ``ok`` is false where ``det <= 0`` (no proper polar factor) or the result is
    not orthonormal to ``3e-14`` (an orthonormal Newton iterate is the polar factor): project
    those with :func:`~posernet.geometry.project_to_so3`.
    """
    sq = a * a
    y = a / (_rowsum3(sq[0:3]) + _rowsum3(sq[3:6]) + _rowsum3(sq[6:9])).sqrt().clamp_min(1e-300)
    cof = _cof(y)
    det = _det(y, cof)
    ok = det > 1e-12
    if not bool(ok.all()):  # no proper polar factor: the caller projects these by SVD
        eye = torch.eye(3, dtype=y.dtype, device=y.device).reshape(9, 1)
        y, cof = torch.where(ok, y, eye), torch.where(ok, cof, eye)
        det = torch.where(ok, det, torch.ones_like(det))
    for it in range(iters):
        if it < 2:  # scaled steps: (g y + cof / (g det)) / 2 = (y + cof / (g^2 det)) (g / 2)
            g = torch.exp(torch.log(det) * (-1.0 / 3.0))
            y = cof.mul_((g * g * det).reciprocal_()).add_(y).mul_(0.5 * g)
        else:  # near orthogonal: plain Newton steps, (y + cof / det) / 2
            y = cof.div_(det).add_(y).mul_(0.5)
        cof = _cof(y)
        det = _det(y, cof)
    y = cof.div_(det).add_(y).mul_(0.5)
    # An unscaled step maps the singular values s to (s + 1/s) / 2 >= 1 (the polar factor
    # stays): |Y|_F^2 - 3 = sum(s'^2 - 1) bounds every s'^2 - 1, the distance to it.
    sq = y * y
    err = _rowsum3(sq[0:3]) + _rowsum3(sq[3:6]) + _rowsum3(sq[6:9]) - 3.0
    return y, ok & (err < 3e-14)


def edge_residuals(R9: Tensor, Re9: Tensor, src: Tensor, dst: Tensor) -> Tensor:
    """``|R_dst R_src^T - R_e|_F`` ``[E]`` from the absolute rotations ``R9 [9, K]`` and the
    edge rotations ``Re9 [9, E]`` (entry-major), ``src``/``dst [E]`` column indices into
    ``R9``."""
    # gather over an expanded index: a copy like index_select along dim 1, several times faster
    Rj = R9.gather(1, dst.expand(9, -1)).view(3, 3, -1)
    Ri = R9.gather(1, src.expand(9, -1)).view(3, 3, -1)
    est = Rj[:, None, 0] * Ri[None, :, 0]
    est += Rj[:, None, 1] * Ri[None, :, 1]
    est += Rj[:, None, 2] * Ri[None, :, 2]
    diff = est.view(9, -1) - Re9
    return (diff * diff).sum(0).sqrt()


# --------------------------------------------------------------------------- the subspace


#: ``Z_0 = _C1 N + _C0 I`` is twice the affine map of ``N`` sending ``[_LO, _HI]`` to ``[-1, 1]``
_C1, _C0 = 4.0 / (_HI - _LO), -2.0 * (_HI + _LO) / (_HI - _LO)


def _residual_ok(Z0: Tensor, Qt: Tensor, tol: float) -> Tensor:
    """The test of :func:`top3_filtered` ``[G]``, for orthonormal rows ``Qt [G, 3, M]`` and
    ``Z0 = _C1 N + _C0 I [G, M, M]`` (the same invariant subspaces as ``N``): ``|N Q - Q (Q^T N
    Q)|_F <= tol`` and ``tr(Q^T N Q) > 2 + _HI``, evaluated on ``Z0``."""
    ZQ = Qt @ Z0  # rows: (Z0 Q)^T, Z0 symmetric
    H = ZQ @ Qt.mT
    E = torch.baddbmm(ZQ, H, Qt, alpha=-1.0)  # Z0 Q - Q H, as rows
    res = (E * E).sum((1, 2)).sqrt()
    trace = H.diagonal(dim1=-2, dim2=-1).sum(-1)
    return (res <= tol * _C1) & (trace > _C1 * (2.0 + _HI) + 3.0 * _C0)


def _filter(Z0: Tensor, Vt: Tensor, squarings: int, first: int, passes: int,
            bufs: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
    """:func:`top3_filtered` on one chunk, given ``Z0 = _C1 N + _C0 I [G, M, M]``; ``bufs``:
    two ``[>= G, M, M]`` work arrays."""
    G, M, _ = Z0.shape
    Z = Z0
    for k in range(squarings):
        Zn = torch.bmm(Z, Z, out=bufs[k % 2][:G])
        Zn.diagonal(dim1=-2, dim2=-1).sub_(2.0)
        Z = Zn
    Q = Vt
    for _ in range(first):
        Q = Q @ Z  # Z symmetric: (Z Q)^T = Q^T Z
    # from an orthonormal start in (or near) the subspace the rows are nearly orthogonal
    # (condition ~1): one Cholesky QR pass; a non-orthonormal result fails the test anyway
    Q = orth_rows(Q, passes=2 if first == 1 else 1)
    tol = _TOL * M ** 0.5
    ok = _residual_ok(Z0, Q, tol)
    for _ in range(passes - 1):
        nbad = G - int(ok.sum())
        if nbad == 0:
            break
        if 4 * nbad >= G:  # many: the whole chunk (no copies)
            Q = torch.where(ok[:, None, None], Q, orth_rows((Q @ Z) @ Z, passes=1))
            ok = _residual_ok(Z0, Q, tol)
        else:
            bad = (~ok).nonzero().squeeze(1)
            Zb = Z[bad]
            Qb = orth_rows((Q[bad] @ Zb) @ Zb, passes=1)
            Q[bad] = Qb
            ok[bad] = _residual_ok(Z0[bad], Qb, tol)
    return Q, ok


def _chunk(M: int) -> int:
    """Components per chunk for ``[M, M]`` matrices: ``_CHUNK`` entries per work array."""
    return max(1, _CHUNK // (M * M))


def top3_filtered(N: Tensor, Vt: Tensor, squarings: int = _SQUARINGS, first: int = _FIRST,
                  passes: int = _PASSES, chunk: int | None = None) -> tuple[Tensor, Tensor]:
    """Orthonormal rows ``Qt [G, 3, M]`` spanning the top-3 invariant subspace of the
    symmetric ``N [G, M, M]`` (spectrum in ``[-1, 1]``, padded rows and columns 0), from a
    start ``Vt [G, 3, M]`` (rows; e.g. the previous IRLS iteration's basis); and ``ok [G]``.

    ``Y``, the affine map of ``N`` sending ``[_LO, _HI]`` to ``[-1, 1]``, and ``Z_{k+1} =
    Z_k^2 - 2 I`` from ``Z_0 = 2 Y`` give ``Z = 2 T_{2^k}(Y)`` (``T`` the Chebyshev
    polynomial): at most 2 in modulus on the rest of the spectrum, ``2 cosh(2^k
    acosh(x))`` on a top eigenvalue (``x >= 1.105``, the image of 1: more than 700x for
    ``2^4``). The rows go through ``first`` products with ``Z`` and :func:`orth_rows`, then
    passes of two products and :func:`orth_rows` until ``|N Q - Q (Q^T N Q)|_F <= _TOL
    sqrt(M)`` and ``tr(Q^T N Q) > 2 + _HI`` (all three Ritz values above ``_HI``, where the
    filter ranks them first); only the failing components go on. Batched matrix products,
    no LAPACK call per matrix; ``chunk`` components at a time, so that ``Z`` stays in the
    cache between products. ``first=1`` for a random start (more products before the first
    orthonormalisation can leave the rows too close to parallel).

    The rows span the same space as :func:`~posernet.sync.spectral.top3_dense`'s
    eigenvectors but are not eigenvectors. ``ok`` fails where the filter is slow (a fourth
    eigenvalue above ``_HI``, the top three far apart, the top three not above ``_HI``):
    solve those with :func:`~posernet.sync.spectral.top3_dense`.
    """
    G, M, _ = N.shape
    chunk = _chunk(M) if chunk is None else chunk
    Q = torch.empty_like(Vt)
    ok = torch.empty(G, dtype=torch.bool, device=N.device)
    bufs = (torch.empty(min(chunk, G), M, M, dtype=N.dtype, device=N.device),
            torch.empty(min(chunk, G), M, M, dtype=N.dtype, device=N.device))
    for lo in range(0, G, chunk):
        hi = min(G, lo + chunk)
        Z0 = N[lo:hi] * _C1
        Z0.diagonal(dim1=-2, dim2=-1).add_(_C0)
        Q[lo:hi], ok[lo:hi] = _filter(Z0, Vt[lo:hi], squarings, first, passes, bufs)
    return Q, ok


# --------------------------------------------------------------------------- the IRLS


_COMPACT = 0.1  # drop the stopped components once they are this share of the batch


def _pattern(prob: PaddedProblem) -> Tensor:
    """The relative rotations in ``N``'s layout with unit weights, coordinates in
    component-major order (row ``a n + j``: component ``a`` of node ``j``) ``[G, 3n, 3n]``:
    block ``(j, i)`` is ``R_e`` for stored edge ``e = i -> j``, block ``(i, j)`` its
    transpose, the diagonal of valid nodes 1, everything else 0. A symmetric permutation of
    :func:`~posernet.sync.spectral.dense_N`'s layout (same spectrum), in which scaling by the
    ``[G, n, n]`` weights is one elementwise product over contiguous rows."""
    G, n, m = prob.G, prob.n, prob.m
    em = prob.edge_mask
    g = torch.arange(G, device=em.device)[:, None].expand(G, m)[em]
    src, dst = prob.src[em], prob.dst[em]
    P = torch.zeros(G, 3, n, 3, n, dtype=prob.R.dtype, device=prob.R.device)
    blk = prob.R[em]
    P[g, :, dst, :, src] = blk  # each (component, ordered pair) occurs once
    P[g, :, src, :, dst] = blk.mT
    P = P.view(G, 3 * n, 3 * n)
    P.diagonal(dim1=-2, dim2=-1).copy_(prob.node_mask.repeat(1, 3))
    return P


def _rotations(Qt: Tensor, s: Tensor, node_mask: Tensor) -> Tensor:
    """Rotations ``[9, G n]`` (entry-major; identity on padded nodes) from the basis rows
    ``Qt [G, 3, 3n]`` (component-major coordinates) of the top-3 eigenspace of ``N``: as
    :func:`~posernet.sync.spectral.rotations_from_eigvecs` does from the eigenvectors, in a
    gauge of its own: rows scaled by ``D3^{-1/2}``, orthonormalised, handedness by the sum of
    the blocks' determinants, blocks projected onto SO(3)."""
    G, _, M = Qt.shape
    n = M // 3
    # the rows of Qt are orthonormal, so the scaled rows' condition number is at most the
    # spread of s: one Cholesky QR pass is round-off (~eps * 16) up to a spread of 4
    big = torch.where(node_mask, s, torch.zeros_like(s)).amax(1)
    small = torch.where(node_mask, s, torch.full_like(s, float("inf"))).amin(1)
    spread = float((big / small).max()) if G else 1.0
    Rt = orth_rows(Qt * (s * node_mask).repeat(1, 3)[:, None, :], passes=1 if spread <= 4 else 2)
    # blocks B_j[a, c] = Rh[a n + j, c] = Rt[c, a n + j] -> entry-major [9, G n]
    a = Rt.view(G, 3, 3, n).permute(2, 1, 0, 3).reshape(9, G * n)
    det = _det(a, _cof(a)).view(G, n)
    flip = (det * node_mask).sum(1) < 0
    if bool(flip.any()):  # the first basis vector: column 0 of every block
        a[0::3] *= torch.where(flip, -1.0, 1.0).to(a.dtype).repeat_interleave(n)
    R9, ok = polar9(a, _POLAR_FIRST)
    if not bool(ok.all()):  # farther from a rotation: more Newton steps, then an SVD
        bad = (~ok).nonzero().squeeze(1)
        R9[:, bad], okb = polar9(a[:, bad])
        bad = bad[~okb]
        if bad.numel():
            R9[:, bad] = project_to_so3(a[:, bad].T.reshape(-1, 3, 3)).reshape(-1, 9).T
    eye = torch.eye(3, dtype=R9.dtype, device=R9.device).reshape(9, 1)
    return torch.where(node_mask.reshape(1, -1), R9, eye)


def _node_scales(src: Tensor, dst: Tensor, node_mask: Tensor, we: Tensor,
                 wd: Tensor) -> Tensor:
    """``D3^{-1/2}`` per node ``[C, n]`` (1 on padded nodes) from the weights ``we [C, m]``,
    ``wd [C]`` and the edges ``src``/``dst [C, m]``."""
    C, n = node_mask.shape
    deg = wd[:, None].expand(C, n).clone()
    deg.scatter_add_(1, src, we).scatter_add_(1, dst, we)  # padded edges add 0 to node 0
    return torch.where(node_mask, deg, torch.ones_like(deg)).rsqrt()


def _subspace(pat: Tensor, src: Tensor, dst: Tensor, node_mask: Tensor, s: Tensor, we: Tensor,
              wd: Tensor, Vt: Tensor, first: int,
              bufs: tuple[Tensor, Tensor, Tensor]) -> Tensor:
    """The top-3 eigenspace of ``N`` for one chunk of ``C`` components: orthonormal rows
    ``[C, 3, 3n]`` from ``pat [C, 3n, 3n]`` (:func:`_pattern`), ``src``/``dst [C, m]``,
    ``node_mask [C, n]``, node scales ``s [C, n]`` (:func:`_node_scales`), weights ``we [C,
    m]``, ``wd [C]`` and start rows ``Vt [C, 3, 3n]``; the filter, or ``eigh`` where it fails.
    ``bufs``: three ``[>= C, 3n, 3n]`` work arrays (``Z0`` and the filter's two)."""
    C, n = node_mask.shape
    # N: block (j, i) scaled by s_i s_j w_e, the diagonal by s_j^2 w_diag, padded nodes 0
    coef = s.gather(1, src) * s.gather(1, dst) * we
    W = torch.zeros(C, n * n, dtype=s.dtype, device=s.device)
    W.scatter_(1, dst * n + src, coef).scatter_(1, src * n + dst, coef)
    W = W.view(C, n, n)
    W.diagonal(dim1=-2, dim2=-1).copy_(  # overwrites the zeros padded edges put on (0, 0)
        torch.where(node_mask, wd[:, None] * s * s, torch.zeros_like(s)))
    # the filter's Z0 = _C1 N + _C0 I straight from the weights (N itself is not needed)
    Z0 = bufs[2][:C]  # written in place: a fresh array of this size costs its page faults
    torch.mul(W.mul_(_C1).view(C, 1, n, 1, n), pat.view(C, 3, n, 3, n),
              out=Z0.view(C, 3, n, 3, n))
    Z0.diagonal(dim1=-2, dim2=-1).add_(_C0)
    Qt, ok = _filter(Z0, Vt, _SQUARINGS, first, _PASSES, bufs[:2])
    if not bool(ok.all()):
        bad = (~ok).nonzero().squeeze(1)
        Nb = (Z0[bad] - _C0 * torch.eye(3 * n, dtype=Z0.dtype, device=Z0.device)) / _C1
        Nb.diagonal(dim1=-2, dim2=-1).add_(
            torch.where(node_mask[bad], 0.0, -2.0).to(Nb.dtype).repeat(1, 3))
        Qt[bad] = top3_dense(Nb).mT
    return Qt


def _reweight(Qt: Tensor, s: Tensor, src: Tensor, dst: Tensor, edge_mask: Tensor,
              node_mask: Tensor, count: Tensor, we: Tensor, wd: Tensor, wp: Tensor | None,
              Re9: Tensor, theta: float, tol: float) -> tuple[Tensor, Tensor, Tensor]:
    """The rest of an IRLS iteration of ``C`` components, given the basis rows ``Qt [C, 3,
    3n]`` and the node scales ``s [C, n]``: rotations, residuals against the edge rotations
    ``Re9 [9, C m]``, the new weights ``[C, m]``, ``[C]`` (times the prior ``wp [C, m]`` if
    given) and the stop flags ``[C]`` (relative weight change ``<= tol``). Run on the whole
    batch at once: its elementwise work is then large enough to be split between threads."""
    C, n = node_mask.shape
    m = src.shape[1]
    R9 = _rotations(Qt, s, node_mask)
    base = (torch.arange(C, device=src.device) * n)[:, None]
    res = edge_residuals(R9, Re9, (base + src).flatten(), (base + dst).flatten()).view(C, m)
    res = torch.where(edge_mask, res, torch.zeros_like(res))
    w_new = mad_cauchy_weights(res, edge_mask, theta)
    if wp is not None:
        w_new = w_new * wp
    wd_new = w_new.amax(dim=1)
    cnt = count.to(we.dtype)
    # |W_old - W|_F / (|W|_F n) over the full symmetric n x n weight matrix.
    num = (2 * ((we - w_new) ** 2).sum(1) + cnt * (wd - wd_new) ** 2).sqrt()
    den = (2 * (w_new ** 2).sum(1) + cnt * wd_new ** 2).sqrt() * cnt
    return w_new, wd_new, num / den.clamp_min(1e-300) <= tol


def dense_irls(prob: PaddedProblem, w_edge: Tensor, w_diag: Tensor, max_iters: int,
               tol: float, theta: float, seed: int,
               w_prior: Tensor | None) -> RotationSolution:
    """The robust dense IRLS of :func:`~posernet.sync.irls.rotation_irls` from the start
    weights ``w_edge [G, m]``, ``w_diag [G]`` (``w_prior [G, m]``: multiplies every later
    Cauchy weight, or ``None``). Returns the
    :class:`~posernet.sync.spectral.RotationSolution` (see the module docstring).

    Each iteration filters a chunk of components at a time (:func:`_chunk`; their work arrays
    stay in the cache) and re-weights the whole batch. Components that stop stay in the batch
    (frozen: their weights no longer change) until they are :data:`_COMPACT` of it, then the
    batch is rebuilt without them and trimmed to the largest remaining component.
    """
    G, n, m, dev, dt = prob.G, prob.n, prob.m, prob.R.device, prob.R.dtype
    used_edge, used_diag = w_edge.clone(), w_diag.clone()
    iters = torch.zeros(G, dtype=torch.long, device=dev)
    converged = torch.zeros(G, dtype=torch.bool, device=dev)
    last_n = torch.zeros(G, dtype=torch.long, device=dev)  # padded size of the last solve
    # a CPU generator: the same start on every device
    gen = torch.Generator().manual_seed(seed)
    rows = prob.node_mask.repeat(1, 3)[:, None, :].to(dt)
    Vt = torch.randn(G, 3, 3 * n, generator=gen, dtype=dt).to(dev) * rows
    # the components in the batch (their ids, problem, pattern, edge rotations entry-major,
    # weights) and which of them still iterate
    idx, sub, pat = torch.arange(G, device=dev), prob, _pattern(prob)
    Re9 = prob.R.reshape(G * m, 9).T.contiguous()
    we, wd, wp = w_edge, w_diag, w_prior
    live = torch.ones(G, dtype=torch.bool, device=dev)
    for k in range(1, max_iters + 1):
        Gs, ns, ms = sub.G, sub.n, sub.m
        chunk = _chunk(3 * ns)
        bufs = tuple(torch.empty(min(chunk, Gs), 3 * ns, 3 * ns, dtype=dt, device=dev)
                     for _ in range(3))
        s = _node_scales(sub.src, sub.dst, sub.node_mask, we, wd)
        Qt = torch.empty_like(Vt)
        for lo in range(0, Gs, chunk):
            c = slice(lo, min(Gs, lo + chunk))
            Qt[c] = _subspace(pat[c], sub.src[c], sub.dst[c], sub.node_mask[c], s[c], we[c],
                              wd[c], Vt[c], 1 if k == 1 else _FIRST, bufs)
        w_new, wd_new, stop = _reweight(Qt, s, sub.src, sub.dst, sub.edge_mask, sub.node_mask,
                                        sub.count, we, wd, wp, Re9, theta, tol)
        lv = live.nonzero().squeeze(1)
        gl = idx[lv]
        used_edge[gl, :ms], used_diag[gl] = we[lv], wd[lv]
        iters[gl] = k
        last_n[gl] = int(sub.count[lv].max())  # the batch the solve-per-iteration loop had
        converged[gl[stop[lv]]] = True
        live = live & ~stop
        if not bool(live.any()):
            break
        we = torch.where(live[:, None], w_new, we)
        wd = torch.where(live, wd_new, wd)
        Vt = Qt
        if int(live.sum()) <= (1.0 - _COMPACT) * Gs:
            keep = live.nonzero().squeeze(1)
            idx, sub = idx[keep], sub.select(keep)
            n2, m2 = sub.n, sub.m
            pat = pat.view(Gs, 3, ns, 3, ns)[keep][:, :, :n2, :, :n2].reshape(
                -1, 3 * n2, 3 * n2)
            Vt = Qt.view(Gs, 3, 3, ns)[keep][..., :n2].reshape(-1, 3, 3 * n2)
            Re9 = Re9.view(9, Gs, ms)[:, keep, :m2].reshape(9, -1)
            we, wd = we[keep, :m2], wd[keep]
            wp = None if wp is None else wp[keep, :m2]
            live = live[keep]
    # The eigenvectors of every component's last solve: the matrix the solve-per-iteration
    # loop had (dense_N, padded to the size of its batch then), bit for bit.
    s = degrees(prob, used_edge, used_diag).rsqrt()
    N = dense_N(prob, used_edge, used_diag, s)
    R = torch.eye(3, dtype=dt, device=dev).expand(G, n, 3, 3).clone()
    V3 = torch.zeros(G, 3 * n, 3, dtype=dt, device=dev)
    Rh = torch.zeros_like(V3)
    for size in torch.unique(last_n).tolist():
        grp = (last_n == size).nonzero().squeeze(1)
        M = 3 * size
        V3g = top3_dense(N[grp, :M, :M])
        Rg, Rhg = rotations_from_eigvecs(V3g, s[grp, :size], prob.node_mask[grp, :size])
        R[grp, :size], V3[grp, :M], Rh[grp, :M] = Rg, V3g, Rhg
    return RotationSolution(R=R, V3=V3, Rh=Rh, w_edge=used_edge, w_diag=used_diag,
                            iterations=iters, converged=converged,
                            eig_converged=torch.ones(G, dtype=torch.bool, device=dev))

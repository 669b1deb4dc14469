"""Straightforward numpy/scipy EIG-SE3, one graph at a time: the literal published algorithm.

This is the yardstick for :mod:`posernet.sync.eig_se3` (tests check that the batched, structured
solver gives the same poses) and the baseline of ``benchmarks/bench_sync.py``. It follows the
authors' MATLAB ``SE3_eig`` / ``SE3_eig_IRLS`` step by step on the full ``4n x 4n`` matrix:

1. ``X`` with ``X_ab = M_a M_b^{-1}`` (stored edge ``i -> j`` with pose ``P``: ``X_ji = P``,
   ``X_ij = P^{-1}``), masked by the weights ``W`` (adjacency + identity);
2. the 4 eigenvectors of ``D^{-1} X`` with the largest real part -- dense ``numpy.linalg.eig``
   for small graphs, ARPACK ``scipy.sparse.linalg.eigs`` (as MATLAB's ``eigs``) for large ones;
3. change of basis: ``B`` = every 4th row, ``alpha`` = its 3 least right singular vectors,
   ``beta = B \\ 1``; ``U <- [U alpha, U beta]``; handedness; SO(3) projection of each block;
   translation column divided by the (4, 4) entry;
4. IRLS: rotation residuals, ``th = theta / 0.6745 * mad(r, 1)``, Cauchy weights, diagonal
   ``max(w)``, stop when ``|W_old - W|_F / (|W|_F n) <= tol`` or after ``max_iters`` solves.

Two choices make the output unique (the MATLAB code's depends on LAPACK's eigenvector
normalisation): the eigenvectors are replaced by an orthonormal real basis of their span, and
``beta`` is the minimum-norm least-squares solution. Handedness uses the sign of the sum of the
blocks' determinants. The same choices are made by the batched solver.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg

__all__ = ["ReferenceResult", "eig_se3_reference"]

_MAD_FLOOR = 1e-9  # same floor on the IRLS threshold as the batched solver (exact data)


@dataclass
class ReferenceResult:
    """``poses (n, 4, 4)`` world-to-camera, ``iterations``, final ``weights (E,)`` of the last
    solve, ``converged`` IRLS flag."""

    poses: np.ndarray
    iterations: int
    weights: np.ndarray
    converged: bool
    eigenvalues: np.ndarray = field(default_factory=lambda: np.zeros(0))


def _project_so3(A: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(A)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def _top4(P, sparse: bool) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues/vectors of the 4 eigenvalues of largest real part."""
    if sparse:
        n4 = P.shape[0]
        v0 = np.ones(n4) / np.sqrt(n4)
        vals, vecs = scipy.sparse.linalg.eigs(P, k=4, which="LR", v0=v0, tol=0,
                                              ncv=min(n4, 40), maxiter=100000)
    else:
        vals, vecs = np.linalg.eig(P)
    order = np.argsort(-vals.real, kind="stable")[:4]
    return vals[order], vecs[:, order]


def eig_se3_reference(num_nodes: int, edge_index: np.ndarray, rel_poses: np.ndarray,
                      robust: bool = True, max_iters: int = 50, tol: float = 1e-5,
                      theta: float = 2.0, use_sparse: bool | None = None) -> ReferenceResult:
    """EIG-SE3 (+ IRLS) on one connected graph.

    ``edge_index (2, E)`` stored edges ``i -> j``, ``rel_poses (E, 4, 4)`` their poses
    ``M_j M_i^{-1}``. ``use_sparse=None`` picks ARPACK when ``4n > 256``. Returns
    :class:`ReferenceResult`.
    """
    n = int(num_nodes)
    ei = np.asarray(edge_index, dtype=np.int64)
    P = np.asarray(rel_poses, dtype=np.float64)
    E = ei.shape[1]
    if n < 2 or E == 0:
        raise ValueError(f"need at least 2 nodes and 1 edge, got {n} nodes and {E} edges")
    if use_sparse is None:
        use_sparse = 4 * n > 256
    I, J = ei
    Pinv = np.linalg.inv(P)
    # Block coordinates of the 4n x 4n matrix: blocks (J, I) = P, (I, J) = P^{-1}, (a, a) = I4.
    r4 = np.arange(4)
    rows_blk = np.concatenate([J, I, np.arange(n)])
    cols_blk = np.concatenate([I, J, np.arange(n)])
    vals_blk = np.concatenate([P, Pinv, np.broadcast_to(np.eye(4), (n, 4, 4))])
    rr = (4 * rows_blk[:, None, None] + r4[None, :, None]) + 0 * r4[None, None, :]
    cc = (4 * cols_blk[:, None, None] + r4[None, None, :]) + 0 * r4[None, :, None]

    w = np.ones(E)
    w_diag = 1.0
    w_old, wd_old = w.copy(), w_diag
    k = 0
    delta = 2 * tol
    poses = np.tile(np.eye(4), (n, 1, 1))
    used = w.copy()
    evals = np.zeros(4)
    while k < (max_iters if robust else 1) and delta > tol:
        k += 1
        wb = np.concatenate([w, w, np.full(n, w_diag)])
        deg = np.bincount(I, w, n) + np.bincount(J, w, n) + w_diag
        Xv = vals_blk * wb[:, None, None]
        data = (Xv / deg[rows_blk][:, None, None]).ravel()  # rows of D^{-1} X
        if use_sparse:
            Pm = scipy.sparse.csr_matrix((data, (rr.ravel(), cc.ravel())), shape=(4 * n, 4 * n))
        else:
            Pm = np.zeros((4 * n, 4 * n))
            np.add.at(Pm, (rr.ravel(), cc.ravel()), data)
        evals, U = _top4(Pm, bool(use_sparse))
        # Orthonormal real basis of the eigenvectors' span.
        U = scipy.linalg.svd(np.concatenate([U.real, U.imag], axis=1),
                             full_matrices=False)[0][:, :4]
        B = U[3::4]
        Vt = np.linalg.svd(B)[2]
        alpha = Vt[-3:].T
        beta = np.linalg.pinv(B, rcond=1e-12) @ np.ones(n)
        U = np.concatenate([U @ alpha, (U @ beta)[:, None]], axis=1)
        blocks = U.reshape(n, 4, 4)
        if np.linalg.det(blocks[:, :3, :3]).sum() < 0:
            blocks[:, :, 0] *= -1
        Rs = _project_so3(blocks[:, :3, :3])
        ts = blocks[:, :3, 3] / blocks[:, 3, 3][:, None]
        poses = np.tile(np.eye(4), (n, 1, 1))
        poses[:, :3, :3], poses[:, :3, 3] = Rs, ts
        used = w.copy()
        if not robust:
            break
        res = np.linalg.norm(Rs[J] @ np.swapaxes(Rs[I], -1, -2) - P[:, :3, :3], axis=(1, 2))
        mad = np.median(np.abs(res - np.median(res)))
        th = max(theta / 0.6745 * mad, _MAD_FLOOR)
        w = 1.0 / (1.0 + (res / th) ** 2)
        w_diag = float(w.max())
        num = np.sqrt(2 * np.sum((w_old - w) ** 2) + n * (wd_old - w_diag) ** 2)
        den = np.sqrt(2 * np.sum(w ** 2) + n * w_diag ** 2) * n
        delta = num / den
        w_old, wd_old = w.copy(), w_diag
    return ReferenceResult(poses=poses, iterations=k, weights=used,
                           converged=(not robust) or delta <= tol, eigenvalues=evals)

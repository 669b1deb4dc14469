"""Robust bundle adjustment: Levenberg-Marquardt with exact Schur-complement steps, reweighted
by a per-observation robust loss; analytic sparse Jacobian. (Two scipy-based solvers that
stood beside it lost on every problem of ``benchmarks/bench_ba.py``: slower at equal
accuracy, or less accurate, and were removed.)

Unknowns: per camera a rotation increment ``w`` (angle-axis, ``R = exp(w) R_0``: starts at 0,
stays far from the pi wrap of a rotation vector) and translation ``t``; per point ``X``;
optionally a log focal scale (one shared or one per camera, ``fx, fy, skew`` scaled by
``exp(s)``). Residuals: undistorted pixel minus projection, 2 per observation, in pixels; the
robust loss (on each observation's 2D error) uses ``f_scale`` in pixels.

Gauge: one camera per connected component (cameras linked by shared points) keeps its pose;
the global scale is left free (the Jacobian has one null direction that the trust region
damps), so camera positions are only defined up to one global scale per component.

Failure policy: the input poses are never lost. ``BundleResult.w2c`` is the BA output only
when it converged (or ``accept_unconverged``), is finite and did not raise the robust cost;
otherwise it is the input, and ``accepted`` is False with the reason in ``message``.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from itertools import pairwise

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.sparse import bsr_matrix, coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components

from ..options import check_options, option
from ..threads import available_cores

__all__ = ["LOSSES", "BundleOptions", "BundleResult", "bundle_adjust", "gauge_cameras"]

LOSSES: tuple[str, ...] = ("linear", "huber", "soft_l1", "cauchy", "arctan")
#: ``auto`` is for callers that know where the intrinsics came from (``posernet.reconstruction``
#: resolves it: refine when they were guessed); :func:`bundle_adjust` itself reads it as ``none``
FOCAL_MODES: tuple[str, ...] = ("none", "shared", "per_camera", "auto")
GAUGES: tuple[str, ...] = ("max_degree", "first")
#: where the adjustment of a component starts: ``averaged`` (the motion-averaging poses),
#: ``positioning`` (the averaged rotations with centres and points solved together from their
#: rays, :mod:`posernet.sfm.positioning`), ``incremental`` (cameras registered one at a time
#: by PnP from a seed pair, :mod:`posernet.sfm.incremental`) or ``auto`` (the averaged start;
#: when its adjustment is in doubt -- a camera unrefined, less than ``explained_min`` of the
#: track observations explained, a camera seeing its points only at tiny angles, two centres
#: on one spot -- the positioning start too, and the incremental one when the better of them
#: is still in doubt; kept: the most refined cameras seeing their points at a useful angle,
#: then the most observations explained)
STARTS: tuple[str, ...] = ("auto", "averaged", "positioning", "incremental")


@dataclass
class BundleOptions:
    """Options of :func:`bundle_adjust` and of the orchestrator
    :func:`posernet.sfm.mapper.bundle_adjust_reconstruction`.

    Solver: ``loss`` (one of :data:`LOSSES`), ``f_scale`` (px: residuals beyond it are
    down-weighted), ``max_nfev`` (function evaluations; reaching it is a failure), tolerances,
    ``refine_focal`` (``"none"``, ``"shared"``, ``"per_camera"``; ``"auto"``: see
    :data:`FOCAL_MODES`), ``gauge`` (which camera per
    component stays fixed: ``"max_degree"`` most observations, or ``"first"``),
    ``accept_unconverged`` (keep an improved but unconverged result instead of the input),
    ``anneal_factor`` (robust losses start with ``f_scale`` at this many times the median
    error and shrink it to ``f_scale`` in stages, divided by ``anneal_step`` per stage; 0 turns
    this off).

    Orchestrator: ``max_reproj_px`` (observations above it after a BA are dropped; also the
    triangulation filter of later rounds), ``initial_reproj_factor`` (first triangulation, from
    motion-averaging poses that may be degrees off: a track is kept when its largest error is
    below ``max(max_reproj_px, factor * median track error)``), ``min_angle_deg`` (smallest
    triangulation angle), ``rounds`` (BA passes: BA, filter, BA, ...), ``min_points_per_camera``
    (cameras seeing fewer triangulated points keep their input pose and are flagged),
    ``start`` (:data:`STARTS`: the poses the adjustment starts from), ``explained_min`` (with
    ``start="auto"``, the share of track observations an adjustment from the averaged poses
    must explain, every camera refined, for the incremental start not to be tried) and
    ``incremental_max_cameras`` (larger components start from the averaged poses only).

    ``pcg_min_cameras``: the solver solves the reduced camera system of problems with at
    least this many variable cameras by conjugate gradients on the implicit Schur complement
    (block-Jacobi preconditioner) instead of a dense Cholesky factorisation, whose cost grows
    with the cube of the cameras (0: always, a huge value: never). ``threads``: threads that
    share that system's products (the block products of the direct solve, the passes over
    the observations of conjugate gradients; the same numbers with any count).
    """

    loss: str = option("cauchy", choices=LOSSES,
                       help="robust kernel on reprojection errors")
    f_scale: float = option(2.0, gt=0, help="px: errors beyond this are down-weighted")
    max_nfev: int = option(1000, ge=1, help="solver evaluations per adjustment; reaching it = "
                           "not converged")
    xtol: float = option(1e-10, gt=0, help="converged when a step is below this share of the "
                         "parameters")
    refine_focal: str = option("none", choices=FOCAL_MODES,
                               help="focal lengths refined with the poses; auto: refine "
                                    "guessed intrinsics, keep given ones")
    gauge: str = option("max_degree", choices=GAUGES,
                        help="the camera per component that keeps its pose")
    accept_unconverged: bool = option(False, help="keep an improved but unconverged result")
    anneal_factor: float = option(3.0, ge=0, help="robust losses start at this many times the "
                                  "median error (0: off)")
    anneal_step: float = option(4.0, gt=1, help="... and divide f_scale by this per stage")
    irls_tol: float = option(1e-5, gt=0, help="converged when a step lowers the robust cost by "
                             "less than this share")
    camera_tol: float = option(1e-4, ge=0, help="also converged when a step lowers the robust "
                               "cost by less than 10 x irls_tol and turns no camera by more "
                               "than this (rad) nor moves it by more than this share of the "
                               "cameras' spread (0: off)")
    max_reproj_px: float = option(4.0, gt=0, help="observations still above this after an "
                                  "adjustment are dropped")
    initial_reproj_factor: float = option(3.0, gt=0, help="first triangulation: tracks kept "
                                          "below this x the median track error")
    min_angle_deg: float = option(1.0, ge=0, help="smallest triangulation angle of a point")
    rounds: int = option(2, ge=1, help="adjust, drop outliers, adjust again")
    min_points_per_camera: int = option(15, ge=0, help="fewer points: the camera keeps its "
                                        "averaged pose (reported)")
    start: str = option("auto", choices=STARTS, help="poses BA starts from (auto: averaged, "
                        "then positioning and incremental when that one is in doubt)")
    incremental_max_cameras: int = option(40, ge=2, help="larger components are not "
                                          "registered incrementally")
    explained_min: float = option(0.75, ge=0, le=1, help="auto: other starts tried when the "
                                  "averaged one explains less than this share of the track "
                                  "observations")
    pair_explained_min: float = option(0.3, ge=0, le=1, help="auto: other starts tried also "
                                       "when a verified pair with pair_explained_matches "
                                       "matches or more keeps less than this share of them "
                                       "as common 3D points (a loop left open)")
    pair_explained_matches: int = option(100, ge=1, help="... counting pairs with this many "
                                         "matches")
    start_error_px: float = option(20.0, gt=0, help="auto: other starts tried also when the "
                                   "averaged start's median reprojection error is above "
                                   "this (px)")
    refocus: float = option(0.1, ge=0, help="posernet-reconstruct: when one guessed focal "
                            "length shared by every image moved by more than this share, the "
                            "pairs are verified again with the adjusted one and the cameras "
                            "placed again (0: never)")
    pcg_min_cameras: int = option(400, ge=0, help="lm: problems with this many variable "
                                  "cameras solve the reduced system by conjugate gradients")
    threads: int = option(0, ge=0, help="threads of the reduced camera system's products "
                          "(0: every available core)")

    def __post_init__(self) -> None:
        check_options(self)


@dataclass
class BundleResult:
    """Outcome of :func:`bundle_adjust`.

    ``w2c (N, 4, 4)``, ``points (P, 3)``, ``K (N, 3, 3)``: the BA output when ``accepted``,
    else the input unchanged. ``errors (O,)``: reprojection error (px) of every observation
    under the returned solution. Costs are the robust costs (scipy's ``0.5 * sum rho``).
    ``fixed_cameras``: the gauge cameras. Positions are up to one global scale per component.
    """

    w2c: np.ndarray
    points: np.ndarray
    K: np.ndarray
    converged: bool
    accepted: bool
    iterations: int
    initial_cost: float
    final_cost: float
    median_error_before: float
    mean_error_before: float
    median_error_after: float
    mean_error_after: float
    message: str
    errors: np.ndarray
    fixed_cameras: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    num_observations: int = 0
    seconds: float = 0.0

    def lines(self) -> list[str]:
        """Human-readable summary."""
        state = "converged" if self.converged else "NOT converged"
        kept = "output kept" if self.accepted else "input poses kept"
        return [
            f"bundle adjustment: {state}, {kept} ({self.message}); {self.iterations} "
            f"evaluations, {self.seconds:.2f} s, {self.num_observations} observations",
            f"reprojection error median/mean: {self.median_error_before:.3f}/"
            f"{self.mean_error_before:.3f} px -> {self.median_error_after:.3f}/"
            f"{self.mean_error_after:.3f} px; robust cost {self.initial_cost:.4g} -> "
            f"{self.final_cost:.4g}",
            "positions are up to one global scale (gauge: cameras "
            f"{self.fixed_cameras.tolist()} fixed, scale free)",
        ]


def _rho(z: np.ndarray, loss: str) -> tuple[np.ndarray, np.ndarray]:
    """Robust loss ``rho(z)`` and its derivative at ``z = (e / f_scale)^2`` (scipy's forms)."""
    if loss == "linear":
        return z, np.ones_like(z)
    if loss == "huber":
        big = z > 1
        sz = np.sqrt(np.where(big, z, 1.0))
        return np.where(big, 2 * sz - 1, z), np.where(big, 1 / sz, 1.0)
    if loss == "soft_l1":
        s = np.sqrt(1 + z)
        return 2 * (s - 1), 1 / s
    if loss == "cauchy":
        return np.log1p(z), 1 / (1 + z)
    return np.arctan(z), 1 / (1 + z**2)


def _robust_cost(r: np.ndarray, loss: str, f_scale: float) -> float:
    """``0.5 * f_scale^2 * sum_o rho(|e_o|^2 / f_scale^2)`` over observations ``o``; ``r`` is
    the flat residual vector (2 per observation). The loss acts on the 2D error of an
    observation (one outlier = one observation, not two independent coordinates)."""
    e2 = (r.reshape(-1, 2) ** 2).sum(1)
    return float(0.5 * f_scale**2 * _rho(e2 / f_scale**2, loss)[0].sum())


def _rotvec_to_matrix(w: np.ndarray) -> np.ndarray:
    """``(N, 3)`` rotation vectors -> ``(N, 3, 3)``: Rodrigues' formula in numpy (called once
    per solver evaluation on a few cameras, where a torch call costs 20x more; scipy's
    Rotation, the same values, costs 0.15-0.2 s of import in a run that needs nothing else of
    ``scipy.spatial``)."""
    W, sinc, cosc, _ = _so3_series(w)
    return np.eye(3) + sinc[:, None, None] * W + cosc[:, None, None] * (W @ W)


def _so3_series(w: np.ndarray) -> tuple[np.ndarray, ...]:
    """For rotation vectors ``w (N, 3)``: ``hat(w) (N, 3, 3)`` and the coefficients
    ``sin t / t``, ``(1 - cos t) / t^2`` and ``(t - sin t) / t^3`` ``(N,)`` of ``t = |w|``,
    by their series near zero, which the exponential and its left Jacobian are made of."""
    th = np.linalg.norm(w, axis=1)
    small = th < 1e-5
    ths = np.where(small, 1.0, th)
    sinc = np.where(small, 1.0 - th**2 / 6, np.sin(ths) / ths)
    cosc = np.where(small, 0.5 - th**2 / 24, (1 - np.cos(ths)) / ths**2)
    third = np.where(small, 1.0 / 6 - th**2 / 120, (ths - np.sin(ths)) / ths**3)
    return _hat(w), sinc, cosc, third


def _hat(v: np.ndarray) -> np.ndarray:
    """``(M, 3)`` -> skew matrices ``(M, 3, 3)`` with ``hat(a) b = a x b``."""
    z = np.zeros(v.shape[0])
    return np.stack((np.stack((z, -v[:, 2], v[:, 1]), 1),
                     np.stack((v[:, 2], z, -v[:, 0]), 1),
                     np.stack((-v[:, 1], v[:, 0], z), 1)), 1)


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian ``(N, 3, 3)``: ``exp(w + d) ~ exp(J_l(w) d) exp(w)``."""
    W, _, cosc, third = _so3_series(w)
    return np.eye(3) + cosc[:, None, None] * W + third[:, None, None] * (W @ W)


def gauge_cameras(obs_image: np.ndarray, obs_point: np.ndarray, num_cameras: int,
                  num_points: int, mode: str = "max_degree") -> np.ndarray:
    """One gauge camera per connected component of the camera-point graph, ``(C,)`` indices.

    ``mode="max_degree"``: the camera with the most observations of its component (its pose is
    the best constrained); ``"first"``: the smallest index. Cameras without observations are
    not part of any component.
    """
    if obs_image.size == 0:
        return np.zeros(0, np.int64)
    n = num_cameras + num_points
    g = coo_matrix((np.ones(obs_image.size, np.int8), (obs_image, num_cameras + obs_point)),
                   shape=(n, n))
    _, label = connected_components(g, directed=False)
    deg = np.bincount(obs_image, minlength=num_cameras)
    cams = np.flatnonzero(deg > 0)
    score = -deg[cams] if mode == "max_degree" else np.zeros(cams.size)
    order = np.lexsort((cams, score, label[cams]))
    lab = label[cams][order]
    first = np.ones(lab.size, bool)
    first[1:] = lab[1:] != lab[:-1]
    return np.sort(cams[order][first]).astype(np.int64)


class _Problem:
    """Residuals and analytic sparse Jacobian of one BA problem (see the module docstring)."""

    def __init__(self, w2c: np.ndarray, points: np.ndarray, K: np.ndarray, xy: np.ndarray,
                 cam: np.ndarray, pt: np.ndarray, fixed: np.ndarray, focal: str) -> None:
        N, P = w2c.shape[0], points.shape[0]
        self.R0, self.t0, self.X0, self.K = w2c[:, :3, :3], w2c[:, :3, 3], points, K
        # Observations sorted by camera: per-camera products become plain (n, 3) @ (3, 3)
        # BLAS calls instead of slow batched 3x3 products. Residuals are in this order;
        # ``unsort`` maps per-observation values back to the caller's order.
        self.order = np.argsort(cam, kind="stable")
        self.xy, self.cam, self.pt = xy[self.order], cam[self.order], pt[self.order]
        cam, pt = self.cam, self.pt
        counts = np.bincount(cam, minlength=N)
        ends = np.cumsum(counts)
        self.segs = [(int(c), int(ends[c] - counts[c]), int(ends[c]))
                     for c in np.flatnonzero(counts)]
        seen_cam = counts > 0
        var_cam = seen_cam.copy()
        var_cam[fixed] = False
        self.var_cam = np.flatnonzero(var_cam)
        fixed_seen = np.intersect1d(np.asarray(fixed, np.int64), np.flatnonzero(seen_cam))
        # one gauge camera: the scale can be held by rescaling about its centre
        self.gauge_centre = (-self.R0[fixed_seen[0]].T @ self.t0[fixed_seen[0]]
                             if fixed_seen.size == 1 else None)
        self.var_pt = np.flatnonzero(np.bincount(pt, minlength=P) > 0)
        self.cam_col = np.full(N, -1, np.int64)
        self.cam_col[self.var_cam] = 6 * np.arange(self.var_cam.size)
        off = 6 * self.var_cam.size
        self.pt_col = np.full(P, -1, np.int64)
        self.pt_col[self.var_pt] = off + 3 * np.arange(self.var_pt.size)
        off += 3 * self.var_pt.size
        # Focal groups: -1 = not refined.
        self.f_group = np.full(N, -1, np.int64)
        if focal == "shared":
            self.f_group[seen_cam] = 0
        elif focal == "per_camera":
            self.f_group[seen_cam] = np.arange(int(seen_cam.sum()))
        self.n_focal = int(self.f_group.max()) + 1 if (self.f_group >= 0).any() else 0
        self.f_off = off
        self.n_params = off + self.n_focal
        self.perm = None  # CSR layout of the Jacobian, built on first use (trf solvers only)

    def x0(self) -> np.ndarray:
        x = np.zeros(self.n_params)
        cams = self.cam_col[self.var_cam]
        x[cams[:, None] + np.arange(3, 6)] = self.t0[self.var_cam]
        x[self.pt_col[self.var_pt][:, None] + np.arange(3)] = self.X0[self.var_pt]
        return x

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, ...]:
        """``x`` -> rotation increments, ``R, t (N, ...)``, ``X (P, 3)``, ``K (N, 3, 3)``."""
        N = self.R0.shape[0]
        w = np.zeros((N, 3))
        t = self.t0.copy()
        cols = self.cam_col[self.var_cam][:, None]
        w[self.var_cam] = x[cols + np.arange(3)]
        t[self.var_cam] = x[cols + np.arange(3, 6)]
        R = _rotvec_to_matrix(w) @ self.R0
        X = self.X0.copy()
        X[self.var_pt] = x[self.pt_col[self.var_pt][:, None] + np.arange(3)]
        K = self.K.copy()
        if self.n_focal:
            has = self.f_group >= 0
            s = np.exp(x[self.f_off + self.f_group[has]])
            K[has, :2, :2] *= s[:, None, None]
        return w, R, t, X, K

    def unsort(self, values: np.ndarray) -> np.ndarray:
        """Per-observation ``values (O, ...)`` from the internal order to the caller's."""
        out = np.empty_like(values)
        out[self.order] = values
        return out

    def _project(self, x: np.ndarray) -> tuple[np.ndarray, ...]:
        w, R, t, X, K = self.unpack(x)
        c = self.cam
        Xo = X[self.pt]
        RX = np.empty_like(Xo)
        for ci, a, b in self.segs:
            RX[a:b] = Xo[a:b] @ R[ci].T
        p = RX + t[c]
        z = p[:, 2]
        n = p[:, :2] / z[:, None]
        fx, sk, fy = K[c, 0, 0], K[c, 0, 1], K[c, 1, 1]
        q = np.stack((fx * n[:, 0] + sk * n[:, 1], fy * n[:, 1]), 1)  # uv - principal point
        uv = q + K[c, :2, 2]
        return w, R, RX, z, q, uv, fx, sk, fy

    def residuals(self, x: np.ndarray) -> np.ndarray:
        uv = self._project(x)[5]
        return (uv - self.xy).ravel()

    def _build_structure(self) -> None:
        """Fixed CSR layout of the Jacobian; each call only fills the values."""
        O = self.cam.size
        obs = np.arange(O)
        rows, cols = [], []
        self.cam_obs = obs[self.cam_col[self.cam] >= 0]
        self.f_obs = obs[self.f_group[self.cam] >= 0]
        self.pt_obs = obs[self.pt_col[self.pt] >= 0]
        blocks = ((self.cam_obs, self.cam_col[self.cam[self.cam_obs]], 6),
                  (self.pt_obs, self.pt_col[self.pt[self.pt_obs]], 3),
                  (self.f_obs, self.f_off + self.f_group[self.cam[self.f_obs]], 1))
        for o, c0, width in blocks:
            # data order of a block: (obs, row 0/1, column 0..width-1)
            r = 2 * o[:, None, None] + np.arange(2)[None, :, None]
            cc = c0[:, None, None] + np.arange(width)[None, None, :]
            r, cc = np.broadcast_arrays(r, cc)
            rows.append(r.ravel())
            cols.append(cc.ravel())
        rows_a, cols_a = np.concatenate(rows), np.concatenate(cols)
        order = np.lexsort((cols_a, rows_a))
        self.perm = order
        self.indices = cols_a[order]
        self.indptr = np.concatenate(([0], np.cumsum(np.bincount(rows_a, minlength=2 * O))))
        self.shape = (2 * O, self.n_params)

    def blocks(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-observation Jacobian blocks (internal order): ``(O, 2, 6)`` rotation increment
        and translation of its camera, ``(O, 2, 3)`` its point, ``(O, 2)`` its log focal scale
        (whether or not those are variables)."""
        w, R, RX, z, q, _, fx, sk, fy = self._project(x)
        O = z.size
        inv_z = 1.0 / z
        # d uv / d p with p = R X + t: [[fx, sk, -q0], [0, fy, -q1]] / z.
        duv_dp = np.zeros((O, 2, 3))
        duv_dp[:, 0, 0] = fx * inv_z
        duv_dp[:, 0, 1] = sk * inv_z
        duv_dp[:, 1, 1] = fy * inv_z
        duv_dp[:, :, 2] = -q * inv_z[:, None]
        # d p / d w = -[R X]_x J_l(w), and a^T (-[v]_x) = (v x a)^T for each row a.
        cross = np.cross(RX[:, None, :], duv_dp)
        Jl = _left_jacobian(w)
        d_cam = np.empty((O, 2, 6))
        d_pt = np.empty_like(duv_dp)
        for ci, a, b in self.segs:
            d_cam[a:b, :, :3] = (cross[a:b].reshape(-1, 3) @ Jl[ci]).reshape(-1, 2, 3)
            d_pt[a:b] = (duv_dp[a:b].reshape(-1, 3) @ R[ci]).reshape(-1, 2, 3)
        d_cam[:, :, 3:] = duv_dp
        return d_cam, d_pt, q  # d uv / d log f = A n = q

    def jacobian(self, x: np.ndarray, row_weight: np.ndarray | None = None) -> csr_matrix:
        """Sparse ``(2 O, n_params)`` Jacobian, rows scaled by ``row_weight (2 O,)`` if given."""
        if self.perm is None:
            self._build_structure()
        d_cam, d_pt, d_f = self.blocks(x)
        data = []
        if self.cam_obs.size:
            data.append(d_cam[self.cam_obs].ravel())
        if self.pt_obs.size:
            data.append(d_pt[self.pt_obs].ravel())
        if self.f_obs.size:
            data.append(d_f[self.f_obs].ravel())
        vals = np.concatenate(data)[self.perm]
        if row_weight is not None:
            vals *= np.repeat(row_weight, np.diff(self.indptr))
        return csr_matrix((vals, self.indices, self.indptr), shape=self.shape)


def _gram(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Per-row ``A_o^T B_o`` of ``(O, 2, m)`` and ``(O, 2, n)`` blocks -> ``(O, m, n)``
    (batched matmul: faster than einsum or broadcast sums on tiny matrices)."""
    return np.matmul(A.transpose(0, 2, 1), B)


#: observations per slice of :func:`_segment_grams` (its ``(n, 6, 6)`` products, 9 MB)
_GRAM_CHUNK = 32768


def _segment_grams(A: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """``np.add.reduceat(_gram(A, A), starts, axis=0)`` for ``A (O, 2, m)`` without the
    ``(O, m, m)`` products at once: slices of about :data:`_GRAM_CHUNK` observations cut at
    segment starts (the same sums, in the same order)."""
    bounds = np.r_[starts, A.shape[0]]
    out = np.empty((starts.size, A.shape[2], A.shape[2]))
    k = 0
    while k < starts.size:
        stop = max(k + 1, int(np.searchsorted(bounds, bounds[k] + _GRAM_CHUNK, "right")) - 1)
        stop = min(stop, starts.size)
        a, b = bounds[k], bounds[stop]
        out[k:stop] = np.add.reduceat(_gram(A[a:b], A[a:b]), starts[k:stop] - a, axis=0)
        k = stop
    return out


def _subtract_upper_product(S: np.ndarray, W: np.ndarray, Vinv: np.ndarray, cols: np.ndarray,
                            indptr: np.ndarray, npt: int, threads: int = 1) -> None:
    """``S -= Y W^T`` in place, ``Y = W V^-1``: ``S (6 nc, 6 nc)``, ``W (O, 6, 3)`` one block
    per observation (block row: the camera, ``indptr (nc + 1,)``; block column: the point,
    ``cols (O,)``), ``Vinv (npt, 3, 3)`` symmetric per point, so that ``Y W^T`` is symmetric.
    Cameras go in groups; only the block rows of groups ``i <= j`` are multiplied (scipy BSR
    products) and the rest mirrored: about 0.6 of the block products of the whole product.
    ``Y`` is formed one group at a time, never whole (it and its gather of ``Vinv`` are as
    large as ``W``: tens of MB at a few hundred thousand observations). A group's products
    run on ``threads`` threads (scipy's sparse products release the GIL); each lands in its
    own blocks of ``S``, so the result does not depend on the count."""
    nc = indptr.size - 1
    bounds = np.unique(np.linspace(0, nc, max(1, min(8, nc // 32)) + 1).astype(np.int64))
    groups = []
    for a, b in pairwise(bounds.tolist()):
        lo, hi = indptr[a], indptr[b]
        ip = indptr[a:b + 1] - lo
        groups.append((a, b, lo, hi, ip,
                       bsr_matrix((W[lo:hi], cols[lo:hi], ip), shape=(6 * (b - a), 3 * npt))))
    pool = ThreadPoolExecutor(threads) if threads > 1 else None  # per call: nothing left over
    run = pool.map if pool is not None else map
    try:
        for i, (a, b, lo, hi, ip, _) in enumerate(groups):
            Y = np.matmul(W[lo:hi], Vinv[cols[lo:hi]])
            Yi = bsr_matrix((Y, cols[lo:hi], ip), shape=(6 * (b - a), 3 * npt))
            rest = groups[i:]
            products = run(lambda g, Yi=Yi: (Yi @ g[5].T).toarray(), rest)
            for (c, d, *_), P in zip(rest, products, strict=True):
                S[6 * a:6 * b, 6 * c:6 * d] -= P
                if c != a:
                    S[6 * c:6 * d, 6 * a:6 * b] -= P.T
    finally:
        if pool is not None:
            pool.shutdown()


def _row_blocks(A: csr_matrix, parts: int) -> list[tuple[int, int, csr_matrix]]:
    """``A``'s rows in ``parts`` ranges of about equal nonzeros, each a CSR matrix on views of
    ``A``'s arrays (no copy): ``(first row, end row, block)``."""
    n = A.shape[0]
    cuts = np.searchsorted(A.indptr, np.linspace(0, A.nnz, parts + 1)[1:-1])
    bounds = np.unique(np.r_[0, np.clip(cuts, 0, n), n])
    out = []
    for r0, r1 in pairwise(bounds.tolist()):
        p0, p1 = A.indptr[r0], A.indptr[r1]
        out.append((r0, r1, csr_matrix((A.data[p0:p1], A.indices[p0:p1],
                                        A.indptr[r0:r1 + 1] - p0), shape=(r1 - r0, A.shape[1]))))
    return out


class _RowSplit:
    """``A @ x`` for a CSR ``A`` with its rows shared between the threads of ``pool``: each
    row's product is computed as in one call (scipy's products release the GIL), so the result
    is the same to the bit."""

    def __init__(self, A: csr_matrix, pool: ThreadPoolExecutor | None, parts: int) -> None:
        self.A, self.pool = A, pool
        self.blocks = _row_blocks(A, parts) if pool is not None and parts > 1 else []

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        if len(self.blocks) < 2:
            return self.A @ x
        out = np.empty(self.A.shape[0], np.result_type(self.A.dtype, x.dtype))

        def part(block: tuple[int, int, csr_matrix]) -> None:
            r0, r1, B = block
            out[r0:r1] = B @ x

        for _ in self.pool.map(part, self.blocks):
            pass
        return out


class _Schur:
    """The normal equations of one weighted Jacobian, reduced onto the camera parameters.

    Built once per Jacobian from its per-observation blocks (:meth:`_Problem.blocks`, rows
    scaled by the weights), then solved for any damping (:meth:`step`): ``U`` (camera and focal
    parameters, dense), ``V`` (one 3x3 block per point), ``W`` (one 6x3 camera-point block per
    observation), so that the reduced system ``S = U - W V^-1 W^T`` costs one block-sparse
    product (scipy BSR) instead of generic sparse ones.

    ``iterative``: never form ``S``; :meth:`step` solves it by preconditioned conjugate
    gradients (:meth:`_step_pcg`), for problems with many cameras, where the dense ``S`` and
    its Cholesky factorisation (``(6 nc)^3 / 3`` flops) dominate.
    """

    #: conjugate gradients stop at this relative residual ``|S x - b| / |b|`` (the step then
    #: agrees with the direct solve to about this relative precision)
    pcg_rtol: float = 1e-8
    pcg_maxiter: int = 1000

    def __init__(self, prob: _Problem, d_cam: np.ndarray, d_pt: np.ndarray, d_f: np.ndarray,
                 r: np.ndarray, iterative: bool = False, threads: int = 1) -> None:
        nc, npt, nf = prob.var_cam.size, prob.var_pt.size, prob.n_focal
        self.nc, self.npt, self.nf = nc, npt, nf
        self.threads = threads
        self.iterative = bool(iterative) and nc > 0
        self.pcg_iterations: list[int] = []
        O = d_pt.shape[0]
        r = r.reshape(O, 2)
        pj = (prob.pt_col[prob.pt] - 6 * nc) // 3  # point index among the variable points
        # points: V and gradient, summed per point by a sparse aggregation matrix
        agg = csr_matrix((np.ones(O), (pj, np.arange(O))), shape=(npt, O))
        self.V = np.asarray(agg @ _gram(d_pt, d_pt).reshape(O, 9)).reshape(npt, 3, 3)
        self.gp = np.asarray(agg @ _gram(d_pt, r[:, :, None]).reshape(O, 3))
        # cameras: observations are sorted by camera, so per-camera sums are segment sums
        nP = 6 * nc + nf
        U = np.zeros((0, 0) if self.iterative else (nP, nP))
        g = np.zeros(nP)
        self.Ucc = np.zeros((nc, 6, 6))  # the cameras' diagonal blocks of U
        self.Uf = csr_matrix((nP, nP))  # iterative: U's focal rows and columns
        cv = prob.cam_col[prob.cam] >= 0  # observations of a variable camera
        self.ci = prob.cam_col[prob.cam[cv]] // 6  # ascending: index among variable cameras
        self.pj_c = pj[cv]
        self.Wc = np.zeros((0, 6, 3))
        if nc:
            A = d_cam if cv.all() else d_cam[cv]
            starts = np.flatnonzero(np.r_[True, self.ci[1:] != self.ci[:-1]])
            blocks = _segment_grams(A, starts)
            self.Ucc[self.ci[starts]] = blocks
            for k, c in enumerate([] if self.iterative else self.ci[starts]):
                U[6 * c:6 * c + 6, 6 * c:6 * c + 6] = blocks[k]  # one dense 6x6 per camera
            g[:6 * nc] = np.add.reduceat(_gram(A, r[cv][:, :, None])[..., 0], starts,
                                         axis=0).ravel()
            self.Wc = _gram(A, d_pt if cv.all() else d_pt[cv])
            self.indptr = np.searchsorted(self.ci, np.arange(nc + 1))
            # Few cameras: W V^-1 W^T as one dense BLAS product beats the block-sparse one
            # (whose cost grows with the observations per point squared, not with cameras).
            pair_blocks = float((np.bincount(self.pj_c, minlength=npt) ** 2).sum())
            dense_flops = 2.0 * (6 * nc) ** 2 * 3 * npt
            self.dense = (not self.iterative and (36.0 * nc * npt * 8 < 256e6)
                          and dense_flops < 2e3 * pair_blocks)
            if self.dense:
                self.rows = (6 * self.ci)[:, None, None] + np.arange(6)[None, :, None]
                self.cols = (3 * self.pj_c)[:, None, None] + np.arange(3)[None, None, :]
                self.Wd = np.zeros((6 * nc, 3 * npt))
                self.Wd[self.rows, self.cols] = self.Wc
        self.Wf = None
        if nf:
            fo = prob.f_group[prob.cam] >= 0
            fg = prob.f_group[prob.cam[fo]]
            f = d_f[fo]  # (n, 2)
            ff = np.bincount(fg, (f * f).sum(1), minlength=nf)
            if self.iterative:
                self.Uf = csr_matrix((ff, (6 * nc + np.arange(nf), 6 * nc + np.arange(nf))),
                                     shape=(nP, nP))
            else:
                U[6 * nc:, 6 * nc:] = np.diag(ff)
            g[6 * nc:] = np.bincount(fg, (f * r[fo]).sum(1), minlength=nf)
            both = fo & cv
            if both.any():
                cf = _gram(d_cam[both], d_f[both][:, :, None])[..., 0]  # (n, 6)
                rows = (6 * (prob.cam_col[prob.cam[both]] // 6))[:, None] + np.arange(6)
                cols = 6 * nc + prob.f_group[prob.cam[both]]
                Ms = csr_matrix((cf.ravel(), (rows.ravel(), np.repeat(cols, 6))),
                                shape=(nP, nP))
                if self.iterative:
                    self.Uf = (self.Uf + Ms + Ms.T).tocsr()
                else:
                    M = Ms.toarray()
                    U += M + M.T
            wf = _gram(f[:, :, None], d_pt[fo])[:, 0]  # (n, 3)
            self.Wf = csr_matrix((wf.ravel(), (np.repeat(fg, 3),
                                               ((3 * pj[fo])[:, None] + np.arange(3)).ravel())),
                                 shape=(nf, 3 * npt))
        self.U, self.g = U, g

    def step(self, lam: float) -> tuple[np.ndarray, np.ndarray]:
        """Camera-side and point steps ``(6 nc + nf,)``, ``(npt, 3)`` of the system damped by
        Marquardt's ``lam * diag`` (with a floor, so that gauge directions stay bounded)."""
        if self.iterative:
            return self._step_pcg(lam)
        nc, npt, nf = self.nc, self.npt, self.nf
        S = self.U.copy()
        S[np.diag_indices_from(S)] += lam * np.maximum(np.diag(self.U), 1e-9)
        V = self.V.copy()
        V[:, np.arange(3), np.arange(3)] += lam * np.maximum(
            np.diagonal(self.V, axis1=1, axis2=2), 1e-9)
        Vinv = np.linalg.inv(V)
        gp = self.gp
        Vg = np.einsum("pij,pj->pi", Vinv, gp)  # V^-1 g_p, (npt, 3)
        b = -self.g.copy()
        Wc_bsr = Yc_bsr = None
        if nc:
            shape = (6 * nc, 3 * npt)
            if self.dense:
                Y = np.matmul(self.Wc, Vinv[self.pj_c])  # W V^-1, a 6x3 block per observation
                Wc_bsr = self.Wd
                Yc_bsr = np.zeros(shape)
                Yc_bsr[self.rows, self.cols] = Y
                S[:6 * nc, :6 * nc] -= Yc_bsr @ self.Wd.T
            else:
                Wc_bsr = bsr_matrix((self.Wc, self.pj_c, self.indptr), shape=shape)
                _subtract_upper_product(S, self.Wc, Vinv, self.pj_c, self.indptr, npt,
                                        self.threads)
                if nf:  # the focal rows need W V^-1 whole
                    Yc_bsr = bsr_matrix((np.matmul(self.Wc, Vinv[self.pj_c]), self.pj_c,
                                         self.indptr), shape=shape)
            b[:6 * nc] += Wc_bsr @ Vg.ravel()
        if nf:
            VWf = csr_matrix(bsr_matrix((Vinv, np.arange(npt), np.arange(npt + 1)),
                                        shape=(3 * npt,) * 2) @ self.Wf.T).T
            ff = (self.Wf @ VWf.T).toarray()
            S[6 * nc:, 6 * nc:] -= ff
            if nc:
                fc = self.Wf @ Yc_bsr.T  # W_f V^-1 W_c^T, (nf, 6 nc)
                cf = (fc.toarray() if hasattr(fc, "toarray") else np.asarray(fc)).T
                S[:6 * nc, 6 * nc:] -= cf
                S[6 * nc:, :6 * nc] -= cf.T
            b[6 * nc:] += self.Wf @ Vg.ravel()
        try:
            dc = cho_solve(cho_factor(S, check_finite=False), b, check_finite=False)
        except np.linalg.LinAlgError:
            dc = np.linalg.lstsq(S, b, rcond=None)[0]
        wtd = np.zeros(3 * npt)
        if nc:
            wtd += Wc_bsr.T @ dc[:6 * nc]
        if nf:
            wtd += self.Wf.T @ dc[6 * nc:]
        dp = -Vg - np.einsum("pij,pj->pi", Vinv, wtd.reshape(npt, 3))
        return dc, dp

    def damping(self) -> tuple[np.ndarray, np.ndarray]:
        """The diagonals Marquardt's damping scales, ``(6 nc + nf,)`` and ``(npt, 3)``, with
        the floor :meth:`step` gives them."""
        if self.iterative:
            du = np.diagonal(self.Ucc, axis1=1, axis2=2).ravel()
            if self.nf:
                du = np.r_[du, self.Uf[6 * self.nc:, 6 * self.nc:].diagonal()]
        else:
            du = np.diag(self.U)
        return (np.maximum(du, 1e-9),
                np.maximum(np.diagonal(self.V, axis1=1, axis2=2), 1e-9))

    def predicted_decrease(self, lam: float, dc: np.ndarray, dp: np.ndarray) -> float:
        """How much the damped Gauss-Newton model says the step ``dc, dp`` of :meth:`step`
        lowers the cost: ``h^T (lam D h - g) / 2`` (the model's gradient ``g``, ``D`` the
        damped diagonal), which needs no product with the Jacobian."""
        du, dv = self.damping()
        return 0.5 * float(lam * (du * dc * dc).sum() - (self.g * dc).sum()
                           + lam * (dv * dp * dp).sum() - (self.gp * dp).sum())

    def _damped_v(self, lam: float) -> np.ndarray:
        """``(npt, 3, 3)`` inverses of the damped point blocks."""
        V = self.V.copy()
        V[:, np.arange(3), np.arange(3)] += lam * np.maximum(
            np.diagonal(self.V, axis1=1, axis2=2), 1e-9)
        return np.linalg.inv(V)

    def _step_pcg(self, lam: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`step` by conjugate gradients (scipy's ``cg``) on the reduced system
        ``S dc = b`` without forming ``S``: each product ``S x = U x - W (V^-1 (W^T x))`` costs
        a pass over the observations. Preconditioner: the inverse of ``S``'s 6x6 diagonal
        block per camera (and of its diagonal entry per focal parameter), as Ceres's
        ``ITERATIVE_SCHUR`` with ``SCHUR_JACOBI``. Stops at :attr:`pcg_rtol`."""
        from scipy.sparse.linalg import LinearOperator, cg

        nc, npt, nf = self.nc, self.npt, self.nf
        Vinv = self._damped_v(lam)
        Vg = np.einsum("pij,pj->pi", Vinv, self.gp)
        shape = (6 * nc, 3 * npt)
        Wc = csr_matrix(bsr_matrix((self.Wc, self.pj_c, self.indptr), shape=shape))
        WcT = Wc.T.tocsr()
        Vb = csr_matrix(bsr_matrix((Vinv, np.arange(npt), np.arange(npt + 1)),
                                   shape=(3 * npt, 3 * npt)))
        idx = np.arange(6)
        Ucc = self.Ucc.copy()
        Ucc[:, idx, idx] += lam * np.maximum(np.diagonal(self.Ucc, axis1=1, axis2=2), 1e-9)
        Ub = csr_matrix(bsr_matrix((Ucc, np.arange(nc), np.arange(nc + 1)),
                                   shape=(6 * nc, 6 * nc)))
        # S's diagonal blocks: U_ii - sum over camera i's observations of W_o V^-1 W_o^T
        WV = np.matmul(self.Wc, Vinv[self.pj_c])
        starts = self.indptr[:-1]
        P = Ucc - np.add.reduceat(np.matmul(WV, self.Wc.transpose(0, 2, 1)), starts, axis=0)
        try:
            Pinv = np.linalg.inv(P)
        except np.linalg.LinAlgError:
            Pinv = np.linalg.pinv(P)
        b = -self.g.copy()
        b[:6 * nc] += Wc @ Vg.ravel()
        if nf:
            Uff = self.Uf[6 * nc:, 6 * nc:].diagonal()
            fdamp = lam * np.maximum(Uff, 1e-9)
            Wf, WfT = self.Wf, self.Wf.T.tocsr()
            Ufc = self.Uf[:6 * nc, 6 * nc:]
            Ucf = self.Uf[6 * nc:, :6 * nc]
            b[6 * nc:] += Wf @ Vg.ravel()
            pf = Uff + fdamp - np.asarray((Wf @ Vb).multiply(Wf).sum(1)).ravel()
            pf = np.where(pf > 0, 1.0 / np.where(pf > 0, pf, 1.0), 0.0)

        # the passes over the observations shared between threads, row ranges each
        pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None
        Wc_, WcT_ = (_RowSplit(M, pool, self.threads) for M in (Wc, WcT))

        def matvec(x: np.ndarray) -> np.ndarray:
            xc = x[:6 * nc]
            wt = WcT_ @ xc
            out = np.empty_like(x)
            if nf:
                xf = x[6 * nc:]
                wt += WfT @ xf
                vw = Vb @ wt
                out[:6 * nc] = Ub @ xc + Ufc @ xf - Wc_ @ vw
                out[6 * nc:] = Ucf @ xc + (Uff + fdamp) * xf - Wf @ vw
            else:
                out[:] = Ub @ xc - Wc_ @ (Vb @ wt)
            return out

        def precond(x: np.ndarray) -> np.ndarray:
            out = np.empty_like(x)
            out[:6 * nc] = np.matmul(Pinv, x[:6 * nc].reshape(nc, 6, 1)).ravel()
            if nf:
                out[6 * nc:] = pf * x[6 * nc:]
            return out

        n = 6 * nc + nf
        count = [0]

        def tick(_: np.ndarray) -> None:
            count[0] += 1

        try:
            dc, _ = cg(LinearOperator((n, n), matvec=matvec), b, rtol=self.pcg_rtol,
                       maxiter=self.pcg_maxiter, M=LinearOperator((n, n), matvec=precond),
                       callback=tick)
        finally:
            if pool is not None:
                pool.shutdown()
        self.pcg_iterations.append(count[0])
        wtd = WcT @ dc[:6 * nc]
        if nf:
            wtd += WfT @ dc[6 * nc:]
        dp = -Vg - np.einsum("pij,pj->pi", Vinv, wtd.reshape(npt, 3))
        return dc, dp


def _pose_matrices(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (R.shape[0], 1, 1))
    T[:, :3, :3], T[:, :3, 3] = R, t
    return T


def _stats(err: np.ndarray) -> tuple[float, float]:
    if err.size == 0:
        return float("nan"), float("nan")
    return float(np.median(err)), float(np.mean(err))


def _variable_cameras(prob: _Problem, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotations ``(V, 3, 3)`` and centres ``(V, 3)`` of the variable cameras in ``x``."""
    _, R, t, _, _ = prob.unpack(x)
    R, t = R[prob.var_cam], t[prob.var_cam]
    return R, -np.einsum("nji,nj->ni", R, t)


def _spread(prob: _Problem, x: np.ndarray) -> float:
    """Mean distance of the variable cameras' centres from the gauge camera's."""
    c = _variable_cameras(prob, x)[1]
    return float(np.linalg.norm(c - prob.gauge_centre, axis=1).mean())


def _rescale(prob: _Problem, x: np.ndarray, spread: float) -> np.ndarray:
    """``x`` scaled about the gauge camera's centre so that :func:`_spread` is ``spread``:
    reprojections are unchanged, and the free scale cannot drift (to 0 or to infinity)."""
    now = _spread(prob, x)
    if not (np.isfinite(now) and now > 0 and spread > 0):
        return x
    k = spread / now
    c0 = prob.gauge_centre
    _, R, t, _, _ = prob.unpack(x)
    out = x.copy()
    cols = prob.cam_col[prob.var_cam][:, None] + np.arange(3, 6)
    c = -np.einsum("nji,nj->ni", R[prob.var_cam], t[prob.var_cam])
    out[cols] = -np.einsum("nij,nj->ni", R[prob.var_cam], c0 + k * (c - c0))
    pcols = prob.pt_col[prob.var_pt][:, None] + np.arange(3)
    out[pcols] = c0 + k * (x[pcols] - c0)
    return out


def _camera_move(prob: _Problem, x: np.ndarray, x_new: np.ndarray, spread: float
                 ) -> float:
    """The largest change of a variable camera from ``x`` to ``x_new``: its rotation angle
    (rad) or its centre's shift as a share of ``spread``, whichever is larger (inf without a
    spread)."""
    if not prob.var_cam.size:
        return 0.0
    if not spread > 0:
        return float("inf")
    R0, c0 = _variable_cameras(prob, x)
    R1, c1 = _variable_cameras(prob, x_new)
    # |R1 - R0|_F = 2 sqrt(2) sin(angle / 2): no arccos, which loses the small angles
    turn = np.linalg.norm(R1 - R0, axis=(1, 2)).max() / np.sqrt(2)
    shift = np.linalg.norm(c1 - c0, axis=1).max() / spread
    return float(max(turn, shift))


def _solve_lm(prob: _Problem, x0: np.ndarray, med0: float, opt: BundleOptions
              ) -> tuple[np.ndarray, np.ndarray, int, bool, str]:
    """Levenberg-Marquardt with exact Schur-complement steps and IRLS weights.

    Every iteration reweights the observations by ``rho'(|e|^2 / f^2)`` and takes a damped
    Gauss-Newton step (:class:`_Schur`), accepted when it lowers the robust cost at ``f``.
    The damping follows Nielsen's rule (Madsen, Nielsen & Tingleff, *Methods for non-linear
    least squares problems*, 2004): after a step it shrinks by up to 3x as far as the model
    predicted the decrease; a rejected step multiplies it by 2, 4, 8, ... in turn. A fixed
    "divide by 5 / multiply by 10" let it fall too low in the long curved valley of a free
    focal length (focal against scene depth), so that every other step was rejected: 744
    evaluations against 161 for the same optimum on 8 DTU views.
    Exact reduced solves keep their accuracy on ill-conditioned problems (long focal lengths,
    where rotation and translation nearly trade off) on which an iterative trust-region solve
    stalls. ``f`` anneals from ``anneal_factor`` x the median error to ``f_scale``, divided by
    ``anneal_step`` per stage (graduated robustness). Converged when a step at the final ``f``
    lowers the cost by less than ``irls_tol`` of it (or the step is below ``xtol``), or by
    less than ten times that while no camera turns or moves by more than ``camera_tol``
    (:func:`_camera_move`): on a well-posed problem the last steps of the reweighted solve
    still lower the cost by about 1e-5 of it each while moving the cameras by a thousandth
    of a degree, whereas a start that slides along a valley (centres collapsed onto one spot)
    lowers the cost as little while its cameras move by a tenth of the spread. Returns the
    parameters, the residuals, the evaluations used, whether it converged and why.
    """
    n_cam, n_pt = 6 * prob.var_cam.size, prob.var_pt.size
    x = x0
    hold = prob.gauge_centre is not None and prob.var_cam.size > 0
    spread0 = _spread(prob, x0) if hold else 0.0
    if opt.camera_tol > 0 and not hold and prob.var_cam.size:
        c = _variable_cameras(prob, x0)[1]
        spread_move = float(np.linalg.norm(c - c.mean(0), axis=1).mean())
    else:
        spread_move = spread0
    r = prob.residuals(x)
    fs = opt.f_scale
    if opt.anneal_factor > 0 and opt.loss != "linear":
        fs = max(opt.f_scale, opt.anneal_factor * med0)
    cost = _robust_cost(r, opt.loss, fs)
    nfev, lam, nu = 1, 1e-4, 2.0
    while nfev < opt.max_nfev:
        e2 = (r.reshape(-1, 2) ** 2).sum(1)
        sw = np.repeat(np.sqrt(_rho(e2 / fs**2, opt.loss)[1]), 2)
        system = None  # the previous system and blocks go before the new ones are made
        d_cam, d_pt, d_f = prob.blocks(x)
        w_obs = sw[::2, None]  # one weight per observation (both rows)
        d_cam *= w_obs[:, :, None]  # fresh arrays: weighted in place
        d_pt *= w_obs[:, :, None]
        d_f *= w_obs
        system = _Schur(prob, d_cam, d_pt, d_f, sw * r,
                        iterative=prob.var_cam.size >= opt.pcg_min_cameras,
                        threads=opt.threads or available_cores())
        del d_cam, d_pt, d_f
        while nfev < opt.max_nfev:
            dc, dp = system.step(lam)
            dx = np.zeros_like(x)
            dx[:n_cam] = dc[:n_cam]
            dx[n_cam:n_cam + 3 * n_pt] = dp.ravel()
            dx[n_cam + 3 * n_pt:] = dc[n_cam:]
            x_new = x + dx
            r_new = prob.residuals(x_new)
            nfev += 1
            cost_new = _robust_cost(r_new, opt.loss, fs) if np.isfinite(r_new).all() else np.inf
            if cost_new < cost:
                # Nielsen's update: damp less the better the model predicted the decrease
                pred = system.predicted_decrease(lam, dc, dp)
                rho = min((cost - cost_new) / pred, 1.0) if pred > 0 else 1.0
                lam, nu = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), 1e-12), 2.0
                break
            lam, nu = min(lam * nu, 1e12), 2.0 * nu
            if lam >= 1e12:
                break
        if not cost_new < cost:
            if fs <= opt.f_scale:
                return x, r, nfev, True, "no step lowers the robust cost (LM)"
            fs = max(opt.f_scale, fs / opt.anneal_step)
            cost = _robust_cost(r, opt.loss, fs)
            lam, nu = 1e-4, 2.0
            continue
        gain = cost - cost_new
        small = (gain <= opt.irls_tol * cost_new
                 or np.linalg.norm(dx) <= opt.xtol * (np.linalg.norm(x) + opt.xtol)
                 or (gain <= 10 * opt.irls_tol * cost_new and opt.camera_tol > 0
                     and _camera_move(prob, x, x_new, spread_move) <= opt.camera_tol))
        x, r, cost = (_rescale(prob, x_new, spread0) if hold else x_new), r_new, cost_new
        if fs > opt.f_scale:
            if small or gain <= 1e-3 * cost:
                fs = max(opt.f_scale, fs / opt.anneal_step)
                cost = _robust_cost(r, opt.loss, fs)
        elif small:
            return x, r, nfev, True, "robust cost converged (LM)"
    return x, r, nfev, False, "evaluation budget used up"


def bundle_adjust(w2c: np.ndarray, points: np.ndarray, K: np.ndarray, xy: np.ndarray,
                  obs_image: np.ndarray, obs_point: np.ndarray,
                  options: BundleOptions | None = None,
                  fixed_cameras: np.ndarray | None = None) -> BundleResult:
    """Robust bundle adjustment of cameras and points; never raises on bad numbers.

    ``w2c (N, 4, 4)``, ``points (P, 3)``, ``K (N, 3, 3)``; observations: undistorted pixels
    ``xy (O, 2)`` of point ``obs_point (O,)`` in image ``obs_image (O,)``. Cameras and points
    without observations are left as they are. ``fixed_cameras``: poses to hold fixed
    (default: :func:`gauge_cameras`). Shape errors raise ValueError; empty or non-finite input
    and solver failures come back as ``accepted=False`` with the input unchanged.
    """
    opt = options or BundleOptions()
    t_start = time.perf_counter()
    w2c = np.asarray(w2c, np.float64)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    K = np.asarray(K, np.float64)
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    obs_image = np.asarray(obs_image, np.int64).reshape(-1)
    obs_point = np.asarray(obs_point, np.int64).reshape(-1)
    N, P, O = w2c.shape[0], points.shape[0], xy.shape[0]
    if w2c.shape != (N, 4, 4) or K.shape != (N, 3, 3):
        raise ValueError(f"w2c must be (N, 4, 4) and K (N, 3, 3), got {w2c.shape}, {K.shape}")
    if obs_image.shape != (O,) or obs_point.shape != (O,):
        raise ValueError(f"obs_image and obs_point must be ({O},), got {obs_image.shape}, "
                         f"{obs_point.shape}")
    if O and (obs_image.min() < 0 or obs_image.max() >= N or obs_point.min() < 0
              or obs_point.max() >= P):
        raise ValueError("obs_image / obs_point index out of range")

    def fail(msg: str, err: np.ndarray | None = None, cost: float = float("nan"),
             fixed: np.ndarray | None = None, nfev: int = 0) -> BundleResult:
        e = err if err is not None else np.full(O, np.nan)
        med, mean = _stats(e[np.isfinite(e)])
        return BundleResult(w2c=w2c.copy(), points=points.copy(), K=K.copy(), converged=False,
                            accepted=False, iterations=nfev, initial_cost=cost,
                            final_cost=cost, median_error_before=med, mean_error_before=mean,
                            median_error_after=med, mean_error_after=mean, message=msg,
                            errors=e, fixed_cameras=(fixed if fixed is not None
                                                     else np.zeros(0, np.int64)),
                            num_observations=O, seconds=time.perf_counter() - t_start)

    if O == 0:
        return fail("no observations")
    cams = np.unique(obs_image)
    used_pts = np.unique(obs_point)
    if not (np.isfinite(w2c[cams]).all() and np.isfinite(K[cams]).all()
            and np.isfinite(points[used_pts]).all() and np.isfinite(xy).all()):
        return fail("non-finite input (NaN/inf in poses, intrinsics, points or observations)")
    fixed = (gauge_cameras(obs_image, obs_point, N, P, opt.gauge) if fixed_cameras is None
             else np.unique(np.asarray(fixed_cameras, np.int64)))
    prob = _Problem(w2c, points, K, xy, obs_image, obs_point, fixed, opt.refine_focal)
    x0 = prob.x0()
    r0 = prob.residuals(x0)
    err0 = prob.unsort(np.linalg.norm(r0.reshape(-1, 2), axis=1))
    if not np.isfinite(r0).all():
        return fail("non-finite residuals at the start (a point at depth 0?)", err0,
                    fixed=fixed)
    cost0 = _robust_cost(r0, opt.loss, opt.f_scale)
    med0, mean0 = _stats(err0)
    if prob.n_params == 0:
        return fail("nothing to optimise (all cameras fixed, no points)", err0, cost0, fixed)
    try:
        solve = _solve_lm
        x, r1, nfev, converged, msg = solve(prob, x0, med0, opt)
    except (ValueError, np.linalg.LinAlgError, FloatingPointError) as exc:
        return fail(f"solver error: {exc}", err0, cost0, fixed)
    _, R, t, X, K_new = prob.unpack(x)
    cost1 = _robust_cost(r1, opt.loss, opt.f_scale)
    err1 = prob.unsort(np.linalg.norm(r1.reshape(-1, 2), axis=1))
    finite = bool(np.isfinite(x).all() and np.isfinite(r1).all())
    if not finite:
        return fail("solver returned non-finite values", err0, cost0, fixed, nfev)
    if not converged and not opt.accept_unconverged:
        r = fail(f"not converged within max_nfev={opt.max_nfev} ({msg})", err0, cost0,
                 fixed, nfev)
        r.final_cost = cost1  # what the unconverged solution reached (not returned)
        return r
    if cost1 > cost0:
        return fail(f"robust cost rose {cost0:.4g} -> {cost1:.4g}", err0, cost0, fixed, nfev)
    med1, mean1 = _stats(err1)
    return BundleResult(w2c=_pose_matrices(R, t), points=X, K=K_new, converged=converged,
                        accepted=True, iterations=nfev, initial_cost=cost0,
                        final_cost=cost1, median_error_before=med0, mean_error_before=mean0,
                        median_error_after=med1, mean_error_after=mean1,
                        message=msg, errors=err1, fixed_cameras=fixed,
                        num_observations=O, seconds=time.perf_counter() - t_start)

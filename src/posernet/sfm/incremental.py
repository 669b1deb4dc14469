"""Incremental registration of one component's cameras: the start that motion averaging cannot
give where two-view geometry is ambiguous.

With a long lens on a small object (a narrow field of view, all points at about one depth), a
pair's essential matrix is nearly ambiguous: rotations several degrees (up to tens of degrees)
from the truth explain the matches to a fraction of a pixel. Averaging such edges gives poses
that bundle adjustment cannot pull out of the wrong valley. Growing the reconstruction one
camera at a time, as incremental structure from motion does, uses every camera's 2D-3D
correspondences instead: a seed pair, then repeatedly the camera that sees the most
triangulated points, placed by PnP and followed by a bundle adjustment of all cameras placed
so far.

:func:`register_incrementally` does that on the keypoint tracks of
:func:`~posernet.sfm.mapper.bundle_adjust_reconstruction`; that function compares its result
with the averaged start and keeps the one that explains more observations.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .bundle import BundleOptions, bundle_adjust
from .resection import solve_pnp
from .triangulation import reprojection_errors, triangulate_tracks

__all__ = ["Registration", "register_incrementally"]


@dataclass
class Registration:
    """Outcome of :func:`register_incrementally`: ``w2c (N, 4, 4)`` (registered cameras
    replaced, others as given), ``registered (N,)``, ``order`` the cameras in the order they
    were placed (the seed pair first), ``seed`` the seed pair."""

    w2c: np.ndarray
    registered: np.ndarray
    order: list[int]
    seed: tuple[int, int] | None


def _covisibility(track: np.ndarray, image: np.ndarray, num_tracks: int, n: int) -> np.ndarray:
    """``(N, N)`` number of tracks each pair of images shares (0 on the diagonal)."""
    A = np.zeros((num_tracks, n), np.float64)
    A[track, image] = 1.0
    C = A.T @ A
    np.fill_diagonal(C, 0)
    return C


def _seed_pose(xy: np.ndarray, track: np.ndarray, image: np.ndarray, a: int, b: int,
               K: np.ndarray, w2c: np.ndarray, thr: float, seed: int) -> np.ndarray:
    """Pose of ``b`` from the pair's own essential matrix (on the tracks both see) after
    ``a``'s pose, at unit baseline (averaged positions can nearly coincide); the averaged pose
    of ``b`` when the pair gives none."""
    ia, ib = np.flatnonzero(image == a), np.flatnonzero(image == b)
    common, pa, pb = np.intersect1d(track[ia], track[ib], return_indices=True)
    if common.size < 8:
        return w2c[b]
    x1 = (xy[ia[pa]] - K[a, :2, 2]) / np.diag(K[a])[:2]
    x2 = (xy[ib[pb]] - K[b, :2, 2]) / np.diag(K[b])[:2]
    f = 0.5 * (K[a, 0, 0] + K[b, 0, 0])
    cv2.setRNGSeed(int(seed) & 0x7FFFFFFF)
    try:
        E, mask = cv2.findEssentialMat(x1, x2, np.eye(3), method=cv2.USAC_MAGSAC, prob=0.9999,
                                       threshold=thr / f, maxIters=2000)
        if E is None or E.shape != (3, 3):
            return w2c[b]
        n, R, t, _ = cv2.recoverPose(E, x1, x2, np.eye(3), mask=mask)
    except cv2.error:
        return w2c[b]
    if n < 0.5 * common.size or not np.isfinite(R).all():
        return w2c[b]
    rel = np.eye(4)
    rel[:3, :3], rel[:3, 3] = R, t.ravel() / np.linalg.norm(t)
    return rel @ w2c[a]


def register_incrementally(xy: np.ndarray, track: np.ndarray, image: np.ndarray,
                           num_tracks: int, K: np.ndarray, w2c: np.ndarray,
                           members: np.ndarray, options: BundleOptions | None = None,
                           min_inliers: int = 15, min_inlier_ratio: float = 0.25,
                           seed: int = 0, growth: float = 1.25) -> Registration:
    """Place the ``members (N,)`` cameras one at a time (see the module docstring).

    Observations as in :func:`~posernet.sfm.triangulation.triangulate_tracks` (undistorted
    pixels ``xy (O, 2)`` of track ``track (O,)`` in image ``image (O,)``), ``K (N, 3, 3)``;
    ``w2c (N, 4, 4)`` the averaged poses: of the seed pair (the two members sharing the most
    tracks) the first keeps its averaged pose and the second is placed by the pair's own
    essential matrix; each PnP also tries the averaged pose as its start. A camera
    is registered when ``min_inliers`` and ``min_inlier_ratio`` of its correspondences agree
    within ``options.max_reproj_px``; the loop ends when no camera left sees ``min_inliers``
    points (a Python loop over cameras: meant for small components). The placed cameras are
    adjusted together when their number has grown by the factor ``growth`` since the last
    adjustment (every registration with ``growth=1``): a logarithmic number of adjustments,
    as the caller adjusts the result once more as a whole.
    """
    opt = options or BundleOptions()
    N = w2c.shape[0]
    members = np.asarray(members, bool)
    out = np.asarray(w2c, np.float64).copy()
    keep = members[image]
    xy, track, image = xy[keep], track[keep], image[keep]
    reg = np.zeros(N, bool)
    if members.sum() < 2 or not track.size:
        return Registration(out, reg, [], None)
    C = _covisibility(track, image, num_tracks, N)
    a, b = np.unravel_index(int(np.argmax(C)), C.shape)
    if C[a, b] < min_inliers:
        return Registration(out, reg, [], None)
    out[b] = _seed_pose(xy, track, image, int(a), int(b), K, out, opt.max_reproj_px, seed)
    reg[[a, b]] = True
    order = [int(a), int(b)]
    tried = reg.copy()
    thr = opt.max_reproj_px
    adjusted_at = 0  # cameras placed at the last adjustment
    while True:
        # triangulate what the placed cameras see, adjust them, drop what they still miss
        sel = reg[image]
        tri = triangulate_tracks(xy[sel], track[sel], image[sel], num_tracks, K, out,
                                 max_reproj_px=np.inf, min_angle_deg=opt.min_angle_deg)
        pts = tri.points
        ok = tri.valid[track] & sel
        if tri.valid.any():
            first = max(thr, opt.initial_reproj_factor * float(np.median(tri.max_error[tri.valid])))
            err = reprojection_errors(np.nan_to_num(pts), xy, track, image, K, out)
            ok &= err <= first
        if int(reg.sum()) >= growth * adjusted_at:
            adjusted_at = int(reg.sum())
            ba = bundle_adjust(out, np.nan_to_num(pts), K, xy[ok], image[ok], track[ok], opt)
            if ba.accepted:
                out = np.where(reg[:, None, None], ba.w2c, out)
                pts = np.where(tri.valid[:, None], ba.points, pts)
        err = reprojection_errors(np.nan_to_num(pts), xy, track, image, K, out)
        good = ok & (err <= thr)
        good_tr = np.bincount(track[good], minlength=num_tracks) >= 2
        # the next camera: the one that sees the most well-measured points
        cand = members & ~tried
        seen = good_tr[track] & cand[image]
        counts = np.bincount(image[seen], minlength=N)
        counts[~cand] = -1
        if not cand.any() or counts.max() < min_inliers:
            break
        cam = int(np.argmax(counts))
        tried[cam] = True
        o = np.flatnonzero(seen & (image == cam))
        T, inl = solve_pnp(pts[track[o]].astype(np.float64), xy[o].astype(np.float64), K[cam],
                      out[cam], thr, seed)
        if T is not None and inl >= min_inliers and inl >= min_inlier_ratio * o.size:
            out[cam] = T
            reg[cam] = True
            order.append(cam)
    return Registration(out, reg, order, (int(a), int(b)))

"""Cameras whose position the averaging could not fix, placed again from 3D points (PnP).

Translation averaging fixes a camera's position only through the directions of its edges: a
camera hanging on one edge (a leaf) or on a chain can slide along its directions, so motion
averaging may put it at any distance (on a narrow-lens ring of photos, 10^8 times too far).
:func:`anchored_cameras` finds the cameras the averaging does pin (the 2-core of the graph of
edges with a usable direction); :func:`resect_cameras` triangulates the tracks seen by those
cameras and gives each other camera the pose that its observations of these points say
(PnP inside RANSAC, or the translation alone with the averaged rotation held, whichever
agrees with more points), one camera at a time, best supported first, so that a
resected camera's points help the next one (as incremental SfM registers images).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .triangulation import triangulate_tracks

__all__ = ["Resection", "anchored_cameras", "resect_cameras", "solve_pnp"]


def anchored_cameras(edges: np.ndarray, weights: np.ndarray, members: np.ndarray,
                     strength: np.ndarray | None = None) -> np.ndarray:
    """Cameras whose averaged position is pinned by edge directions, ``(N,)`` bool.

    ``edges (E, 2)`` image index pairs, ``weights (E,)`` translation weights (0: the pair has
    no usable direction, e.g. rotation-only), ``members (N,)`` the cameras of one component.
    The 2-core of the usable edges among ``members`` (every camera keeps >= 2 such edges
    after peeling leaves repeatedly). When the core is empty (a tree of edges: every position
    slides), the two ends of the strongest edge (``strength (E,)``, e.g. inlier counts;
    default the first usable edge) are the anchors: their baseline sets the scale.
    """
    members = np.asarray(members, bool)
    n = members.size
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    use = (np.asarray(weights, np.float64).reshape(-1) > 0) & members[edges].all(1)
    e = edges[use]
    core = members.copy()
    while True:
        live = core[e].all(1)
        deg = np.bincount(e[live].ravel(), minlength=n)
        drop = core & (deg < 2)
        if not drop.any():
            break
        core &= ~drop
    if core.any() or not use.any():
        return core if core.any() else members.copy()
    s = (np.ones(int(use.sum())) if strength is None
         else np.asarray(strength, np.float64).reshape(-1)[use])
    a, b = e[int(np.argmax(s))]
    out = np.zeros(n, bool)
    out[[a, b]] = True
    return out


@dataclass
class Resection:
    """Outcome of :func:`resect_cameras`: ``w2c (N, 4, 4)`` (resected cameras replaced),
    ``resected`` / ``failed`` ``(N,)`` masks of the non-anchored cameras, and per camera
    ``inliers`` / ``points`` (2D-3D correspondences tried; 0 where not tried)."""

    w2c: np.ndarray
    resected: np.ndarray
    failed: np.ndarray
    inliers: np.ndarray
    points: np.ndarray


def _count(T: np.ndarray, X: np.ndarray, x: np.ndarray, K: np.ndarray, thr: float
           ) -> np.ndarray:
    """Inlier mask of ``X (M, 3)`` <-> pixels ``x (M, 2)`` under pose ``T (4, 4)``: in front of
    the camera and reprojected within ``thr`` px."""
    pc = X @ T[:3, :3].T + T[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        h = pc @ K.T
        err = np.linalg.norm(h[:, :2] / h[:, 2:3] - x, axis=1)
    return (pc[:, 2] > 0) & (err < thr)


def solve_pnp(X: np.ndarray, x: np.ndarray, K: np.ndarray, T0: np.ndarray, thr: float, seed: int
         ) -> tuple[np.ndarray | None, int]:
    """World-to-camera pose of one camera from ``X (M, 3)`` <-> undistorted pixels ``x (M, 2)``:
    the better (more inliers within ``thr`` px) of RANSAC PnP (OpenCV, SQPnP) and a
    Levenberg-Marquardt fit started from ``T0 (4, 4)``, each polished on its inliers with the
    threshold tightened in stages; ``(None, 0)`` when neither finds a pose."""
    cands = [(cv2.Rodrigues(T0[:3, :3])[0], T0[:3, 3].reshape(3, 1).copy())]
    for flag in (cv2.SOLVEPNP_SQPNP, cv2.SOLVEPNP_AP3P, cv2.SOLVEPNP_EPNP):
        cv2.setRNGSeed(seed)
        try:
            ok, rvec, tvec, inl = cv2.solvePnPRansac(
                X, x, K, None, iterationsCount=1000, reprojectionError=thr, confidence=0.999,
                flags=flag)
        except cv2.error:  # SQPnP asserts on near-degenerate (long-lens) configurations
            continue
        if ok and inl is not None and len(inl) >= 4:
            cands.append((rvec, tvec))
    best, best_n = None, 0
    for rvec, tvec in cands:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        for t in (10 * thr, 3 * thr, thr):
            inl = _count(T, X, x, K, t)
            if inl.sum() < 4:
                break
            rvec, tvec = cv2.solvePnPRefineLM(X[inl], x[inl], K, None, rvec.copy(),
                                              tvec.astype(np.float64).copy())
            T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        n = int(_count(T, X, x, K, thr).sum())
        if np.isfinite(T).all() and n > best_n:
            best, best_n = T, n
    return best, best_n


def resect_cameras(xy: np.ndarray, track: np.ndarray, image: np.ndarray, num_tracks: int,
                   K: np.ndarray, w2c: np.ndarray, anchored: np.ndarray, placed: np.ndarray,
                   *, max_reproj_px: float = 4.0, min_angle_deg: float = 1.0,
                   min_inliers: int = 15, min_inlier_ratio: float = 0.25,
                   reproj_factor: float = 3.0, seed: int = 0) -> Resection:
    """Re-place the ``placed & ~anchored`` cameras by PnP on points triangulated from the
    anchored (and already resected) cameras.

    Observations as in :func:`~posernet.sfm.triangulation.triangulate_tracks`: undistorted
    pixels ``xy (O, 2)`` of track ``track (O,)`` in image ``image (O,)``; ``K (N, 3, 3)``,
    ``w2c (N, 4, 4)`` the averaged poses. Averaged poses may be degrees off, so the points and
    the PnP inliers use ``max(max_reproj_px, reproj_factor * median track error)`` as their
    threshold. A camera is resected when at least ``min_inliers`` and ``min_inlier_ratio`` of
    its 2D-3D correspondences agree within it;
    otherwise it is ``failed`` and keeps its averaged pose (whose position nothing fixed: the
    caller should not trust it). Each step takes the camera that sees the most triangulated
    points (a Python loop over cameras, not observations).
    """
    N = w2c.shape[0]
    out = w2c.copy()
    fixed = np.asarray(anchored, bool) & np.asarray(placed, bool)
    todo = np.asarray(placed, bool) & ~fixed
    resected = np.zeros(N, bool)
    failed = np.zeros(N, bool)
    n_inl = np.zeros(N, np.int64)
    n_pts = np.zeros(N, np.int64)
    while todo.any():
        sel = fixed[image]
        tri = triangulate_tracks(xy[sel], track[sel], image[sel], num_tracks, K, out,
                                 max_reproj_px=np.inf, min_angle_deg=min_angle_deg)
        thr = max_reproj_px
        if tri.valid.any():
            thr = max(thr, reproj_factor * float(np.median(tri.max_error[tri.valid])))
        valid = tri.valid & (tri.max_error <= thr)
        seen = valid[track] & todo[image]
        counts = np.bincount(image[seen], minlength=N)
        counts[~todo] = -1
        cam = int(np.argmax(counts))
        o = np.flatnonzero(seen & (image == cam))
        n_pts[cam] = o.size
        T, inl = (None, 0)
        if o.size >= min_inliers:
            T, inl = solve_pnp(tri.points[track[o]].astype(np.float64), xy[o].astype(np.float64),
                          K[cam], out[cam], thr, seed)
        n_inl[cam] = inl
        todo[cam] = False
        if T is not None and inl >= min_inliers and inl >= min_inlier_ratio * o.size:
            out[cam] = T
            resected[cam] = fixed[cam] = True
        else:
            failed[cam] = True
    return Resection(w2c=out, resected=resected, failed=failed, inliers=n_inl, points=n_pts)

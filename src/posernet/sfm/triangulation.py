"""Multi-view linear triangulation (DLT) of many tracks at once, with the usual SfM filters.

Conventions: world-to-camera ``w2c (N, 4, 4)`` with ``x_cam = R X + t``; pixels
``x = K x_cam / z`` (OpenCV axes); observations are *undistorted* pixels (see
:func:`undistort_keypoints`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.sparse import csr_matrix

from .. import pinhole

__all__ = [
    "REASONS",
    "Triangulation",
    "project",
    "reprojection_errors",
    "segment_sum",
    "triangulate_tracks",
    "undistort_keypoints",
]

# Why a track was rejected, in the order the filters run (the first failing one is recorded).
REASONS: tuple[str, ...] = ("few_views", "degenerate", "cheirality", "angle", "reprojection")


def undistort_keypoints(uv: Sequence[np.ndarray], K: np.ndarray,
                        dist: Sequence[np.ndarray | None] | None) -> list[np.ndarray]:
    """Undistorted pixel coordinates, once up front: ``uv[i] (K_i, 2)`` -> same shapes.

    ``K (N, 3, 3)``; ``dist[i]``: OpenCV distortion coefficients of image i or None (also
    ``dist=None`` for all). ``cv2.undistortPoints(..., P=K)`` keeps the pixel units, so the rest
    of the pipeline sees an ideal pinhole camera with the same ``K``.
    """
    out = []
    for i, pts in enumerate(uv):
        p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        d = None if dist is None else dist[i]
        if d is None or p.shape[0] == 0 or not np.any(np.asarray(d)):
            out.append(p.copy())
            continue
        und = cv2.undistortPoints(p.reshape(-1, 1, 2), K[i], np.asarray(d, np.float64),
                                  P=K[i])
        out.append(und.reshape(-1, 2).astype(np.float64))
    return out


def segment_sum(values: np.ndarray, group: np.ndarray, n: int) -> np.ndarray:
    """Sum rows of ``values (O, ...)`` into ``n`` groups by ``group (O,)`` -> ``(n, ...)``."""
    flat = values.reshape(values.shape[0], int(np.prod(values.shape[1:])))
    S = csr_matrix((np.ones(group.size), (group, np.arange(group.size))), shape=(n, group.size))
    return np.asarray(S @ flat).reshape((n, *values.shape[1:]))


def _segment_max(values: np.ndarray, group: np.ndarray, n: int, fill: float) -> np.ndarray:
    out = np.full(n, fill, dtype=np.float64)
    np.maximum.at(out, group, values)
    return out


def project(points: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels and depths of matched rows: ``points (O, 3)``, ``K (O, 3, 3)``, ``w2c (O, 4, 4)``
    -> ``uv (O, 2)``, ``z (O,)`` (the pinhole of :func:`posernet.pinhole.project`)."""
    pc = np.einsum("oij,oj->oi", w2c[:, :3, :3], points) + w2c[:, :3, 3]
    return pinhole.project(pc, K), pc[:, 2]


def reprojection_errors(points: np.ndarray, xy: np.ndarray, obs_point: np.ndarray,
                        obs_image: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> np.ndarray:
    """Pixel reprojection error of every observation, ``(O,)`` (inf behind the camera).

    ``points (P, 3)``, observed undistorted pixels ``xy (O, 2)`` of point ``obs_point (O,)`` in
    image ``obs_image (O,)``, ``K (N, 3, 3)``, ``w2c (N, 4, 4)``.
    """
    uv, z = project(points[obs_point], K[obs_image], w2c[obs_image])
    err = np.linalg.norm(uv - xy, axis=1)
    return np.where((z > 0) & np.isfinite(err), err, np.inf)


@dataclass
class Triangulation:
    """Result of :func:`triangulate_tracks` for ``T`` tracks.

    ``points (T, 3)`` (NaN where the DLT had no solution), ``valid (T,)``, ``reason (T,)`` index
    into :data:`REASONS` of the first failing filter (-1 = valid), ``max_error (T,)`` largest
    reprojection error of the track (px), ``angle_deg (T,)`` its triangulation angle,
    ``num_views (T,)``; ``counts`` tracks rejected per reason (plus ``"valid"``).
    """

    points: np.ndarray
    valid: np.ndarray
    reason: np.ndarray
    max_error: np.ndarray
    angle_deg: np.ndarray
    num_views: np.ndarray
    counts: dict[str, int] = field(default_factory=dict)


def _max_ray_angle(rays: np.ndarray, track: np.ndarray, n: int, exact_max_len: int
                   ) -> np.ndarray:
    """Largest angle (rad) between two unit rays ``(O, 3)`` of the same track, ``(n,)``.

    Exact (all view pairs, vectorised) for tracks of at most ``exact_max_len`` views; longer
    tracks use farthest-ray sweeps (from the mean ray, then from the ray found): never above
    the true maximum, never below half of it, usually equal.
    """
    order = np.argsort(track, kind="stable")
    rays, track = rays[order], track[order]
    length = np.bincount(track, minlength=n)
    start = np.concatenate(([0], np.cumsum(length)[:-1]))
    out = np.zeros(n)
    pos = np.arange(track.size) - start[track]
    short = length[track] <= exact_max_len
    # Exact: enumerate pairs (o, o + k) for k = 1 .. L - 1 - pos within each short track.
    cnt = np.where(short, length[track] - 1 - pos, 0)
    if cnt.sum():
        first = np.repeat(np.arange(track.size), cnt)
        step = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt) + 1
        second = first + step
        cos = np.clip(np.einsum("ij,ij->i", rays[first], rays[second]), -1.0, 1.0)
        np.maximum.at(out, track[first], np.arccos(cos))
    long_tr = length > exact_max_len
    if long_tr.any():
        sel = long_tr[track]
        t, r = track[sel], rays[sel]
        # Sweep 1: the ray farthest from the mean; sweep 2: the ray farthest from that one.
        # The angle between the two is at least half the true maximum (triangle inequality
        # on the sphere) and usually equal to it.
        mean = segment_sum(r, t, n)[t]
        a = _argmin_by_group(np.einsum("ij,ij->i", r, mean), t, n)
        b = _argmin_by_group(np.einsum("ij,ij->i", r, r[a[t]]), t, n)
        ang = np.zeros(n)
        for anchor in (a, b):
            cos = np.clip(np.einsum("ij,ij->i", r, r[anchor[t]]), -1.0, 1.0)
            np.maximum.at(ang, t, np.arccos(cos))
        out[long_tr] = ang[long_tr]
    return out


def _argmin_by_group(values: np.ndarray, group: np.ndarray, n: int) -> np.ndarray:
    """Per group, the index (into ``values``) of its smallest value; ``(n,)``, -1 if empty."""
    order = np.lexsort((values, group))
    out = np.full(n, -1, np.int64)
    g = group[order]
    first = np.ones(g.size, bool)
    first[1:] = g[1:] != g[:-1]
    out[g[first]] = order[first]
    return out


def triangulate_tracks(xy: np.ndarray, obs_track: np.ndarray, obs_image: np.ndarray,
                       num_tracks: int, K: np.ndarray, w2c: np.ndarray, *,
                       max_reproj_px: float = 4.0, min_angle_deg: float = 1.0,
                       min_views: int = 2, exact_angle_max_len: int = 64) -> Triangulation:
    """Linear (DLT) triangulation of all tracks in one batch, then filters.

    Inputs: undistorted pixels ``xy (O, 2)`` of track ``obs_track (O,)`` in image
    ``obs_image (O,)``, ``K (N, 3, 3)``, ``w2c (N, 4, 4)``. Each observation gives two rows of
    the homogeneous system in normalised camera coordinates (``K^-1 x``, better conditioned
    than pixels) and the world is shifted/scaled to the cameras' centroid and spread first, so
    the result does not depend on the world's units. ``A^T A`` (4x4) is summed per track and
    its smallest eigenvector is the point.

    Filters (a track fails on the first): fewer than ``min_views`` views, degenerate solution
    (point at infinity or NaN), cheirality (depth <= 0 in any view), triangulation angle (the
    largest angle between two viewing rays) below ``min_angle_deg``, reprojection error (the
    track's largest, px) above ``max_reproj_px``.
    """
    xy = np.asarray(xy, np.float64)
    obs_track = np.asarray(obs_track, np.int64)
    obs_image = np.asarray(obs_image, np.int64)
    K = np.asarray(K, np.float64)
    w2c = np.asarray(w2c, np.float64)
    T = int(num_tracks)
    R, t = w2c[:, :3, :3], w2c[:, :3, 3]
    centres = -np.einsum("nji,nj->ni", R, t)
    used = np.unique(obs_image) if obs_image.size else np.zeros(0, np.int64)
    # Similarity normalisation of the world: X = s X' + c.
    c = centres[used].mean(0) if used.size else np.zeros(3)
    s = float(np.sqrt(((centres[used] - c) ** 2).sum(1).mean())) if used.size > 1 else 1.0
    s = s if np.isfinite(s) and s > 1e-12 else 1.0
    Pn = np.concatenate((R, ((np.einsum("nij,j->ni", R, c) + t) / s)[:, :, None]), axis=2)
    # Normalised image coordinates of every observation.
    Kinv = np.linalg.inv(K)
    h = np.einsum("oij,oj->oi", Kinv[obs_image], np.c_[xy, np.ones(len(xy))])
    xn = h[:, :2] / h[:, 2:3]
    P = Pn[obs_image]  # (O, 3, 4)
    r1 = xn[:, :1] * P[:, 2] - P[:, 0]
    r2 = xn[:, 1:2] * P[:, 2] - P[:, 1]
    # Unit rows: every view weighs the same whatever its depth.
    r1 /= np.linalg.norm(r1, axis=1, keepdims=True)
    r2 /= np.linalg.norm(r2, axis=1, keepdims=True)
    AtA = segment_sum(np.einsum("oi,oj->oij", r1, r1) + np.einsum("oi,oj->oij", r2, r2),
                      obs_track, T)
    num_views = np.bincount(obs_track, minlength=T)
    reason = np.full(T, -1, np.int8)
    reason[num_views < min_views] = REASONS.index("few_views")
    points = np.full((T, 3), np.nan)
    good = np.isfinite(AtA).all((1, 2))
    if T:
        _, vec = np.linalg.eigh(np.where(good[:, None, None], AtA, np.eye(4)))
        Xh = vec[:, :, 0]
        w = Xh[:, 3]
        scale = np.abs(Xh[:, :3]).max(1)
        finite_pt = good & (np.abs(w) > 1e-10 * np.maximum(scale, 1e-300))
        with np.errstate(divide="ignore", invalid="ignore"):
            Xn = Xh[:, :3] / w[:, None]
        points = np.where(finite_pt[:, None], s * Xn + c, np.nan)
        reason[(reason < 0) & ~finite_pt] = REASONS.index("degenerate")
    # Depths, angles, errors per observation (NaN points give NaN: rejected above).
    Xo = points[obs_track]
    pc = np.einsum("oij,oj->oi", R[obs_image], Xo) + t[obs_image]
    depth_ok = np.ones(T, bool)
    with np.errstate(invalid="ignore"):
        bad_depth = ~(pc[:, 2] > 0)
    depth_ok[obs_track[bad_depth]] = False
    reason[(reason < 0) & ~depth_ok] = REASONS.index("cheirality")
    rays = Xo - centres[obs_image]
    with np.errstate(invalid="ignore", divide="ignore"):
        rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    rays = np.nan_to_num(rays)
    angle = np.degrees(_max_ray_angle(rays, obs_track, T, exact_angle_max_len))
    reason[(reason < 0) & (angle < min_angle_deg)] = REASONS.index("angle")
    err = reprojection_errors(points, xy, obs_track, obs_image, K, w2c)
    max_err = _segment_max(err, obs_track, T, 0.0)
    reason[(reason < 0) & ~(max_err <= max_reproj_px)] = REASONS.index("reprojection")
    valid = reason < 0
    counts = {name: int((reason == k).sum()) for k, name in enumerate(REASONS)}
    counts["valid"] = int(valid.sum())
    return Triangulation(points=points, valid=valid, reason=reason, max_error=max_err,
                         angle_deg=angle, num_views=num_views, counts=counts)

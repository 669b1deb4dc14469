"""Global positioning: camera centres and 3D points together from their viewing rays.

Translation averaging places cameras from pairwise directions alone, and on a sparse view
graph (an object on a ring, a chain of far-apart views) that is not rigid: many centres can
slide onto one spot and still agree with every direction. Points tie the cameras together
where pairs cannot: each observation ``o`` says that point ``X_k`` lies along the world-frame
ray ``v_o`` from camera centre ``c_i``. With the rotations known (rotation averaging), solve

    min  sum_o w_o || X_k - c_i - d_o v_o ||^2   over centres, points and  d_o >= 1,

the ray-scale form of BATA and of GLOMAP's global positioning (Pan et al., ECCV 2024) with the
scale bound of LUD (Ozyesil and Singer, CVPR 2015). The bound ``d_o >= 1`` rules out the
collapse (every point at least one unit from each camera that sees it), and with ``d`` free
the problem is convex: it has one minimum, reached from any start. It is solved by exact
block minimisation: for fixed ``d`` the points drop out in closed form and the centres solve
one sparse ``N x N`` Laplacian system (three right-hand sides); for fixed positions each
``d_o`` is the projection ``max(1, v_o . (X_k - c_i))``. Robustness: observations whose ray
misses its point by more than ``max_angle_deg`` lose their weight and the problem is solved
again (``rounds`` times).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix, diags
from scipy.sparse.linalg import splu

__all__ = ["Positioning", "PositioningOptions", "global_positioning", "select_tracks"]


@dataclass
class PositioningOptions:
    """``max_observations``: observations used (the longest tracks first; each camera keeps
    at least ``min_per_camera`` where it has them); ``max_iters`` / ``tol``: block
    minimisation steps per round and the relative cost change that stops them; ``rounds``:
    solves, each after dropping the observations whose ray misses its point by more than
    ``max_angle_deg``; ``min_observations``: a camera keeping fewer explained observations is
    not positioned."""

    max_observations: int = 50000
    min_per_camera: int = 300
    max_iters: int = 100
    tol: float = 1e-6
    rounds: int = 2
    max_angle_deg: float = 3.0
    min_observations: int = 6

    def __post_init__(self) -> None:
        if self.max_observations < 2 or self.min_per_camera < 0 or self.max_iters < 1:
            raise ValueError("max_observations must be >= 2, min_per_camera >= 0, "
                             "max_iters >= 1")
        if not (self.tol > 0 and 0 < self.max_angle_deg < 90 and self.rounds >= 1):
            raise ValueError("tol must be > 0, max_angle_deg in (0, 90), rounds >= 1")


@dataclass
class Positioning:
    """Outcome of :func:`global_positioning`: ``w2c (N, 4, 4)`` with the given rotations and
    the solved centres (positioned cameras; others as given), ``points (T, 3)`` (NaN for
    tracks not used), ``positioned (N,)``, ``angle_deg (O,)`` the angle between each used
    observation's ray and its point (NaN where not used), ``iterations`` block steps in all."""

    w2c: np.ndarray
    points: np.ndarray
    positioned: np.ndarray
    angle_deg: np.ndarray
    iterations: int


def select_tracks(track: np.ndarray, image: np.ndarray, num_tracks: int, num_images: int,
                  max_observations: int, min_per_camera: int) -> np.ndarray:
    """``(T,)`` mask of the tracks to position with: the longest first until
    ``max_observations`` observations, then for each image below ``min_per_camera``
    observations its longest unused tracks."""
    length = np.bincount(track, minlength=num_tracks)
    order = np.argsort(-length, kind="stable")
    order = order[length[order] >= 2]
    take = np.zeros(num_tracks, bool)
    take[order[np.cumsum(length[order]) <= max_observations]] = True
    per_img = np.bincount(image[take[track]], minlength=num_images)
    need = per_img < min_per_camera
    if need.any():
        rank = np.empty(num_tracks, np.int64)
        rank[order] = np.arange(order.size)
        o = np.flatnonzero(~take[track] & need[image] & (length[track] >= 2))
        o = o[np.lexsort((rank[track[o]], image[o]))]
        img = image[o]
        k = np.arange(o.size) - np.searchsorted(img, img, side="left")
        take[track[o[k < (min_per_camera - per_img)[img]]]] = True
    return take


def _sum_rows(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """``(n, 3)`` sums of ``values (O, 3)`` grouped by ``index (O,)``."""
    return np.stack([np.bincount(index, values[:, k], n) for k in range(3)], 1)


def _solve(ray: np.ndarray, cam: np.ndarray, pt: np.ndarray, w: np.ndarray, n_cam: int,
           n_pt: int, opt: PositioningOptions) -> tuple[np.ndarray, np.ndarray, int]:
    """Centres ``(n_cam, 3)`` (camera 0 at the origin: the translation gauge) and points
    ``(n_pt, 3)`` minimising the weighted ray-scale cost; block steps used."""
    A = csr_matrix((w, (pt, cam)), shape=(n_pt, n_cam))
    Wp = np.maximum(np.asarray(A.sum(1)).ravel(), 1e-300)
    Dc = np.asarray(A.sum(0)).ravel()
    L = (diags(Dc) - A.T @ diags(1.0 / Wp) @ A).tocsc()[1:, 1:]
    # a tiny ridge: cameras without weight (all their observations dropped) stay put
    lu = splu((L + diags(np.full(n_cam - 1, 1e-12 * max(Dc.max(), 1.0)))).tocsc())
    d = np.ones(cam.size)
    c = np.zeros((n_cam, 3))
    X = np.zeros((n_pt, 3))
    prev = np.inf
    steps = 0
    for _ in range(opt.max_iters):
        steps += 1
        b = (w * d)[:, None] * ray
        B = _sum_rows(pt, b, n_pt)
        rhs = A.T @ (B / Wp[:, None]) - _sum_rows(cam, b, n_cam)
        c[1:] = lu.solve(rhs[1:])
        X = (A @ c + B) / Wp[:, None]
        diff = X[pt] - c[cam]
        d = np.maximum(1.0, np.einsum("oi,oi->o", diff, ray))
        cost = float((w * ((diff - d[:, None] * ray) ** 2).sum(1)).sum())
        if prev - cost <= opt.tol * max(cost, 1e-300):
            break
        prev = cost
    return c, X, steps


def global_positioning(xy: np.ndarray, track: np.ndarray, image: np.ndarray, num_tracks: int,
                       K: np.ndarray, w2c: np.ndarray, members: np.ndarray,
                       options: PositioningOptions | None = None) -> Positioning:
    """Centres of the ``members (N,)`` cameras and the points of their tracks from rays.

    Observations: undistorted pixels ``xy (O, 2)`` of track ``track (O,)`` in image
    ``image (O,)``; ``K (N, 3, 3)``; the rotations of ``w2c (N, 4, 4)`` are held fixed (their
    centres are not used). Positions are up to a similarity (the first member with
    observations sits at the origin). A member keeping fewer than ``min_observations``
    explained observations is not positioned.
    """
    opt = options or PositioningOptions()
    w2c = np.asarray(w2c, np.float64)
    N = w2c.shape[0]
    members = np.asarray(members, bool).reshape(N)
    out = w2c.copy()
    points = np.full((num_tracks, 3), np.nan)
    angle = np.full(track.size, np.nan)
    keep = members[image]
    keep &= np.bincount(track[keep], minlength=num_tracks)[track] >= 2
    use_tr = select_tracks(track[keep], image[keep], num_tracks, N, opt.max_observations,
                           opt.min_per_camera)
    sel = np.flatnonzero(keep & use_tr[track])
    cams = np.unique(image[sel])
    if cams.size < 2:
        return Positioning(out, points, np.zeros(N, bool), angle, 0)
    cam_id = np.full(N, -1, np.int64)
    cam_id[cams] = np.arange(cams.size)
    trs = np.unique(track[sel])
    pt_id = np.full(num_tracks, -1, np.int64)
    pt_id[trs] = np.arange(trs.size)
    # world-frame unit rays R_i^T K_i^-1 [x, y, 1]
    h = np.concatenate((xy[sel], np.ones((sel.size, 1))), 1)
    local = np.einsum("oij,oj->oi", np.linalg.inv(K[image[sel]]), h)
    ray = np.einsum("oji,oj->oi", w2c[image[sel], :3, :3], local)
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    cam, pt = cam_id[image[sel]], pt_id[track[sel]]
    w = np.ones(sel.size)
    iters = 0
    for _ in range(opt.rounds):
        c, X, it = _solve(ray, cam, pt, w, cams.size, trs.size, opt)
        iters += it
        v = X[pt] - c[cam]
        cos = np.einsum("oi,oi->o", v, ray) / np.maximum(np.linalg.norm(v, axis=1), 1e-300)
        ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        good = ang <= opt.max_angle_deg
        good &= np.bincount(pt[good], minlength=trs.size)[pt] >= 2
        if good.all() or np.unique(cam[good]).size < 2:
            break
        w = good.astype(np.float64)
    explained = np.bincount(cam[ang <= opt.max_angle_deg], minlength=cams.size)
    positioned = np.zeros(N, bool)
    positioned[cams[explained >= opt.min_observations]] = True
    out[cams, :3, 3] = -np.einsum("nij,nj->ni", w2c[cams, :3, :3], c)
    points[trs] = X
    angle[sel] = ang
    return Positioning(out, points, positioned, angle, iters)

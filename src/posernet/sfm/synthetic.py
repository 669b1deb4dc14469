"""Synthetic SfM scenes for tests and benchmarks: random points, cameras on a ring looking at
them, noisy pixel observations and the pairwise keypoint matches they imply."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..geometry import axis_angle_to_rotation_matrix
from ..pinhole import look_at
from ..pinhole import project as pinhole_project

__all__ = ["SyntheticScene", "make_scene", "make_sparse_scene", "perturb_poses"]


@dataclass
class SyntheticScene:
    """Ground truth and observations of one synthetic scene.

    ``K (N, 3, 3)``, ``w2c (N, 4, 4)``, ``points (P, 3)``; per image ``uv[i] (K_i, 2)`` noisy
    pixels of its keypoints and ``kp_point[i] (K_i,)`` the point each keypoint sees;
    ``pair_matches[(a, b)] (M, 2)`` true matches; flat observations ``obs_image, obs_point,
    obs_kp (O,)`` and ``xy (O, 2)`` (= the keypoints' pixels).
    """

    K: np.ndarray
    w2c: np.ndarray
    points: np.ndarray
    uv: list[np.ndarray]
    kp_point: list[np.ndarray]
    pair_matches: dict[tuple[int, int], np.ndarray]
    obs_image: np.ndarray
    obs_point: np.ndarray
    obs_kp: np.ndarray
    xy: np.ndarray
    image_size: tuple[int, int] = (640, 480)


def _project_one(points: np.ndarray, K: np.ndarray, w2c: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``(P, 2)`` and depths ``(P,)`` of ``points (P, 3)`` in one camera ``K (3, 3)``,
    ``w2c (4, 4)`` (two small matrix products, not a per-point batch of 4x4 matrices)."""
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    return pinhole_project(pc, K), pc[:, 2]


def _pair_matches(kp_point: list[np.ndarray], num_points: int, min_matches: int
                  ) -> dict[tuple[int, int], np.ndarray]:
    """True matches ``(M, 2)`` (keypoint in a, keypoint in b) of every pair ``a < b`` whose
    images share at least ``min_matches`` points, in ``(a, b)`` order; ``kp_point[i] (K_i,)``.
    Only pairs that share a point are visited (a sparse visibility product finds them), so a
    long sequence costs its overlapping pairs, not all ``N^2 / 2``."""
    from scipy.sparse import csr_matrix

    n = len(kp_point)
    rows = np.repeat(np.arange(n), [k.size for k in kp_point])
    cols = np.concatenate(kp_point) if n else np.zeros(0, np.int64)
    vis = csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, num_points))
    shared = (vis @ vis.T).tocoo()
    keep = (shared.row < shared.col) & (shared.data >= min_matches)
    pairs = sorted(zip(shared.row[keep].tolist(), shared.col[keep].tolist(), strict=True))
    matches: dict[tuple[int, int], np.ndarray] = {}
    inv = np.full(num_points, -1)
    for a, b in pairs:
        inv[kp_point[a]] = np.arange(kp_point[a].size)
        ka = inv[kp_point[b]]
        both = ka >= 0
        matches[(a, b)] = np.stack((ka[both], np.flatnonzero(both)), 1)
        inv[kp_point[a]] = -1
    return matches


def make_scene(num_cameras: int = 8, num_points: int = 400, noise_px: float = 0.5,
               visibility: float = 0.8, seed: int = 0, focal: float = 500.0,
               radius: float = 4.0) -> SyntheticScene:
    """Points in a unit-ish box, cameras on a ring of ``radius`` (random height and jitter)
    looking at the centre, each point seen by each camera with probability ``visibility``
    (when in front and inside the 640x480 image), Gaussian pixel noise ``noise_px``."""
    rng = np.random.default_rng(seed)
    W, H = 640, 480
    K = np.array([[focal, 0, W / 2], [0, focal, H / 2], [0, 0, 1]])
    Ks = np.repeat(K[None], num_cameras, 0)
    pts = rng.uniform(-1, 1, (num_points, 3)) * np.array([1.5, 1.0, 1.5])
    centres, targets = [], []
    for i in range(num_cameras):
        a = 2 * np.pi * i / num_cameras * 0.6 + rng.normal(0, 0.05)
        c = radius * np.array([np.sin(a), 0, -np.cos(a)]) + rng.normal(0, 0.3, 3)
        c[1] += rng.uniform(-1, 1)
        centres.append(c)
        targets.append(rng.normal(0, 0.2, 3))
    w2c = look_at(np.stack(centres), np.stack(targets), up=np.array([0.0, -1.0, 0.0]))
    uv, kp_point = [], []
    oi, op, ok, oxy = [], [], [], []
    for i in range(num_cameras):
        pix, z = _project_one(pts, Ks[i], w2c[i])
        inside = (z > 0.1) & (pix[:, 0] >= 0) & (pix[:, 0] < W) & (pix[:, 1] >= 0) & \
            (pix[:, 1] < H) & (rng.uniform(size=num_points) < visibility)
        ids = rng.permutation(np.flatnonzero(inside))
        obs = pix[ids] + rng.normal(0, noise_px, (ids.size, 2))
        uv.append(obs)
        kp_point.append(ids)
        oi.append(np.full(ids.size, i))
        op.append(ids)
        ok.append(np.arange(ids.size))
        oxy.append(obs)
    matches = _pair_matches(kp_point, num_points, 8)
    return SyntheticScene(K=Ks, w2c=w2c, points=pts, uv=uv, kp_point=kp_point,
                          pair_matches=matches, obs_image=np.concatenate(oi),
                          obs_point=np.concatenate(op), obs_kp=np.concatenate(ok),
                          xy=np.concatenate(oxy), image_size=(W, H))


def make_sparse_scene(kind: str = "ring", num_cameras: int = 16, num_points: int = 3000,
                      noise_px: float = 0.5, seed: int = 0, focal: float = 800.0,
                      min_matches: int = 15) -> SyntheticScene:
    """A sparse view graph: ``kind="ring"``, cameras on a ring around an object whose surface
    points face outwards and are seen only within 40 deg of their normal (each camera
    overlaps its two neighbours on each side); ``"chain"``, cameras side by side along a
    wall, each seeing a stretch of it (overlap with the next two). Pairs share a match list
    when they see at least ``min_matches`` points."""
    if kind not in ("ring", "chain"):
        raise ValueError(f"kind={kind!r}; choose 'ring' or 'chain'")
    rng = np.random.default_rng(seed)
    W, H = 640, 480
    K = np.array([[focal, 0, W / 2], [0, focal, H / 2], [0, 0, 1.0]])
    n = num_cameras
    up = np.array([0.0, -1.0, 0.0])
    if kind == "ring":
        normal = rng.normal(size=(num_points, 3)) * np.array([1.0, 0.3, 1.0])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        pts, cone = normal.copy(), 40.0
        a = 2 * np.pi * np.arange(n) / n
        w2c = look_at(4.0 * np.stack([np.sin(a), np.zeros(n), -np.cos(a)], 1), np.zeros((n, 3)),
                      up=up)
    else:
        pts = np.stack([rng.uniform(-1, 1.2 * n, num_points), rng.uniform(-1, 1, num_points),
                        rng.uniform(-0.5, 0.5, num_points)], 1)
        normal, cone = np.tile([0.0, 0.0, -1.0], (num_points, 1)), 80.0
        x = 1.2 * np.arange(n)
        w2c = look_at(np.stack([x, np.zeros(n), np.full(n, -4.0)], 1),
                      np.stack([x, np.zeros(n), np.zeros(n)], 1), up=up)
    Ks = np.repeat(K[None], n, 0)
    # chain: a camera sees the wall within (depth <= 4.5) * (W / 2) / focal of its x; only
    # the points in a slightly wider stretch are tested (a long chain then costs O(N), not
    # O(N^2)); the ring tests every point
    by_x = np.argsort(pts[:, 0], kind="stable")
    x_sorted = pts[by_x, 0]
    reach = 4.5 * W / (2 * focal) + 0.5
    uv, kp_point, oi, op, ok = [], [], [], [], []
    for i in range(n):
        c = -w2c[i, :3, :3].T @ w2c[i, :3, 3]
        cand = np.arange(num_points)
        if kind == "chain":
            lo, hi = np.searchsorted(x_sorted, (c[0] - reach, c[0] + reach))
            cand = np.sort(by_x[lo:hi])
        pix, z = _project_one(pts[cand], K, w2c[i])
        view = c - pts[cand]
        view /= np.linalg.norm(view, axis=1, keepdims=True)
        seen = (z > 0.1) & (pix[:, 0] >= 0) & (pix[:, 0] < W) & (pix[:, 1] >= 0) & \
            (pix[:, 1] < H) & ((view * normal[cand]).sum(1) > np.cos(np.radians(cone)))
        sel = rng.permutation(np.flatnonzero(seen))
        ids = cand[sel]
        uv.append(pix[sel] + rng.normal(0, noise_px, (ids.size, 2)))
        kp_point.append(ids)
        oi.append(np.full(ids.size, i))
        op.append(ids)
        ok.append(np.arange(ids.size))
    matches = _pair_matches(kp_point, num_points, min_matches)
    return SyntheticScene(K=Ks, w2c=w2c, points=pts, uv=uv, kp_point=kp_point,
                          pair_matches=matches, obs_image=np.concatenate(oi),
                          obs_point=np.concatenate(op), obs_kp=np.concatenate(ok),
                          xy=np.concatenate(uv), image_size=(W, H))


def perturb_poses(w2c: np.ndarray, rot_deg: float, trans_frac: float, seed: int = 0,
                  keep: tuple[int, ...] = ()) -> np.ndarray:
    """Rotate each camera by ``rot_deg`` about a random axis and move its centre by
    ``trans_frac`` of its distance to the origin (random direction); ``keep``: untouched."""
    rng = np.random.default_rng(seed)
    out = w2c.copy()
    for i in range(w2c.shape[0]):
        if i in keep:
            continue
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        dR = axis_angle_to_rotation_matrix(torch.from_numpy(np.radians(rot_deg) * axis)).numpy()
        R, t = w2c[i, :3, :3], w2c[i, :3, 3]
        c = -R.T @ t
        d = rng.normal(size=3)
        c = c + trans_frac * np.linalg.norm(c) * d / np.linalg.norm(d)
        R2 = dR @ R
        out[i, :3, :3], out[i, :3, 3] = R2, -R2 @ c
    return out

"""Batched DLT triangulation: accuracy, each filter, invariance, undistortion."""

from __future__ import annotations

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from posernet.pinhole import look_at
from posernet.sfm import REASONS, project, triangulate_tracks, undistort_keypoints
from posernet.sfm.synthetic import make_scene


def _tri(scene, xy=None, w2c=None, **kw):
    return triangulate_tracks(scene.xy if xy is None else xy, scene.obs_point, scene.obs_image,
                              scene.points.shape[0], scene.K,
                              scene.w2c if w2c is None else w2c, **kw)


def test_noise_free_is_exact_and_noisy_is_accurate() -> None:
    exact = make_scene(num_cameras=6, num_points=200, noise_px=0.0, seed=3)
    res = _tri(exact, max_reproj_px=1e-6)
    seen = np.bincount(exact.obs_point, minlength=200) >= 2
    assert res.valid.sum() == seen.sum()
    np.testing.assert_allclose(res.points[res.valid], exact.points[res.valid], atol=1e-9)
    noisy = make_scene(num_cameras=6, num_points=200, noise_px=0.5, seed=3)
    res = _tri(noisy)
    err = np.linalg.norm(res.points - noisy.points, axis=1)[res.valid]
    assert res.valid.mean() > 0.9
    assert np.median(err) < 0.01 and err.max() < 0.1  # scene ~3 units wide, cameras at ~4
    assert sum(res.counts.values()) == 200 and set(res.counts) == {*REASONS, "valid"}


def _two_cameras(baseline: float) -> tuple[np.ndarray, np.ndarray]:
    K = np.repeat(np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])[None], 2, 0)
    up = np.array([0.0, -1.0, 0.0])
    x = np.array([0.0, baseline])
    w2c = look_at(np.stack([x, [0.0, 0.0], [-5.0, -5.0]], 1),
                  np.stack([x, [0.0, 0.0], [0.0, 0.0]], 1), up=up)
    return K, w2c


def _observe(X: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> np.ndarray:
    return np.concatenate([project(X, K[[i] * len(X)], w2c[[i] * len(X)])[0]
                           for i in range(len(K))])


def test_each_filter() -> None:
    K, w2c = _two_cameras(2.0)
    X = np.array([[0.5, 0.2, 1.0],     # good
                  [0.3, -0.1, -8.0],   # behind both cameras (they look along +z from z=-5)
                  [1.0, 0.0, 2.0],     # good but one observation moved 30 px
                  [0.2, 0.1, 0.5]])    # seen by one camera only
    xy = _observe(X, K, w2c)  # rows: cam0 X0..X3, cam1 X0..X3
    image = np.repeat([0, 1], 4)
    track = np.tile(np.arange(4), 2)
    xy[6] += 30.0
    keep = ~((track == 3) & (image == 1))
    res = triangulate_tracks(xy[keep], track[keep], image[keep], 4, K, w2c, max_reproj_px=4.0,
                             min_angle_deg=1.0)
    names = [REASONS[r] if r >= 0 else "valid" for r in res.reason]
    assert names == ["valid", "cheirality", "reprojection", "few_views"]
    np.testing.assert_allclose(res.points[0], X[0], atol=1e-9)
    # Tiny baseline: a 1 mm baseline at 5 m gives ~0.01 deg, below the angle filter.
    K2, w2c2 = _two_cameras(1e-3)
    xy2 = _observe(X[:1], K2, w2c2)
    res2 = triangulate_tracks(xy2, np.zeros(2, int), np.array([0, 1]), 1, K2, w2c2,
                              min_angle_deg=1.0)
    assert REASONS[res2.reason[0]] == "angle" and not res2.valid[0]
    assert res2.angle_deg[0] < 0.1


def test_angle_is_max_over_view_pairs_short_and_long_tracks() -> None:
    scene = make_scene(num_cameras=8, num_points=50, noise_px=0.0, seed=4, visibility=1.0)
    exact = _tri(scene, exact_angle_max_len=100)
    sweep = _tri(scene, exact_angle_max_len=2)  # forces the two-sweep path for longer tracks
    # Brute force over pairs.
    C = -np.einsum("nji,nj->ni", scene.w2c[:, :3, :3], scene.w2c[:, :3, 3])
    for t in range(5):
        imgs = scene.obs_image[scene.obs_point == t]
        rays = scene.points[t] - C[imgs]
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        ang = np.degrees(np.arccos(np.clip(rays @ rays.T, -1, 1))).max()
        assert abs(exact.angle_deg[t] - ang) < 1e-6
        assert ang / 2 - 1e-6 <= sweep.angle_deg[t] <= ang + 1e-6


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), log_s=st.floats(-3.0, 3.0))
def test_triangulation_invariant_to_similarity(seed: int, log_s: float) -> None:
    """Moving the world by X' = s Q X + t (and the cameras with it) moves the points alike."""
    scene = make_scene(num_cameras=4, num_points=30, noise_px=0.5, seed=seed % 50)
    rng = np.random.default_rng(seed)
    s = float(np.exp(log_s))
    Q = Rotation.random(random_state=seed).as_matrix()
    t = rng.normal(0, 100, 3)
    w2c2 = scene.w2c.copy()
    w2c2[:, :3, :3] = scene.w2c[:, :3, :3] @ Q.T
    w2c2[:, :3, 3] = s * scene.w2c[:, :3, 3] - np.einsum("nij,j->ni", w2c2[:, :3, :3], t)
    a = _tri(scene)
    b = _tri(scene, w2c=w2c2)
    np.testing.assert_array_equal(a.valid, b.valid)
    moved = s * a.points[a.valid] @ Q.T + t
    np.testing.assert_allclose(b.points[b.valid], moved, atol=1e-7 * max(s, 1.0) * 100)
    np.testing.assert_allclose(b.max_error[b.valid], a.max_error[a.valid], atol=1e-6)


def test_undistort_keypoints_round_trip() -> None:
    K = np.array([[500.0, 0, 320], [0, 510, 240], [0, 0, 1]])
    dist = np.array([-0.2, 0.05, 0.001, -0.001, 0.0])
    rng = np.random.default_rng(0)
    pc = np.c_[rng.uniform(-0.4, 0.4, (50, 2)), np.ones(50)]
    ideal = (pc @ K.T)[:, :2]
    distorted, _ = cv2.projectPoints(pc, np.zeros(3), np.zeros(3), K, dist)
    und = undistort_keypoints([distorted.reshape(-1, 2), ideal], K[None].repeat(2, 0),
                              [dist, None])
    np.testing.assert_allclose(und[0], ideal, atol=1e-3)
    np.testing.assert_array_equal(und[1], ideal)
    assert undistort_keypoints([ideal], K[None], None)[0] is not ideal

"""Two-view verification: accepted general pairs, rotation-only and planar pairs, and the
rejections (static matches, random matches, too few, flat patches)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posernet.frontend.verify import (
    VerifyRules,
    epipolar_consistent,
    keypoint_contrast,
    verify_two_view,
)

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])


def _rot(axis: np.ndarray, deg: float) -> np.ndarray:
    import cv2

    a = np.asarray(axis, float)
    return cv2.Rodrigues(a / np.linalg.norm(a) * np.radians(deg))[0]


def _project(X: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    x = X @ R.T + t
    uv = x @ K.T
    return uv[:, :2] / uv[:, 2:]


def _scene(R: np.ndarray, t: np.ndarray, n: int = 300, seed: int = 0, planar: bool = False,
           noise: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Points in front of camera 1 (``[I|0]``) seen by camera 2 ``[R|t]``, with pixel noise."""
    rng = np.random.default_rng(seed)
    X = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n),
                         np.full(n, 5.0) if planar else rng.uniform(4, 8, n)])
    p1 = _project(X, np.eye(3), np.zeros(3)) + rng.normal(0, noise, (n, 2))
    p2 = _project(X, R, t) + rng.normal(0, noise, (n, 2))
    return p1, p2


def _angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def test_general_pair_is_accepted_with_its_pose():
    R, t = _rot([0.1, 1, 0], 8), np.array([-1.0, 0.1, 0.2])
    p1, p2 = _scene(R, t)
    tv = verify_two_view(p1, p2, K)
    assert tv.status == "ok" and tv.accepted and not tv.rotation_only
    assert _angle(tv.R, R) < 0.5
    assert np.degrees(np.arccos(tv.t @ (t / np.linalg.norm(t)))) < 3
    assert tv.info["inliers"] > 250 and tv.info["tri_angle"] > 1.0
    assert not tv.info["planar"]


def test_pure_rotation_is_a_rotation_only_edge():
    R = _rot([0.3, 1, 0.1], 6)
    p1, p2 = _scene(R, np.zeros(3))
    tv = verify_two_view(p1, p2, K)
    assert tv.status == "rotation" and tv.rotation_only and tv.accepted
    assert _angle(tv.R, R) < 0.3  # the pure-rotation fit, not the 5-point's guess
    assert tv.info["rotation_ratio"] >= 0.9


def test_tiny_baseline_is_rotation_only():
    R, t = _rot([0, 1, 0], 3), np.array([0.02, 0.0, 0.0])  # 2 cm at 4-8 m
    p1, p2 = _scene(R, t, noise=0.1)
    tv = verify_two_view(p1, p2, K)
    assert tv.rotation_only, tv.info


def test_planar_scene_is_reported_and_kept():
    R, t = _rot([0, 1, 0], 10), np.array([-1.0, 0.0, 0.1])
    p1, p2 = _scene(R, t, planar=True)
    tv = verify_two_view(p1, p2, K)
    assert tv.accepted and tv.info["planar"], tv.info
    assert tv.info["homography_ratio"] > 0.9


def test_a_plane_under_some_depth_is_found_with_few_draws():
    """The planar test draws only enough samples to find a plane explaining 90 % of the
    inliers (20): a plane holding 94 % of the points, the rest at other depths, is found under
    every seed; a general scene is never called planar."""
    R, t = _rot([0, 1, 0], 10), np.array([-1.0, 0.0, 0.1])
    p1, p2 = _scene(R, t, planar=True)
    q1, q2 = _scene(R, t, seed=1)
    off = np.arange(0, 300, 17)  # 18 of 300 points off the plane
    p1[off], p2[off] = q1[off], q2[off]
    for seed in range(25):
        tv = verify_two_view(p1, p2, K, seed=seed)
        assert tv.accepted and tv.info["planar"], (seed, tv.info)
        assert not verify_two_view(q1, q2, K, seed=seed).info["planar"]


def test_static_matches_are_rejected():
    """A uniform background matched to itself: the matches stay where they are."""
    rng = np.random.default_rng(1)
    p = rng.uniform([0, 0], [640, 480], (200, 2))
    tv = verify_two_view(p, p + rng.normal(0, 0.2, p.shape), K)
    assert tv.status == "static" and tv.pose is None
    assert tv.info["static_ratio"] > 0.9


def test_random_matches_are_rejected():
    rng = np.random.default_rng(2)
    p1 = rng.uniform([0, 0], [640, 480], (300, 2))
    p2 = rng.uniform([0, 0], [640, 480], (300, 2))
    tv = verify_two_view(p1, p2, K)
    assert not tv.accepted and tv.status in ("low_inlier_ratio", "too_few_inliers",
                                             "cheirality", "no_model"), tv.info


def test_too_few_matches_and_bad_shapes():
    R, t = _rot([0, 1, 0], 8), np.array([-1.0, 0, 0])
    p1, p2 = _scene(R, t, n=10)
    assert verify_two_view(p1, p2, K).status == "too_few_matches"
    assert verify_two_view(np.zeros((0, 2)), np.zeros((0, 2)), K).status == "too_few_matches"
    with pytest.raises(ValueError, match="shape"):
        verify_two_view(p1, p2[:5], K)
    with pytest.raises(ValueError, match="min_inliers"):
        VerifyRules(min_inliers=3)
    with pytest.raises(ValueError, match="min_front"):
        VerifyRules(min_front=1.5)


def test_outliers_are_outside_the_inlier_mask_and_epipolar_consistency():
    R, t = _rot([0.1, 1, 0], 8), np.array([-1.0, 0.1, 0.2])
    p1, p2 = _scene(R, t, n=300)
    rng = np.random.default_rng(3)
    bad = rng.choice(300, 60, replace=False)
    p2 = p2.copy()
    p2[bad] = rng.uniform([0, 0], [640, 480], (60, 2))
    tv = verify_two_view(p1, p2, K)
    assert tv.status == "ok"
    assert tv.inliers[bad].mean() < 0.1 and np.delete(tv.inliers, bad).mean() > 0.9
    ok = epipolar_consistent(p1, p2, tv.R, tv.t, K, threshold=2.0)
    assert ok[bad].mean() < 0.1 and np.delete(ok, bad).mean() > 0.95


def test_keypoint_contrast_separates_flat_from_textured():
    rng = np.random.default_rng(4)
    img = np.full((100, 200), 5, np.uint8)  # black-ish background with slight noise
    img = np.clip(img + rng.normal(0, 0.5, img.shape), 0, 255).astype(np.uint8)
    img[:, 100:] = rng.integers(0, 255, (100, 100), dtype=np.uint8)  # texture on the right
    uv = np.array([[20.0, 50], [50, 30], [150, 50], [180, 80]])
    c = keypoint_contrast(img, uv, 4)
    assert (c[:2] < 3).all() and (c[2:] > 30).all()
    assert keypoint_contrast(img, np.zeros((0, 2))).shape == (0,)


@settings(max_examples=15, deadline=None)
@given(yaw=st.floats(-25, 25), pitch=st.floats(-10, 10), tx=st.floats(-1.5, 1.5),
       ty=st.floats(-0.5, 0.5), seed=st.integers(0, 1000))
def test_verified_rotation_matches_the_truth(yaw, pitch, tx, ty, seed):
    R = _rot([0, 1, 0], yaw) @ _rot([1, 0, 0], pitch)
    t = np.array([tx, ty, 0.3])
    p1, p2 = _scene(R, t, n=250, seed=seed)
    # drop what left the second image (as a real matcher would)
    keep = (p2[:, 0] > 0) & (p2[:, 0] < 640) & (p2[:, 1] > 0) & (p2[:, 1] < 480)
    tv = verify_two_view(p1[keep], p2[keep], K)
    if keep.sum() >= 60:
        assert tv.accepted, tv.info
        assert _angle(tv.R, R) < 1.0

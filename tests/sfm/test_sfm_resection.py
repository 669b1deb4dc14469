"""Cameras the averaging did not pin: which they are, and their re-placement from 3D points."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from posernet.metrics import absolute_pose_errors_per_camera
from posernet.sfm import (
    BundleOptions,
    anchored_cameras,
    bundle_adjust,
    bundle_adjust_reconstruction,
    resect_cameras,
)
from posernet.sfm.synthetic import make_scene, perturb_poses
from posernet.sfm.triangulation import undistort_keypoints


def _errors(est: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    g = torch.zeros(est.shape[0], dtype=torch.long)
    rot, pos = absolute_pose_errors_per_camera(torch.from_numpy(est), torch.from_numpy(gt), g, 1)
    return float(rot.max()), float(pos.max())


def _slide_out(w2c: np.ndarray, cam: int, ref: int, factor: float) -> np.ndarray:
    """``w2c`` with camera ``cam`` moved along the line from ``ref`` to ``factor`` times its
    distance (what translation averaging does to a leaf: direction right, distance free)."""
    out = w2c.copy()
    c = [-w2c[i, :3, :3].T @ w2c[i, :3, 3] for i in (ref, cam)]
    new = c[0] + factor * (c[1] - c[0])
    out[cam, :3, 3] = -w2c[cam, :3, :3] @ new
    return out


def test_anchored_cameras_peel_leaves_and_chains() -> None:
    members = np.ones(6, bool)
    # triangle 0-1-2, camera 3 on one edge, 4-5 a chain hanging from 3
    edges = np.array([[0, 1], [1, 2], [0, 2], [2, 3], [3, 4], [4, 5]])
    w = np.ones(len(edges))
    assert anchored_cameras(edges, w, members).tolist() == [True] * 3 + [False] * 3
    # a rotation-only edge (weight 0) pins nothing: 0-2 gone, the triangle is a chain
    w0 = w.copy()
    w0[2] = 0
    strength = np.array([5, 50, 5, 5, 5, 5])
    got = anchored_cameras(edges, w0, members, strength)
    assert got.tolist() == [False, True, True, False, False, False]  # ends of the strongest
    # cameras outside the component are never anchored
    part = members.copy()
    part[0] = False
    assert not anchored_cameras(edges, w, part)[0]
    # a component with no usable edge: nothing to peel against, keep every member
    assert anchored_cameras(edges, np.zeros(len(edges)), members).all()


@pytest.fixture(scope="module")
def scene():
    return make_scene(num_cameras=8, num_points=400, noise_px=0.3, seed=3)


def _flat(scene):
    und = undistort_keypoints(scene.uv, scene.K, None)
    return np.concatenate(und)[np.cumsum([0] + [len(u) for u in und])[scene.obs_image]
                               + scene.obs_kp], scene.obs_point, scene.obs_image


def test_resection_replaces_a_far_leaf(scene) -> None:
    xy, track, image = _flat(scene)
    w0 = _slide_out(perturb_poses(scene.w2c, 0.3, 0.01, seed=1), 7, 6, 1e6)
    anchored = np.ones(8, bool)
    anchored[7] = False
    rs = resect_cameras(xy, track, image, scene.points.shape[0], scene.K, w0, anchored,
                        np.ones(8, bool))
    assert rs.resected.tolist() == [False] * 7 + [True] and not rs.failed.any()
    assert rs.inliers[7] >= 15 and rs.points[7] >= rs.inliers[7]
    rot, pos = _errors(rs.w2c, scene.w2c)
    assert rot < 1.0 and pos < 0.1, (rot, pos)
    np.testing.assert_array_equal(rs.w2c[:7], w0[:7])  # anchored cameras untouched


def test_resection_without_enough_points_fails_and_keeps_the_pose(scene) -> None:
    xy, track, image = _flat(scene)
    w0 = _slide_out(scene.w2c, 7, 6, 1e6)
    anchored = np.ones(8, bool)
    anchored[7] = False
    # camera 7 keeps 5 observations only (too few for PnP), or none at all
    for keep in ((image != 7) | (np.cumsum(image == 7) <= 5), image != 7):
        rs = resect_cameras(xy[keep], track[keep], image[keep], scene.points.shape[0],
                            scene.K, w0, anchored, np.ones(8, bool))
        assert rs.failed.tolist() == [False] * 7 + [True] and not rs.resected.any()
        assert rs.inliers[7] == 0
        np.testing.assert_array_equal(rs.w2c, w0)


def test_orchestrator_resects_unpinned_camera(scene) -> None:
    """From the averaged start (the incremental start never uses a far averaged position)."""
    avg = BundleOptions(start="averaged")
    w0 = _slide_out(perturb_poses(scene.w2c, 1.0, 0.03, seed=2), 7, 6, 1e8)
    anchored = np.ones(8, bool)
    anchored[7] = False
    placed = np.ones(8, bool)
    res = bundle_adjust_reconstruction(scene.uv, scene.pair_matches, scene.K, None, w0, placed,
                                       avg, anchored=anchored)
    assert res.stats["resection"]["resected"] == 1 and not res.weak.any()
    rot, pos = _errors(res.w2c, scene.w2c)
    assert rot < 0.1 and pos < 0.02, (rot, pos)
    assert "re-placed from 3D points (PnP) 1" in "\n".join(res.lines())
    # without the anchors the far camera spoils the triangulation (the old behaviour)
    bad = bundle_adjust_reconstruction(scene.uv, scene.pair_matches, scene.K, None, w0,
                                       placed, avg)
    assert _errors(bad.w2c, scene.w2c)[1] > 10 * pos
    # a camera PnP cannot place (its observations scrambled) is not trusted: weak and
    # undetermined (not to be reported as placed), the others still adjusted
    uv = [u.copy() for u in scene.uv]
    uv[7] = np.random.default_rng(0).uniform(0, 480, uv[7].shape)
    res = bundle_adjust_reconstruction(uv, scene.pair_matches, scene.K, None, w0, placed,
                                       avg, anchored=anchored)
    assert res.stats["resection"]["failed"] == 1
    assert res.undetermined.tolist() == [False] * 7 + [True] and res.weak[7]
    assert _errors(res.w2c[:7], scene.w2c[:7])[1] < 0.02


def test_lm_solver_holds_scale_and_handles_a_long_lens() -> None:
    """A 3000 px lens on a 640 px image (12 deg field of view): rotation and translation nearly
    trade off. LM with exact Schur steps converges; the free scale does not drift."""
    sc = make_scene(num_cameras=8, num_points=300, noise_px=0.3, seed=4, focal=3000.0,
                    radius=25.0)
    w0 = perturb_poses(sc.w2c, 3.0, 0.1, seed=5, keep=(0,))
    opt = BundleOptions(max_nfev=400)
    res = bundle_adjust(w0, sc.points + 0.05, sc.K, sc.xy, sc.obs_image, sc.obs_point, opt,
                        fixed_cameras=np.array([0]))
    assert res.accepted and res.converged, res.message
    assert res.median_error_after < 0.5
    rot, _ = _errors(res.w2c, sc.w2c)
    assert rot < 0.1, rot
    c_in = np.stack([-T[:3, :3].T @ T[:3, 3] for T in w0])
    c_out = np.stack([-T[:3, :3].T @ T[:3, 3] for T in res.w2c])
    spread = [np.linalg.norm(c[1:] - c[0], axis=1).mean() for c in (c_in, c_out)]
    assert spread[1] == pytest.approx(spread[0], rel=1e-6)

"""Global positioning: centres and points from rays on the sparse view graphs (a ring of an
object, a chain along a wall) on which pairwise directions alone are not rigid."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from posernet.metrics import absolute_pose_errors_per_camera
from posernet.sfm import BundleOptions, bundle_adjust_reconstruction
from posernet.sfm.positioning import PositioningOptions, global_positioning, select_tracks
from posernet.sfm.synthetic import make_sparse_scene, perturb_poses
from posernet.sfm.tracks import build_tracks


def _centres(w2c: np.ndarray) -> np.ndarray:
    return -np.einsum("nji,nj->ni", w2c[:, :3, :3], w2c[:, :3, 3])


def _position_error(est: np.ndarray, gt: np.ndarray) -> float:
    """Largest centre error after a similarity alignment, as a share of the extent."""
    g = torch.zeros(est.shape[0], dtype=torch.long)
    _, pos = absolute_pose_errors_per_camera(torch.from_numpy(est), torch.from_numpy(gt), g, 1)
    c = _centres(gt)
    return float(pos.max()) / float(np.linalg.norm(c.max(0) - c.min(0)))


def _observations(scene):
    tr = build_tracks(scene.pair_matches, [len(u) for u in scene.uv])
    offs = np.concatenate(([0], np.cumsum([len(u) for u in scene.uv])))
    return np.concatenate(scene.uv)[offs[tr.image] + tr.keypoint], tr


def _collapse(w2c: np.ndarray) -> np.ndarray:
    """Every centre on one spot, rotations kept: what translation averaging returns when the
    pair directions leave the graph free to fold."""
    out = w2c.copy()
    out[:, :3, 3] = -np.einsum("nij,j->ni", w2c[:, :3, :3], _centres(w2c).mean(0))
    return out


@pytest.mark.parametrize("kind", ["ring", "chain"])
def test_sparse_graphs_are_placed_from_rays(kind: str) -> None:
    sc = make_sparse_scene(kind)
    degree = np.bincount(np.array(list(sc.pair_matches)).ravel(), minlength=16)
    assert degree.max() <= 4  # neighbours only: directions alone are not rigid here
    xy, tr = _observations(sc)
    gp = global_positioning(xy, tr.track, tr.image, tr.num_tracks, sc.K, _collapse(sc.w2c),
                            np.ones(16, bool))
    assert gp.positioned.all()
    assert _position_error(gp.w2c, sc.w2c) < 0.01
    np.testing.assert_allclose(gp.w2c[:, :3, :3], sc.w2c[:, :3, :3])  # rotations held
    used = np.isfinite(gp.angle_deg)
    assert np.median(gp.angle_deg[used]) < 0.2


@pytest.mark.parametrize("kind", ["ring", "chain"])
def test_collapsed_start_is_undone_by_the_positioning_start(kind: str) -> None:
    """From collapsed centres and rotations a degree off, the adjustment from the averaged
    poses cannot recover; from the positioning start it does."""
    sc = make_sparse_scene(kind)
    w0 = _collapse(perturb_poses(sc.w2c, 1.0, 0.0, seed=2))
    placed = np.ones(16, bool)
    avg = bundle_adjust_reconstruction(sc.uv, sc.pair_matches, sc.K, None, w0, placed,
                                       BundleOptions(start="averaged"))
    pos = bundle_adjust_reconstruction(sc.uv, sc.pair_matches, sc.K, None, w0, placed,
                                       BundleOptions(start="positioning"))
    assert _position_error(avg.w2c, sc.w2c) > 0.2
    assert pos.refined.all() and _position_error(pos.w2c, sc.w2c) < 0.005


def test_outlier_observations_are_dropped() -> None:
    sc = make_sparse_scene("ring", seed=1)
    xy, tr = _observations(sc)
    bad = np.random.default_rng(0).random(xy.shape[0]) < 0.05
    xy = xy.copy()
    xy[bad] = np.random.default_rng(1).uniform(0, 480, (int(bad.sum()), 2))
    gp = global_positioning(xy, tr.track, tr.image, tr.num_tracks, sc.K, sc.w2c,
                            np.ones(16, bool))
    assert _position_error(gp.w2c, sc.w2c) < 0.01
    far = gp.angle_deg > PositioningOptions().max_angle_deg
    assert far[bad].mean() > 0.5 and far[~bad].mean() < 0.1


def test_members_and_empty_input() -> None:
    sc = make_sparse_scene("chain", num_cameras=6)
    xy, tr = _observations(sc)
    members = np.array([True, True, True, False, False, False])
    gp = global_positioning(xy, tr.track, tr.image, tr.num_tracks, sc.K, sc.w2c, members)
    assert gp.positioned.tolist() == members.tolist()
    np.testing.assert_array_equal(gp.w2c[~members], sc.w2c[~members])
    none = global_positioning(xy, tr.track, tr.image, tr.num_tracks, sc.K, sc.w2c,
                              np.zeros(6, bool))
    assert not none.positioned.any() and np.isnan(none.points).all()


def test_select_tracks_keeps_the_longest_and_covers_every_image() -> None:
    track = np.array([0, 0, 0, 1, 1, 2, 2, 3, 3])
    image = np.array([0, 1, 2, 0, 1, 1, 2, 3, 4])
    take = select_tracks(track, image, 4, 5, max_observations=3, min_per_camera=1)
    assert take.tolist() == [True, False, False, True]


def test_options_are_checked() -> None:
    with pytest.raises(ValueError, match="max_angle_deg"):
        PositioningOptions(max_angle_deg=0)
    with pytest.raises(ValueError, match="max_iters"):
        PositioningOptions(max_iters=0)

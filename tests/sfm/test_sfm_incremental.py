"""Incremental registration as the start of bundle adjustment, and the choice between starts."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from posernet.metrics import absolute_pose_errors_per_camera
from posernet.sfm import BundleOptions, bundle_adjust_reconstruction
from posernet.sfm.incremental import register_incrementally
from posernet.sfm.synthetic import make_scene, perturb_poses
from posernet.sfm.tracks import build_tracks
from posernet.sfm.triangulation import undistort_keypoints


def _errors(est: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    """Median rotation (deg) and position error after a similarity alignment."""
    g = torch.zeros(est.shape[0], dtype=torch.long)
    rot, pos = absolute_pose_errors_per_camera(torch.from_numpy(est), torch.from_numpy(gt), g, 1)
    return float(rot.median()), float(pos.median())


@pytest.fixture(scope="module")
def long_lens():
    """A 3000 px lens on 640x480 images (12 deg field of view) around a small object: two-view
    geometry is nearly ambiguous, as on the Middlebury dino."""
    return make_scene(num_cameras=8, num_points=400, noise_px=0.3, seed=4, focal=3000.0,
                      radius=25.0)


def _tracks(scene, members):
    und = undistort_keypoints(scene.uv, scene.K, None)
    sub = {k: m for k, m in scene.pair_matches.items() if members[k[0]] and members[k[1]]}
    tr = build_tracks(sub, [len(u) for u in und])
    offs = np.concatenate(([0], np.cumsum([len(u) for u in und])))
    return np.concatenate(und)[offs[tr.image] + tr.keypoint], tr


def test_registration_recovers_poses_from_a_poor_start(long_lens) -> None:
    sc = long_lens
    w0 = perturb_poses(sc.w2c, 8.0, 0.3, seed=1)  # averaging gone degrees wrong
    members = np.ones(8, bool)
    xy, tr = _tracks(sc, members)
    reg = register_incrementally(xy, tr.track, tr.image, tr.num_tracks, sc.K, w0, members)
    assert reg.registered.all() and sorted(reg.order) == list(range(8))
    assert reg.seed is not None and list(reg.seed) == reg.order[:2]
    rot, pos = _errors(reg.w2c, sc.w2c)
    start_rot, _ = _errors(w0, sc.w2c)
    assert rot < 0.2 and start_rot > 5, (rot, start_rot)
    assert pos < 0.01 * 25, pos


def _collapsed(w2c: np.ndarray, factor: float) -> np.ndarray:
    """Camera centres pulled to their mean by ``factor`` (rotations kept): what translation
    averaging gave one dino component, whose edge directions were mutually inconsistent."""
    out = w2c.copy()
    c = np.stack([-T[:3, :3].T @ T[:3, 3] for T in w2c])
    new = c.mean(0) + factor * (c - c.mean(0))
    out[:, :3, 3] = -np.einsum("nij,nj->ni", w2c[:, :3, :3], new)
    return out


def test_auto_start_keeps_the_start_that_explains_more(long_lens) -> None:
    sc = long_lens
    w0 = _collapsed(perturb_poses(sc.w2c, 5.0, 0.0, seed=1), 1e-3)
    placed = np.ones(8, bool)
    res = {s: bundle_adjust_reconstruction(sc.uv, sc.pair_matches, sc.K, None, w0, placed,
                                           BundleOptions(start=s))
           for s in ("averaged", "incremental", "auto")}
    start = res["auto"].stats["start"]
    assert start["kept"] == "incremental"
    obs = start["observations"]
    assert obs["incremental"] == res["auto"].obs_image.size > obs["averaged"]
    assert not res["averaged"].refined.any()  # nothing to triangulate from: BA fails
    assert res["auto"].refined.all()
    np.testing.assert_allclose(res["auto"].w2c, res["incremental"].w2c)
    rot_avg = _errors(res["averaged"].w2c, sc.w2c)[0]
    rot_auto, pos_auto = _errors(res["auto"].w2c, sc.w2c)
    assert rot_avg > 3 and rot_auto < 0.1, (rot_auto, rot_avg)
    assert pos_auto < 0.01 * 25, pos_auto
    assert any(line.startswith("start: incremental") for line in res["auto"].lines())


def test_a_good_averaged_start_is_kept() -> None:
    sc = make_scene(num_cameras=6, num_points=300, noise_px=0.3, seed=3)
    placed = np.ones(6, bool)
    # explaining most observations with every camera refined: incremental not even tried
    res = bundle_adjust_reconstruction(sc.uv, sc.pair_matches, sc.K, None, sc.w2c, placed,
                                       BundleOptions())
    assert res.stats["start"]["kept"] == "averaged"
    assert re.fullmatch(r"explains (9\d|100)% of the track observations, every camera refined",
                        res.stats["start"]["why"])
    assert "registration" not in res.stats["seconds"]
    assert _errors(res.w2c, sc.w2c)[0] < 0.05
    # noisier keypoints: a few observations over max_reproj_px, so explained_min=1 tries the
    # incremental start too; the one explaining more wins, a tie keeps the averaged one
    sc = make_scene(num_cameras=6, num_points=300, noise_px=2.0, seed=3)
    both = bundle_adjust_reconstruction(sc.uv, sc.pair_matches, sc.K, None, sc.w2c, placed,
                                        BundleOptions(explained_min=1.0))
    obs = both.stats["start"]["observations"]
    want = "averaged" if obs["averaged"] >= obs["incremental"] else "incremental"
    assert both.stats["start"]["kept"] == want
    assert obs[want] == both.obs_image.size


def test_a_camera_that_cannot_be_registered_is_not_placed(long_lens) -> None:
    sc = long_lens
    uv = [u.copy() for u in sc.uv]
    uv[5] = np.random.default_rng(0).uniform(0, 480, uv[5].shape)  # its matches are noise
    w0 = perturb_poses(sc.w2c, 8.0, 0.3, seed=1)
    res = bundle_adjust_reconstruction(uv, sc.pair_matches, sc.K, None, w0, np.ones(8, bool),
                                       BundleOptions(start="incremental"))
    assert res.stats["start"]["kept"] == "incremental"
    assert res.undetermined.tolist() == [False] * 5 + [True] + [False] * 2
    assert res.weak[5] and not res.refined[5] and res.placed.all()
    keep = np.arange(8) != 5
    assert _errors(res.w2c[keep], sc.w2c[keep])[0] < 0.2


def test_large_components_start_from_the_averaged_poses(long_lens) -> None:
    sc = long_lens
    res = bundle_adjust_reconstruction(sc.uv, sc.pair_matches, sc.K, None, sc.w2c,
                                       np.ones(8, bool),
                                       BundleOptions(incremental_max_cameras=7))
    assert res.stats["start"] == {"kept": "averaged", "why": "component over 7 cameras"}


def test_start_options_are_checked() -> None:
    with pytest.raises(ValueError, match="start='global'; choose one of"):
        BundleOptions(start="global")
    with pytest.raises(ValueError, match="incremental_max_cameras must be >= 2"):
        BundleOptions(incremental_max_cameras=1)
    with pytest.raises(ValueError, match="explained_min must be in"):
        BundleOptions(explained_min=1.5)

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


@pytest.mark.parametrize("growth", [1.0, 1.25, 2.0])
def test_registration_adjusts_as_the_model_grows(long_lens, monkeypatch, growth) -> None:
    """The placed cameras are adjusted when their number has grown by ``growth``: every
    registration at 1, fewer at larger factors, and the cameras are recovered either way."""
    import posernet.sfm.incremental as inc

    calls = []
    real = inc.bundle_adjust
    monkeypatch.setattr(inc, "bundle_adjust", lambda *a, **k: calls.append(1) or real(*a, **k))
    sc = long_lens
    w0 = perturb_poses(sc.w2c, 8.0, 0.3, seed=1)
    members = np.ones(8, bool)
    xy, tr = _tracks(sc, members)
    reg = register_incrementally(xy, tr.track, tr.image, tr.num_tracks, sc.K, w0, members,
                                 growth=growth)
    assert reg.registered.all()
    # 2 seed cameras, then 6 registrations: adjusted at 2,3,...,8 / 2,3,4,5,7 / 2,4,8
    assert len(calls) == {1.0: 7, 1.25: 5, 2.0: 3}[growth]
    rot, pos = _errors(reg.w2c, sc.w2c)
    assert rot < 0.5 and pos < 0.01 * 25, (rot, pos)


def _collapsed(w2c: np.ndarray, factor: float) -> np.ndarray:
    """Camera centres pulled to their mean by ``factor`` (rotations kept): what translation
    averaging gave one dino component, whose edge directions were mutually inconsistent."""
    out = w2c.copy()
    c = np.stack([-T[:3, :3].T @ T[:3, 3] for T in w2c])
    new = c.mean(0) + factor * (c - c.mean(0))
    out[:, :3, 3] = -np.einsum("nij,nj->ni", w2c[:, :3, :3], new)
    return out


def test_positioning_start_undoes_a_collapse(long_lens) -> None:
    """Averaged centres collapsed onto one spot and rotations 20 deg off: adjusting from them
    fails, while the positioning start (centres and points from rays) and the incremental one
    both recover the cameras; auto keeps the positioning start."""
    sc = long_lens
    w0 = _collapsed(perturb_poses(sc.w2c, 20.0, 0.0, seed=1), 1e-3)
    placed = np.ones(8, bool)
    res = {s: bundle_adjust_reconstruction(sc.uv, sc.pair_matches, sc.K, None, w0, placed,
                                           BundleOptions(start=s))
           for s in ("averaged", "positioning", "incremental", "auto")}
    assert not res["averaged"].refined.any()  # nothing to triangulate from: BA fails
    rot_avg = _errors(res["averaged"].w2c, sc.w2c)[0]
    assert rot_avg > 3, rot_avg
    for s in ("positioning", "incremental", "auto"):
        assert res[s].refined.all(), s
        rot, pos = _errors(res[s].w2c, sc.w2c)
        assert rot < 0.1 and pos < 0.01 * 25, (s, rot, pos)
    assert res["auto"].stats["start"]["kept"] == "positioning"
    assert res["positioning"].stats["start"] == {"kept": "positioning",
                                                 "why": "start=positioning"}
    assert "positioning" in res["auto"].stats["seconds"]
    np.testing.assert_allclose(res["auto"].w2c, res["positioning"].w2c)


def test_adjustment_climbs_out_of_a_mild_collapse(long_lens) -> None:
    """Centres collapsed onto one spot with rotations 5 deg off: the adjustment itself finds
    the cameras (a damping that falls too low in the long lens's valley failed here)."""
    sc = long_lens
    w0 = _collapsed(perturb_poses(sc.w2c, 5.0, 0.0, seed=1), 1e-3)
    res = bundle_adjust_reconstruction(sc.uv, sc.pair_matches, sc.K, None, w0,
                                       np.ones(8, bool), BundleOptions(start="averaged"))
    assert res.refined.all()
    rot, pos = _errors(res.w2c, sc.w2c)
    assert rot < 0.1 and pos < 0.01 * 25, (rot, pos)


def test_auto_start_keeps_the_start_that_explains_more() -> None:
    """Noisy keypoints leave a few observations over max_reproj_px, so explained_min=1 tries
    the incremental start too; the one explaining more wins, a tie keeps the first."""
    sc = make_scene(num_cameras=6, num_points=300, noise_px=2.0, seed=3)
    res = bundle_adjust_reconstruction(sc.uv, sc.pair_matches, sc.K, None, sc.w2c,
                                       np.ones(6, bool), BundleOptions(explained_min=1.0))
    start = res.stats["start"]
    obs = start["observations"]
    assert "explains" in start["why"] and set(obs) >= {"averaged", "positioning"}
    assert set(obs) <= {"averaged", "positioning", "incremental"}
    assert start["kept"] in obs and obs[start["kept"]] == res.obs_image.size
    assert obs[start["kept"]] == max(obs.values())  # every camera refined in each start
    assert any(line.startswith(f"start: {start['kept']}") for line in res.lines())


def test_a_good_first_start_is_kept() -> None:
    sc = make_scene(num_cameras=6, num_points=300, noise_px=0.3, seed=3)
    placed = np.ones(6, bool)
    # explaining most observations with every camera refined: incremental not even tried
    res = bundle_adjust_reconstruction(sc.uv, sc.pair_matches, sc.K, None, sc.w2c, placed,
                                       BundleOptions())
    assert res.stats["start"]["kept"] == "averaged"
    assert re.fullmatch(r"every camera refined, explaining (9\d|100)% of the track "
                        r"observations, none collapsed", res.stats["start"]["why"])
    assert "registration" not in res.stats["seconds"]
    assert "positioning" not in res.stats["seconds"]
    assert _errors(res.w2c, sc.w2c)[0] < 0.05
    # the averaged start, asked for, is the same adjustment
    avg = bundle_adjust_reconstruction(sc.uv, sc.pair_matches, sc.K, None, sc.w2c, placed,
                                       BundleOptions(start="averaged"))
    assert "start" not in avg.stats
    np.testing.assert_allclose(avg.w2c, res.w2c)


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


def test_large_components_are_not_registered_incrementally(long_lens) -> None:
    sc = long_lens
    w0 = _collapsed(perturb_poses(sc.w2c, 20.0, 0.0, seed=1), 1e-3)
    res = bundle_adjust_reconstruction(sc.uv, sc.pair_matches, sc.K, None, w0,
                                       np.ones(8, bool),
                                       BundleOptions(incremental_max_cameras=7))
    assert res.stats["start"]["kept"] == "positioning"
    assert set(res.stats["start"]["observations"]) == {"averaged", "positioning"}
    assert res.stats["start"]["why"].endswith("component over 7 cameras: not registered "
                                              "incrementally")
    avg = bundle_adjust_reconstruction(sc.uv, sc.pair_matches, sc.K, None, sc.w2c,
                                       np.ones(8, bool),
                                       BundleOptions(start="incremental",
                                                     incremental_max_cameras=7))
    assert avg.stats["start"]["kept"] == "averaged"
    assert "registration" not in avg.stats["seconds"]


def test_start_options_are_checked() -> None:
    with pytest.raises(ValueError, match="start: 'global' is not one of auto, averaged"):
        BundleOptions(start="global")
    with pytest.raises(ValueError, match="incremental_max_cameras: 1 is not an integer >= 2"):
        BundleOptions(incremental_max_cameras=1)
    with pytest.raises(ValueError, match=r"explained_min: 1.5 is not a number in \[0, 1\]"):
        BundleOptions(explained_min=1.5)


def test_pairs_whose_matches_the_adjustment_dropped_are_counted() -> None:
    """A correct adjustment keeps most of every verified pair's matches as common 3D points;
    one that dropped a pair's shared observations (a loop left open at that pair) leaves it
    under ``pair_explained_min``, which puts the adjustment in doubt."""
    from dataclasses import replace

    from posernet.sfm.mapper import _doubts, _open_pairs, baseline_pairs

    sc = make_scene(num_cameras=6, num_points=300, noise_px=0.3, seed=3)
    opt = BundleOptions(pair_explained_matches=50)
    res = bundle_adjust_reconstruction(sc.uv, sc.pair_matches, sc.K, None, sc.w2c,
                                       np.ones(6, bool), opt)
    n_kp = [len(u) for u in sc.uv]
    assert _open_pairs(res, sc.pair_matches, n_kp, opt) == 0
    pairs = baseline_pairs(sc.pair_matches)
    assert _doubts(res, np.ones(6, bool), opt, pairs, 0) == []
    # drop camera 1's observations of the points it shares with camera 0
    m = sc.pair_matches[(0, 1)]
    assert len(m) >= 50
    offs = np.concatenate(([0], np.cumsum(n_kp)))
    point = np.full(offs[-1], -1)
    point[offs[res.obs_image] + res.obs_keypoint] = res.obs_point
    shared = set(point[offs[0] + m[:, 0]].tolist()) - {-1}
    gone = (res.obs_image == 1) & np.isin(res.obs_point, list(shared))
    cut = replace(res, obs_image=res.obs_image[~gone], obs_keypoint=res.obs_keypoint[~gone],
                  obs_point=res.obs_point[~gone])
    n_open = _open_pairs(cut, sc.pair_matches, n_kp, opt)
    assert n_open >= 1  # (0, 1), and camera 1's pairs whose points were mostly those
    assert _open_pairs(cut, sc.pair_matches, n_kp, replace(opt, pair_explained_min=0.0)) == 0
    assert _open_pairs(cut, sc.pair_matches, n_kp,
                       replace(opt, pair_explained_matches=10**6)) == 0
    doubts = _doubts(cut, np.ones(6, bool), opt, pairs, 1)
    assert "1 verified pair(s) keep under 30% of their matches" in doubts


def test_a_start_far_off_puts_the_adjustment_in_doubt() -> None:
    """An adjustment whose start was more than ``start_error_px`` off is in doubt even when it
    converged well: from that far, it may have settled in a wrong minimum."""
    from dataclasses import replace

    from posernet.sfm.mapper import _doubts, baseline_pairs

    sc = make_scene(num_cameras=6, num_points=300, noise_px=0.3, seed=3)
    res = bundle_adjust_reconstruction(sc.uv, sc.pair_matches, sc.K, None, sc.w2c,
                                       np.ones(6, bool), BundleOptions())
    pairs = baseline_pairs(sc.pair_matches)
    assert res.stats["median_error_before"] < 1.0
    assert _doubts(res, np.ones(6, bool), BundleOptions(), pairs) == []
    far = replace(res, stats={**res.stats, "median_error_before": 242.0})
    assert _doubts(far, np.ones(6, bool), BundleOptions(), pairs) == ["started 242 px off"]
    assert _doubts(far, np.ones(6, bool), BundleOptions(start_error_px=300.0), pairs) == []

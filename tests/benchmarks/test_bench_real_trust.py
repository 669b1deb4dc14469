"""The trust counts of ``benchmarks/bench_real.py`` (cameras placed right / wrong after a robust
similarity alignment) on planted cases, and unsolved cameras of ``poses.json`` counted as not
placed."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(BENCH))  # benchmarks/_common.py
    try:
        spec = importlib.util.spec_from_file_location("_bench_real_trust_under_test",
                                                      BENCH / "bench_real.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.path.remove(str(BENCH))


def _rot(axis, deg: float) -> np.ndarray:
    rvec = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis) * np.deg2rad(deg)
    return cv2.Rodrigues(rvec)[0]


def _ring(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """``n`` camera-to-world poses on a noisy ring of radius 3 looking inwards."""
    rng = np.random.default_rng(seed)
    out = {}
    for i in range(n):
        a = 2 * np.pi * i / n
        T = np.eye(4)
        T[:3, :3] = _rot([0, 1, 0], np.degrees(a) + rng.normal(0, 5)) @ _rot(
            rng.normal(size=3), rng.uniform(1, 10))
        T[:3, 3] = [3 * np.sin(a), rng.normal(0, 0.3), 3 * np.cos(a)]
        out[f"img{i:02d}.jpg"] = T
    return out


def _to_w2c(c2w: dict[str, np.ndarray], s: float = 1.0, R=None,
            t=None) -> dict[str, np.ndarray]:
    """World-to-camera poses of the cameras ``c2w`` in a world moved by ``x -> s R x + t``."""
    R = np.eye(3) if R is None else R
    t = np.zeros(3) if t is None else t
    out = {}
    for k, T in c2w.items():
        M = np.eye(4)
        M[:3, :3] = R @ T[:3, :3]
        M[:3, 3] = s * R @ T[:3, 3] + t
        out[k] = np.linalg.inv(M)
    return out


def _turned(T: np.ndarray, deg: float, axis=(0.3, 1, 0.2)) -> np.ndarray:
    """Camera-to-world ``T`` turned by ``deg`` about its own centre."""
    out = T.copy()
    out[:3, :3] = _rot(axis, deg) @ T[:3, :3]
    return out


def _moved(T: np.ndarray, dist: float, direction=(1, 0.5, -0.2)) -> np.ndarray:
    out = T.copy()
    out[:3, 3] += dist * np.asarray(direction) / np.linalg.norm(direction)
    return out


@pytest.mark.parametrize("similarity", [False, True])
def test_planted_seven_right_three_wrong(bench, similarity):
    gt = _ring(10)
    keys = sorted(gt)
    extent = bench.scene_extent(gt)
    assert 5.5 < extent < 6.5  # the ring's diameter
    est = dict(gt)
    est[keys[2]] = _turned(gt[keys[2]], 20.0)  # rotation off by 20 deg, centre exact
    est[keys[5]] = _moved(gt[keys[5]], 0.3 * extent)  # centre off by 30 % of the extent
    est[keys[8]] = _moved(_turned(gt[keys[8]], 20.0, (1, 0, 0)), 0.3 * extent, (0, 1, 0))
    # small noise on the right ones: well inside 5 deg and 5 % of the extent
    est[keys[0]] = _moved(_turned(gt[keys[0]], 1.0), 0.01 * extent)
    args = (4.2, _rot([1, 2, 3], 71.0), np.array([5.0, -2.0, 0.5])) if similarity else ()
    r = bench.trust_counts(keys, gt, _to_w2c(est, *args), dict.fromkeys(keys, 0))
    assert (r["right"], r["wrong"], r["not_placed"]) == (7, 3, 0)
    wrong = sorted(k for k, c in r["cameras"].items() if c["status"] == "wrong")
    assert wrong == [keys[2], keys[5], keys[8]]
    # errors in ground-truth units and degrees whatever the estimate's scale (the one noisy
    # right camera moves the refit alignment a little)
    cams = r["cameras"]
    assert abs(cams[keys[2]]["rot_deg"] - 20.0) < 0.5 and cams[keys[2]]["pos"] < 0.01 * extent
    assert abs(cams[keys[5]]["pos"] - 0.3 * extent) < 0.01 * extent
    assert cams[keys[5]]["rot_deg"] < 0.5
    assert cams[keys[0]]["pos"] == pytest.approx(0.01 * extent, rel=0.3)
    assert all(cams[k]["pos"] < 0.005 * extent and cams[k]["rot_deg"] < 0.5
               for k in keys[1:2] + keys[9:])


def test_gross_outliers_do_not_drag_the_alignment(bench):
    gt = _ring(10, seed=3)
    keys = sorted(gt)
    est = dict(gt)
    for k in keys[:4]:  # four cameras thrown far away and turned around
        est[k] = _moved(_turned(gt[k], 150.0), 40.0)
    r = bench.trust_counts(keys, gt, _to_w2c(est, 0.1, _rot([0, 0, 1], 200), np.ones(3)),
                           dict.fromkeys(keys, 0))
    assert (r["right"], r["wrong"]) == (6, 4)
    assert all(r["cameras"][k]["pos"] < 1e-6 for k in keys[4:])


def test_many_cameras_sample_the_hypotheses(bench, monkeypatch):
    # over 63 cameras the 2-camera samples are drawn (TRUST_MAX_PAIRS), and with more than
    # TRUST_LIST_TRIPLES triples they are drawn without listing them (1024 cameras: 1.8e8)
    monkeypatch.setattr(bench, "TRUST_MAX_PAIRS", 200)
    monkeypatch.setattr(bench, "TRUST_LIST_TRIPLES", 1000)
    gt = {f"img{i:03d}.jpg": T for i, T in enumerate(_ring(80, seed=2).values())}
    keys = sorted(gt)
    est = dict(gt)
    for k in keys[:10]:
        est[k] = _moved(_turned(gt[k], 30.0), 2.0)
    r = bench.trust_counts(keys, gt, _to_w2c(est, 2.0, _rot([0, 1, 1], 40), np.ones(3)),
                           dict.fromkeys(keys, 0))
    assert (r["right"], r["wrong"]) == (70, 10)
    assert all(r["cameras"][k]["pos"] < 1e-6 for k in keys[10:])


def test_thresholds_are_five_degrees_and_five_percent(bench):
    gt = _ring(12, seed=1)
    keys = sorted(gt)
    extent = bench.scene_extent(gt)
    est = dict(gt)
    est[keys[0]] = _turned(gt[keys[0]], 3.5, (1, 0, 0))
    est[keys[3]] = _turned(gt[keys[3]], 7.0, (0, 1, 0))
    est[keys[6]] = _moved(gt[keys[6]], 0.035 * extent, (1, 0, 0))
    est[keys[9]] = _moved(gt[keys[9]], 0.07 * extent, (0, 0, 1))
    r = bench.trust_counts(keys, gt, _to_w2c(est), dict.fromkeys(keys, 0))
    status = {k: c["status"] for k, c in r["cameras"].items()}
    assert [status[k] for k in keys[0:12:3]] == ["right", "wrong", "right", "wrong"]
    assert (r["right"], r["wrong"]) == (10, 2)


def test_no_tilting_to_take_in_a_camera_beyond_the_tolerance(bench):
    # on four cameras, the alignment of a sample holding the camera turned by 7 deg can tilt
    # by ~3 deg, leaving all four within 5 deg (max consensus alone would call it right):
    # judged under the least-squares fit of the consensus it is wrong
    gt = _ring(4, seed=0)
    keys = sorted(gt)
    est = dict(gt)
    est[keys[0]] = _turned(gt[keys[0]], 7.0, (1, 0, 0))
    r = bench.trust_counts(keys, gt, _to_w2c(est, 3.0, _rot([1, 1, 0], 50), np.ones(3)),
                           dict.fromkeys(keys, 0))
    assert (r["right"], r["wrong"]) == (3, 1)
    assert r["cameras"][keys[0]]["status"] == "wrong"
    assert r["cameras"][keys[0]]["rot_deg"] > 6.5


def test_components_aligned_apart_unsolved_and_lone_cameras_not_placed(bench):
    gt = _ring(9, seed=2)
    keys = sorted(gt)
    # component 0: five cameras in one world; component 1: two cameras in another world
    # (two cameras alone are enough: their orientations fix the rotation); one camera alone
    # in component 2; one camera not placed at all
    est = _to_w2c({k: gt[k] for k in keys[:5]}, 2.0, _rot([0, 1, 0], 40), np.ones(3))
    est.update(_to_w2c({k: gt[k] for k in keys[5:7]}, 0.2, _rot([1, 0, 0], -80), -np.ones(3)))
    est[keys[7]] = np.eye(4)
    comp = {k: 0 for k in keys[:5]} | {k: 1 for k in keys[5:7]} | {keys[7]: 2}
    r = bench.trust_counts(keys, gt, est, comp)
    assert (r["right"], r["wrong"], r["not_placed"]) == (7, 0, 2)
    assert r["cameras"][keys[7]] == {"status": "not placed", "rot_deg": None, "pos": None}
    assert r["cameras"][keys[8]]["status"] == "not placed"
    # the same two-camera component with a relative rotation 30 deg off: both cannot be right
    bad = dict(est)
    bad.update(_to_w2c({keys[5]: gt[keys[5]], keys[6]: _turned(gt[keys[6]], 30.0)}))
    r = bench.trust_counts(keys, gt, bad, comp)
    assert r["right"] + r["wrong"] == 7 and r["wrong"] >= 1
    nothing = bench.trust_counts(keys, gt, {}, {})
    assert (nothing["right"], nothing["wrong"], nothing["not_placed"]) == (0, 0, 9)


def test_unsolved_cameras_of_poses_json_are_not_placed(bench, tmp_path):
    gt = _ring(5, seed=4)
    keys = sorted(gt)
    cams = {k: {"solved": True, "component": 0, "camera_to_world": T.tolist()}
            for k, T in gt.items()}
    # unsolved cameras keep whatever pose fields they carry: never placed
    cams[keys[1]] = {"solved": False, "component": None, "camera_to_world": None}
    cams[keys[3]] = {"solved": False, "component": 0,
                     "camera_to_world": _moved(gt[keys[3]], 100.0).tolist()}
    (tmp_path / "poses.json").write_text(json.dumps({"cameras": cams}), encoding="utf-8")
    w2c, comp, _ = bench.read_posernet(tmp_path)
    assert sorted(w2c) == [keys[0], keys[2], keys[4]]
    r = bench.trust_counts(keys, gt, w2c, comp)
    assert (r["right"], r["wrong"], r["not_placed"]) == (3, 0, 2)
    assert r["cameras"][keys[3]]["status"] == "not placed"


def test_trust_preset_names_its_sets(bench, tmp_path):
    with pytest.raises(bench.BenchError, match="--trust or --set"):
        bench.main(["--trust", "--set", f"a={tmp_path}", "--out", str(tmp_path / "t.md")])
    assert "middlebury_dino_sparse_ring" in bench.TRUST_SETS
    assert all((bench.DATA / n / "SOURCE.md").is_file() for n in bench.TRUST_SETS)
    sets, notes = bench.discover(("middlebury_dino_sparse_ring", "no_such_set"))
    assert [n for n, _, _ in sets] == ["middlebury_dino_sparse_ring"]
    assert any("no_such_set" in n and "not built" in n for n in notes)

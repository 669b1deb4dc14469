"""``benchmarks/bench_real.py`` without running a reconstruction: its metrics on synthetic poses
(a planted similarity gives zero error), its input errors, and COLMAP rows skipped when pycolmap
is absent."""

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
        spec = importlib.util.spec_from_file_location("_bench_real_under_test",
                                                      BENCH / "bench_real.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.path.remove(str(BENCH))


def _rot(axis: np.ndarray, deg: float) -> np.ndarray:
    rvec = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis) * np.deg2rad(deg)
    return cv2.Rodrigues(rvec)[0]


def _cameras(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """``n`` camera-to-world poses on a noisy ring looking inwards (not collinear)."""
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


def _similar(c2w: dict[str, np.ndarray], s: float, R: np.ndarray,
             t: np.ndarray) -> dict[str, np.ndarray]:
    """World-to-camera poses of the same cameras in a world moved by ``x -> s R x + t``."""
    out = {}
    for k, T in c2w.items():
        M = np.eye(4)
        M[:3, :3] = R @ T[:3, :3]
        M[:3, 3] = s * R @ T[:3, 3] + t
        out[k] = np.linalg.inv(M)
    return out


def test_planted_similarity_gives_zero_error(bench):
    gt = _cameras(7)
    keys = sorted(gt)
    est = _similar(gt, 0.37, _rot([1, 2, 3], 71.0), np.array([5.0, -2.0, 0.5]))
    r = bench.evaluate(keys, gt, est, dict.fromkeys(keys, 0))
    assert (r["images"], r["placed"], r["largest"], r["components"]) == (7, 7, 7, 1)
    assert r["pairs"] == 21
    for key in ("rot_deg", "pos", "rel_rot_deg", "rel_tdir_deg"):
        assert abs(r[key]) < 1e-5, (key, r[key])


def test_errors_components_and_unplaced(bench):
    gt = _cameras(8, seed=1)
    keys = sorted(gt)
    est = _similar(gt, 2.0, _rot([0, 0, 1], 30.0), np.zeros(3))
    # one camera not placed, two in a second (smaller) component
    del est[keys[7]]
    comp = {k: (1 if k in keys[5:7] else 0) for k in est}
    # one camera of the main component turned by 6 degrees about its own centre
    R6 = _rot([0, 1, 0], 6.0)
    T = est[keys[0]]
    centre = -T[:3, :3].T @ T[:3, 3]
    T[:3, :3] = R6 @ T[:3, :3]
    T[:3, 3] = -T[:3, :3] @ centre
    r = bench.evaluate(keys, gt, est, comp)
    assert (r["placed"], r["largest"], r["components"]) == (7, 5, 2)
    assert r["pairs"] == 10
    assert r["pos"] < 1e-9  # centres untouched
    assert 0 < r["rot_deg"] < 2.0  # one of five cameras off: the median is far below 6
    # the turned camera's 4 pairs of 10 carry the rotation error: the median stays small
    assert r["rel_rot_deg"] < 1e-6
    nothing = bench.evaluate(keys, gt, {}, {})
    assert nothing["placed"] == 0 and np.isnan(nothing["rot_deg"])


def _set_folder(root: Path, n: int = 3, poses: bool = True) -> Path:
    root.mkdir(parents=True)
    gt = _cameras(n)
    for k, T in gt.items():
        cv2.imwrite(str(root / k), np.full((32, 32, 3), 127, np.uint8))
        if poses:
            np.savetxt(root / (Path(k).stem + ".pose.txt"), T)
    (root / "intrinsics.json").write_text(json.dumps({"fx": 30, "fy": 30, "cx": 16, "cy": 16}))
    return root


def test_bad_inputs_name_the_problem(bench, tmp_path):
    missing = tmp_path / "nowhere"
    with pytest.raises(bench.BenchError, match="folder not found.*nowhere"):
        bench.load_set("lab", missing)
    nogt = _set_folder(tmp_path / "nogt", poses=False)
    with pytest.raises(bench.BenchError, match=r"'nogt'.*no ground truth for 3 of 3"):
        bench.load_set("nogt", nogt)
    with pytest.raises(bench.BenchError, match="unknown method 'sfm'"):
        bench.parse_method("sfm")
    with pytest.raises(bench.BenchError, match="NAME=DIR"):
        bench.parse_set("just-a-folder")
    with pytest.raises(bench.BenchError, match="folder not found.*nowhere"):
        bench.main(["--set", f"lab={missing}", "--out", str(tmp_path / "r.md")])
    m = bench.parse_method("posernet-x=sync=eig_se3 refine=true")
    assert (m.label, m.kind, m.overrides) == ("posernet-x", "posernet",
                                              ["sync=eig_se3", "refine=true"])
    s = bench.load_set("ok", _set_folder(tmp_path / "ok"), None)
    assert len(s.keys) == 3 and set(s.c2w) == set(s.keys) and s.K[0, 0] == 30
    assert bench.parse_set("a=/x/y:1,2,3,4") == ("a", Path("/x/y"), "1,2,3,4")


def test_colmap_rows_skipped_without_pycolmap(bench, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # import pycolmap -> ImportError
    folder = _set_folder(tmp_path / "tiny")
    out = tmp_path / "res" / "real.md"
    assert bench.main(["--set", f"tiny={folder}:30,30,16,16", "--method", "colmap-global",
                       "--method", "colmap-incremental", "--work", str(tmp_path / "w"),
                       "--out", str(out)]) == 0
    text = out.read_text()
    assert text.count("skipped: pycolmap is not installed") >= 2
    report = json.loads(out.with_suffix(".json").read_text())
    assert [r["method"] for r in report["rows"]] == ["colmap-global", "colmap-incremental"]
    assert all("command" not in r and r["note"].startswith("skipped") for r in report["rows"])
    assert report["versions"]["posernet"] and report["machine"]["cores"] >= 1


def test_colmap_matching_option(bench):
    # exhaustive stays the default and sets no pairing options
    assert "pairing" not in bench.colmap_options("colmap-global", 2, 0)
    opts = bench.colmap_options("colmap-global", 2, 0, "sequential")
    assert opts["pairing"] == {"overlap": 10, "quadratic_overlap": True,
                               "loop_detection": False, "num_threads": 2}
    assert opts["matching"] == {"num_threads": 2}
    with pytest.raises(bench.BenchError, match="vocabtree"):
        bench.colmap_options("colmap-global", 2, 0, "vocabtree")


# ----------------------------------------------------------------- the wide-baseline pairs mode


def test_pose_auc_matches_the_recall_curve(bench) -> None:
    # errors 1 and 3 deg of four pairs, two failed: the recall curve runs (0, 0), (1, 1/4),
    # (3, 2/4), then flat; its area up to each threshold (trapezoids), normalised
    auc5, auc10, auc20 = bench.pose_auc([1.0, 3.0, float("inf"), float("inf")])
    below3 = 0.5 * 0.25 * 1 + 0.5 * (0.25 + 0.5) * 2
    assert auc5 == pytest.approx(100 * (below3 + 0.5 * 2) / 5)
    assert auc10 == pytest.approx(100 * (below3 + 0.5 * 7) / 10)
    assert auc20 == pytest.approx(100 * (below3 + 0.5 * 17) / 20)
    assert bench.pose_auc([0.0] * 3) == pytest.approx([100.0] * 3)
    assert bench.pose_auc([float("inf")] * 2) == [0.0, 0.0, 0.0]


def test_pair_error_is_signed_and_gauge_free(bench) -> None:
    c2w = _cameras(2)
    a, b = sorted(c2w)
    est = _similar(c2w, 2.5, _rot([1, 2, 3], 40), np.array([1.0, -2.0, 0.5]))
    rot, tdir = bench.pair_error(c2w, est, a, b)
    assert rot == pytest.approx(0.0, abs=1e-6) and tdir == pytest.approx(0.0, abs=1e-5)
    # the same pair with the baseline reversed: right rotation, direction 180 deg off
    flipped = dict(est)
    rel = est[b] @ np.linalg.inv(est[a])
    rel[:3, 3] *= -1
    flipped[b] = rel @ est[a]
    rot, tdir = bench.pair_error(c2w, flipped, a, b)
    assert rot == pytest.approx(0.0, abs=1e-6) and tdir == pytest.approx(180.0, abs=1e-4)
    assert bench.pair_error(c2w, {a: est[a]}, a, b) == (float("inf"), float("inf"))


def test_wide_pairs_keep_far_apart_views_that_overlap(bench) -> None:
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])

    def cam(yaw: float, x: float) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = _rot([0, 1, 0], yaw)
        T[:3, 3] = [x, 0, 0]
        return T

    # a (yaw 0) and b (yaw 35, moved sideways) look at the same wall 2 m away; c turned away
    c2w = {"a.png": cam(0, 0), "b.png": cam(-35, 1.3), "c.png": cam(150, 0)}
    assert bench.view_overlap(K, (640, 480), c2w["a.png"], c2w["b.png"]) > 0.2
    assert bench.view_overlap(K, (640, 480), c2w["a.png"], c2w["c.png"]) == 0.0
    s = bench.ImageSet("toy", Path("."), sorted(c2w), "500,500,320,240", K, None, c2w)
    pairs = bench.wide_pairs(s, (640, 480))
    assert [(p[0], p[1]) for p in pairs] == [("a.png", "b.png")]
    assert pairs[0][2] == pytest.approx(35.0)

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

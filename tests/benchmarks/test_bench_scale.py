"""benchmarks/bench_scale.py: its table, its ratios against exhaustive matching and the
side-by-side tables with COLMAP, on mock rows (the runs themselves are what the benchmark
measures; no COLMAP needed)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location("_bench_scale_under_test",
                                                      BENCH / "bench_scale.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.path.remove(str(BENCH))


def _row(size: int, mode: str, **kw) -> dict:
    row = {"size": size, "mode": mode, "pairs": 100, "placed": size, "largest": size,
           "rot_deg": 0.1, "pos": 0.01, "wall_s": 10.0, "peak_mb": 500.0, "note": "",
           "stages": {"images": {"seconds": 2.0}, "pairs": {"seconds": 5.0},
                      "bundle_adjustment": {"seconds": 1.5}}}
    row.update(kw)
    return row


def test_ratios_are_against_exhaustive_of_the_same_size(bench) -> None:
    rows = [_row(16, "exhaustive"), _row(16, "retrieval", pairs=50, rot_deg=0.2, wall_s=5.0),
            _row(64, "retrieval", pairs=300),  # no exhaustive at 64: no ratio
            _row(16, "sequential", note="failed (exit 1)")]  # failed runs: no ratio
    rel = bench.relative_rows(rows)
    assert rel == [["16", "retrieval", "0.50", "2.00", "1.00", "0.50"]]


def test_table_rows_give_per_image_time_and_stages(bench) -> None:
    (cells,) = bench.table_rows([_row(16, "retrieval", wall_s=8.0)])
    assert cells[:3] == ["16", "retrieval", "100"] and cells[3] == "16 / 16"
    assert cells[8] == "0.50"  # 8 s over 16 images
    assert cells[10] == "2.0" and cells[12] == "5.0" and cells[14] == "1.5"
    assert cells[11] == "-"  # a stage the run did not report


def _colmap_row(size: int, **kw) -> dict:
    row = {"size": size, "mode": "sequential", "kind": "colmap-global",
           "method": "colmap-global", "pairs": 80, "verified": 78, "placed": size,
           "largest": size, "components": 1, "right": size, "wrong": 0, "rot_deg": 0.05,
           "pos": 0.002, "wall_s": 4.0, "cpu_s": 7.5, "peak_mb": 250.0, "load_start": 1.5,
           "note": "", "stages": {"features": {"seconds": 1.0}, "matching": {"seconds": 1.5},
                                  "mapping": {"seconds": 1.0}}}
    row.update(kw)
    return row


def _posernet_row(size: int, **kw) -> dict:
    stages = {"images": {"seconds": 2.0}, "pair_selection": {"seconds": 0.5},
              "pairs": {"seconds": 3.0}, "graph": {"seconds": 0.1},
              "averaging": {"seconds": 0.4}, "bundle_adjustment": {"seconds": 1.5},
              "self_check": {"seconds": 0.5}}
    return _row(size, "sequential", kind="posernet", verified=95, components=1, right=size,
                wrong=0, cpu_s=15.0, load_start=1.25, stages=stages, **kw)


def test_colmap_rows_stay_out_of_the_posernet_tables(bench) -> None:
    rows = [_row(16, "exhaustive"), _posernet_row(16), _colmap_row(16, wall_s=1.0)]
    assert [c[1] for c in bench.table_rows(rows)] == ["exhaustive", "sequential"]
    assert [r[1] for r in bench.relative_rows(rows)] == ["sequential"]


def test_side_by_side_gives_both_sides_and_posernet_over_colmap(bench) -> None:
    table = {r[0]: r[1:] for r in bench.compare_rows(_posernet_row(16), _colmap_row(16))}
    assert table["wall (s)"] == ["10.0", "4.0", "2.50"]
    assert table["CPU, user + system (s)"] == ["15.0", "7.5", "2.00"]
    assert table["peak memory (MB)"] == ["500", "250", "2.00"]
    assert table["cameras placed"] == ["16 / 16", "16 / 16", ""]
    assert table["right / wrong (5 deg, 5 % of extent)"] == ["16 / 0", "16 / 0", ""]
    assert table["abs. rot, median (deg)"] == ["0.100", "0.050", "2.00"]
    assert table["pairs matched"] == ["100", "80", "1.25"]
    assert table["pairs verified"] == ["95", "78", "1.22"]
    assert table["features (s)"] == ["2.0", "1.0", "2.00"]
    assert table["matching + verification (s)"] == ["3.5", "1.5", "2.33"]  # selection + pairs
    # steps COLMAP does not time apart: inside its mapper, no ratio
    assert table["view graph + averaging (s)"] == ["0.5", "(in mapper)", "-"]
    assert table["tracks + BA (s)"] == ["1.5", "(in mapper)", "-"]
    assert table["mapper, all of it (s)"] == ["2.5", "1.0", "2.50"]
    assert table["rest: start-up, imports, I/O (s)"] == ["2.0", "0.5", "4.00"]
    assert table["load average (1 min) at start"] == ["1.25", "1.50", ""]  # no ratio


def test_side_by_side_with_a_failed_or_missing_side(bench) -> None:
    failed = {"size": 16, "mode": "sequential", "kind": "colmap-global", "wall_s": 3.0,
              "peak_mb": float("nan"), "note": "failed (exit 1): boom"}
    table = {r[0]: r[1:] for r in bench.compare_rows(_posernet_row(16), failed)}
    assert table["wall (s)"] == ["10.0", "3.0", "3.33"]
    assert table["peak memory (MB)"] == ["500", "-", "-"]
    assert table["cameras placed"] == ["16 / 16", "-", ""]
    assert table["features (s)"] == ["2.0", "-", "-"]
    assert table["note"] == ["", "failed (exit 1): boom", ""]
    table = {r[0]: r[1:] for r in bench.compare_rows(None, _colmap_row(16))}
    assert table["wall (s)"] == ["-", "4.0", "-"] and table["note"][0] == "not run"


def test_one_table_per_size_with_colmap(bench) -> None:
    rows = [_posernet_row(16), _row(16, "retrieval"), _colmap_row(16), _posernet_row(64)]
    md = bench.compare_tables(rows, [16, 64])
    heads = [line for line in md if line.startswith("### ")]
    assert len(heads) == 1 and heads[0].startswith("### 16 images")  # 64: no COLMAP row
    wall = next(line for line in md if line.startswith("| wall (s)"))
    assert wall == "| wall (s) | 10.0 | 4.0 | 2.50 |"


def test_main_writes_the_tables_and_leaves_colmap_out_without_pycolmap(
        bench, tmp_path, monkeypatch) -> None:
    calls = []

    def fake_run(size, mode, *a):
        calls.append(("posernet", size, mode))
        return _posernet_row(size) if mode == "sequential" else _row(size, mode)

    def fake_colmap(size, *a):
        calls.append(("colmap", size))
        return _colmap_row(size)

    monkeypatch.setattr(bench, "run", fake_run)
    monkeypatch.setattr(bench, "run_colmap", fake_colmap)
    monkeypatch.setattr(bench.br, "compile_bytecode", lambda: "compiled")
    out = tmp_path / "scale.md"
    common = ["--modes", "sequential", "--work", str(tmp_path / "w"), "--out", str(out)]
    assert bench.main(["--sizes", "256", "1024", "--colmap", *common]) == 0
    assert calls == [("posernet", 256, "sequential"), ("colmap", 256),
                     ("posernet", 1024, "sequential"), ("colmap", 1024)]
    text = out.read_text()
    assert "### 256 images" in text and "### 1024 images" in text
    assert "load average (1/5/15 min) at the end" in text
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["colmap"] is True and len(report["rows"]) == 4

    calls.clear()
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # import pycolmap -> ImportError
    assert bench.main(["--sizes", "16", *common]) == 0
    assert calls == [("posernet", 16, "sequential")]
    text = out.read_text()
    assert "COLMAP left out: skipped: pycolmap is not installed" in text
    assert "### 16 images" not in text

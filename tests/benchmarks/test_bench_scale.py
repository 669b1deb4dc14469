"""benchmarks/bench_scale.py: its table and its ratios against exhaustive matching (the runs
themselves are what the benchmark measures)."""

from __future__ import annotations

import importlib.util
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

"""Paper-style tables: layout, CSV round trip, mean +- std over seeds, atomic files."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

import pytest
import torch

from posernet.metrics import ThresholdRow
from posernet.report import (
    ABSOLUTE_GROUPS,
    ResultTable,
    TableRow,
    mean_std_row,
    relative_row,
)


def test_relative_table_markdown_layout() -> None:
    rot0 = torch.tensor([2.0, 4.0, 40.0, 100.0])
    tdir0 = torch.tensor([50.0, 60.0, 90.0, float("nan")])  # a graph with no edges is skipped
    table = ResultTable(rows=[relative_row(("KP", "Initial"), rot0, tdir0),
                              relative_row(("KP", "PoserNet"), rot0 / 10, tdir0 / 10)],
                        title="Relative poses")
    md = table.to_markdown()
    lines = md.splitlines()
    header = next(line for line in lines if line.startswith("| input"))
    cols = [c.strip() for c in header.strip("|").split("|")]
    assert cols == ["input", "stage", "rot 3", "rot 5", "rot 10", "rot 30", "rot 45", "rot η",
                    "tdir 3", "tdir 5", "tdir 10", "tdir 30", "tdir 45", "tdir η"]
    row = next(line for line in lines if line.startswith("| KP | Initial"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    # rot: 2 of 4 graphs below 5 deg, median of (2, 4, 40, 100) = 22
    assert cells[2:8] == ["25.00", "50.00", "50.00", "50.00", "75.00", "22.00"]
    # tdir: NaN graph excluded -> 3 graphs, median 60
    assert cells[8:] == ["0.00", "0.00", "0.00", "0.00", "0.00", "60.00"]
    assert "Graphs per row: 3, 4." in md and "η: median over graphs" in md
    assert md.startswith("**Relative poses**")


def test_csv_round_trip_and_atomic_write(tmp_path: Path) -> None:
    table = ResultTable(rows=[relative_row(("BB", "Initial"), [1.0, 20.0], [3.5, 50.0])])
    md_path, csv_path = table.write(tmp_path / "out", stem="table")
    assert md_path.read_text() == table.to_markdown()
    rows = list(csv.DictReader(io.StringIO(csv_path.read_text())))
    assert len(rows) == 1
    r = rows[0]
    assert r["input"] == "BB" and r["stage"] == "Initial"
    assert float(r["rot_lt3"]) == 50.0 and float(r["rot_median"]) == pytest.approx(10.5)
    assert float(r["tdir_lt5"]) == 50.0 and int(r["tdir_count"]) == 2 and r["runs"] == "1"
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["table.csv", "table.md"]


def test_mean_std_over_seeds() -> None:
    seeds = [relative_row(("KP", "PoserNet"), [m, m], [2 * m, 2 * m]) for m in (7.0, 8.0, 9.0)]
    agg = mean_std_row(seeds)
    assert agg.runs == 3
    assert agg.cells["rot"].median == pytest.approx(8.0)
    assert agg.std["rot"].median == pytest.approx(1.0)  # sample std of 7, 8, 9
    assert agg.cells["rot"].percent_below[2] == pytest.approx(100.0)  # all below 10
    table = ResultTable(rows=[agg])
    assert "8.00 ± 1.00" in table.to_markdown()
    assert "mean ± sample std over 3 runs" in table.to_markdown()
    header = table.to_csv().splitlines()[0].split(",")
    assert "rot_median_std" in header and "tdir_lt45_std" in header
    single = mean_std_row(seeds[:1])
    assert single.std["rot"].median == 0.0


def test_absolute_groups_and_errors() -> None:
    row = TableRow(("KP", "EIG-SE3"), {
        "rot": ThresholdRow((3.0, 5.0, 10.0, 30.0, 45.0), (0, 0, 10, 50, 90), 25.0, 10),
        "trans": ThresholdRow((0.05, 0.1, 0.25, 0.5, 0.75), (0, 5, 20, 60, 80), 0.61, 10)})
    md = ResultTable(rows=[row], groups=ABSOLUTE_GROUPS).to_markdown()
    assert "trans 0.05" in md and "| KP | EIG-SE3 |" in md and "0.61" in md
    with pytest.raises(ValueError, match="no values for group 'tdir'"):
        ResultTable(rows=[row]).to_markdown()
    with pytest.raises(ValueError, match="label columns"):
        ResultTable(rows=[row], label_names=("only",), groups=ABSOLUTE_GROUPS).to_csv()
    with pytest.raises(ValueError, match="no rows"):
        mean_std_row([])


def test_empty_row_prints_nan() -> None:
    row = relative_row(("KP", "Initial"), [], [])
    assert math.isnan(row.cells["rot"].median)
    assert "nan" in ResultTable(rows=[row]).to_markdown()

"""Paper-style result tables (markdown + CSV) built from :class:`posernet.metrics.ThresholdRow`.

The layout follows the paper's Table 1: label columns (e.g. input and stage), then one block
per metric group, each with the percentage of graphs below every threshold and the median over
graphs (``eta``)::

    | input | stage    | rot 3 | rot 5 | ... | rot η | tdir 3 | ... | tdir η |
    | KP    | Initial  |  0.00 |  0.12 | ... | 36.26 |   0.00 | ... |  87.23 |
    | KP    | PoserNet | ...

Rows may carry a standard deviation (mean +- std over seeds, see :func:`mean_std_row`).
Files are written atomically (:func:`posernet.io.atomic_write_text`).
"""

from __future__ import annotations

import csv
import io
import math
import os
import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from .io import atomic_write_text
from .metrics import ANGLE_THRESHOLDS_DEG, METRE_THRESHOLDS, ThresholdRow, relative_rows

__all__ = [
    "ABSOLUTE_GROUPS",
    "RELATIVE_GROUPS",
    "MedianRow",
    "MedianTable",
    "MetricGroup",
    "ResultTable",
    "TableRow",
    "absolute_groups",
    "cpu_model",
    "interleave",
    "mean_std_row",
    "ours",
    "relative_row",
]


@dataclass(frozen=True)
class MetricGroup:
    """A block of columns: ``key`` (CSV prefix and short header), ``title``, ``thresholds``."""

    key: str
    title: str
    thresholds: tuple[float, ...]


RELATIVE_GROUPS: tuple[MetricGroup, ...] = (
    MetricGroup("rot", "Orientation error (deg)", ANGLE_THRESHOLDS_DEG),
    MetricGroup("tdir", "Translation direction error (deg)", ANGLE_THRESHOLDS_DEG),
)


def absolute_groups(units: str = "m") -> tuple[MetricGroup, ...]:
    """The absolute-pose column blocks, translation in ``units`` (the ground truth's unit;
    its thresholds are in that unit too)."""
    return (MetricGroup("rot", "Rotation error (deg)", ANGLE_THRESHOLDS_DEG),
            MetricGroup("trans", f"Translation error ({units})", METRE_THRESHOLDS))


ABSOLUTE_GROUPS: tuple[MetricGroup, ...] = absolute_groups()


@dataclass(frozen=True)
class TableRow:
    """One table row: its labels and one :class:`ThresholdRow` per metric group key.

    ``std`` (same keys) holds standard deviations when the row is a mean over seeds;
    ``runs`` is the number of runs averaged (1 for a single run). ``placed`` is
    ``(cameras placed, cameras)`` for rows of absolute poses (summed over runs): cameras that
    motion averaging could not place have no error; they are counted here, not scored.
    """

    labels: tuple[str, ...]
    cells: Mapping[str, ThresholdRow]
    std: Mapping[str, ThresholdRow] | None = None
    runs: int = 1
    placed: tuple[int, int] | None = None


def relative_row(labels: Sequence[str], rot_per_graph: Tensor | Sequence[float],
                 tdir_per_graph: Tensor | Sequence[float],
                 thresholds: Sequence[float] = ANGLE_THRESHOLDS_DEG) -> TableRow:
    """Row of a relative-pose table from per-graph mean errors (degrees).

    The rows are :func:`posernet.metrics.relative_rows` (the one implementation of the tables).
    """
    return TableRow(tuple(labels), relative_rows({"rot": rot_per_graph, "tdir": tdir_per_graph},
                                                 thresholds))


def mean_std_row(rows: Sequence[TableRow], labels: Sequence[str] | None = None) -> TableRow:
    """Mean and sample standard deviation (``ddof=1``; 0 for one run) of rows over seeds.

    All rows must have the same group keys and thresholds. Counts (graphs, skipped items) are
    averaged too; placed cameras are summed over the rows.
    """
    rows = list(rows)
    if not rows:
        raise ValueError("mean_std_row: no rows to aggregate")
    keys = list(rows[0].cells)
    cells: dict[str, ThresholdRow] = {}
    std: dict[str, ThresholdRow] = {}
    for key in keys:
        parts = [r.cells[key] for r in rows]
        ths = parts[0].thresholds
        if any(p.thresholds != ths for p in parts):
            raise ValueError(f"mean_std_row: group {key!r} has different thresholds across rows")
        vals = torch.tensor([[*p.percent_below, p.median] for p in parts], dtype=torch.float64)
        mean = vals.mean(0)
        sd = vals.std(0, correction=1) if len(parts) > 1 else torch.zeros_like(mean)
        count = round(sum(p.count for p in parts) / len(parts))
        skipped = round(sum(p.skipped for p in parts) / len(parts))
        cells[key] = ThresholdRow(ths, tuple(mean[:-1].tolist()), float(mean[-1]), count,
                                  skipped)
        std[key] = ThresholdRow(ths, tuple(sd[:-1].tolist()), float(sd[-1]), count, skipped)
    placed = None
    if any(r.placed is not None for r in rows):
        if any(r.placed is None for r in rows):
            raise ValueError("mean_std_row: some rows count placed cameras and some do not")
        placed = (sum(r.placed[0] for r in rows), sum(r.placed[1] for r in rows))
    return TableRow(tuple(labels) if labels is not None else rows[0].labels, cells, std,
                    runs=len(rows), placed=placed)


def _fmt(v: float, digits: int) -> str:
    return "nan" if math.isnan(v) else f"{v:.{digits}f}"


@dataclass
class ResultTable:
    """A paper-style table: label columns + metric groups; renders markdown and CSV.

    Args:
        rows: the rows, in display order.
        label_names: header of each label column (default ``("input", "stage")``).
        groups: the metric groups (default :data:`RELATIVE_GROUPS`).
        title: optional title printed above the markdown table.
        note: optional line printed below it (e.g. the alignment used).
    """

    rows: list[TableRow] = field(default_factory=list)
    label_names: tuple[str, ...] = ("input", "stage")
    groups: tuple[MetricGroup, ...] = RELATIVE_GROUPS
    title: str | None = None
    note: str | None = None

    def _check(self) -> None:
        for r in self.rows:
            if len(r.labels) != len(self.label_names):
                raise ValueError(f"row {r.labels} has {len(r.labels)} labels, the table "
                                 f"has {len(self.label_names)} label columns")
            for g in self.groups:
                if g.key not in r.cells:
                    raise ValueError(f"row {r.labels} has no values for group {g.key!r}")

    def _cell(self, row: TableRow, key: str, k: int | None, digits: int) -> str:
        """Value ``k`` (a threshold index, or None for the median) with its std if any."""
        cell = row.cells[key]
        v = cell.median if k is None else cell.percent_below[k]
        text = _fmt(v, digits)
        if row.std is not None and row.runs > 1:
            s = row.std[key]
            text += f" ± {_fmt(s.median if k is None else s.percent_below[k], digits)}"
        return text

    def to_markdown(self, digits: int = 2) -> str:
        """Markdown table; threshold columns are % of graphs below, ``η`` the median."""
        self._check()
        header = list(self.label_names)
        for g in self.groups:
            header += [f"{g.key} {t:g}" for t in g.thresholds] + [f"{g.key} η"]
        lines = []
        if self.title:
            lines += [f"**{self.title}**", ""]
        lines.append("| " + " | ".join(header) + " |")
        lines.append("|" + "|".join(["---"] * len(self.label_names) +
                                    ["---:"] * (len(header) - len(self.label_names))) + "|")
        for r in self.rows:
            cells = list(r.labels)
            for g in self.groups:
                cells += [self._cell(r, g.key, k, digits) for k in range(len(g.thresholds))]
                cells.append(self._cell(r, g.key, None, digits))
            lines.append("| " + " | ".join(cells) + " |")
        legend = "; ".join(f"{g.key}: {g.title}" for g in self.groups)
        lines += ["", f"{legend}. Columns: % of graphs whose error is below each threshold; "
                      "η: median over graphs."]
        counts = sorted({c.count for r in self.rows for c in r.cells.values()})
        if counts:
            lines.append(f"Graphs per row: {', '.join(str(c) for c in counts)}.")
        lines += self._placed_lines() + self._skipped_lines()
        if any(r.runs > 1 for r in self.rows):
            runs = sorted({r.runs for r in self.rows if r.runs > 1})
            lines.append(f"Values are mean ± sample std over {', '.join(map(str, runs))} runs.")
        if self.note:
            lines.append(self.note)
        return "\n".join(lines) + "\n"

    def _placed_lines(self) -> list[str]:
        """``Cameras placed: k of n`` for rows that count them (absolute poses)."""
        rows = [r for r in self.rows if r.placed is not None]
        if not rows:
            return []
        if len({r.placed for r in rows}) == 1 and len(rows) == len(self.rows):
            k, n = rows[0].placed
            text = f"Cameras placed: {k} of {n} in every row"
        else:
            text = "Cameras placed: " + "; ".join(
                f"{' / '.join(r.labels)} {r.placed[0]} of {r.placed[1]}" for r in rows)
        if any(r.placed[0] < r.placed[1] for r in rows):
            text += (" (errors are means over each graph's placed cameras; unplaced cameras "
                     "have no pose and are not scored, a graph with none placed is left out "
                     "of its row)")
        return [text + "."]

    def _skipped_lines(self) -> list[str]:
        """Items (edges/cameras) left out of the per-graph means, where there are any."""
        parts = [f"{' / '.join(r.labels)} {g.key} {r.cells[g.key].skipped}"
                 for r in self.rows for g in self.groups if r.cells[g.key].skipped]
        if not parts:
            return []
        return ["Left out of the per-graph means (no measurable error, e.g. a zero-length "
                "translation): " + "; ".join(parts) + "."]

    def to_csv(self) -> str:
        """CSV with one column per label, threshold, median and count (plus ``_std`` columns).

        ``{group}_skipped`` columns are added when some row left items out of its means, and
        ``cameras_placed``/``cameras`` when rows count placed cameras.
        """
        self._check()
        with_std = any(r.std is not None for r in self.rows)
        with_skipped = any(c.skipped for r in self.rows for c in r.cells.values())
        with_placed = any(r.placed is not None for r in self.rows)
        header = list(self.label_names)
        for g in self.groups:
            names = [f"{g.key}_lt{t:g}" for t in g.thresholds] + [f"{g.key}_median"]
            header += names
            if with_std:
                header += [n + "_std" for n in names]
            header.append(f"{g.key}_count")
            if with_skipped:
                header.append(f"{g.key}_skipped")
        header.append("runs")
        if with_placed:
            header += ["cameras_placed", "cameras"]
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(header)
        for r in self.rows:
            out: list[object] = list(r.labels)
            for g in self.groups:
                c = r.cells[g.key]
                out += [*c.percent_below, c.median]
                if with_std:
                    s = r.std[g.key] if r.std is not None else None
                    out += ([*s.percent_below, s.median] if s is not None
                            else [0.0] * (len(g.thresholds) + 1))
                out.append(c.count)
                if with_skipped:
                    out.append(c.skipped)
            out.append(r.runs)
            if with_placed:
                out += list(r.placed) if r.placed is not None else ["", ""]
            w.writerow(out)
        return buf.getvalue()

    def write(self, out_dir: str | os.PathLike[str], stem: str = "table",
              digits: int = 2) -> tuple[Path, Path]:
        """Write ``{stem}.md`` and ``{stem}.csv`` into ``out_dir`` atomically; return both paths."""
        out = Path(out_dir)
        md = atomic_write_text(out / f"{stem}.md", self.to_markdown(digits))
        cs = atomic_write_text(out / f"{stem}.csv", self.to_csv())
        return md, cs


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``; else what :mod:`platform` says), for the machine
    lines of result tables and benchmarks."""
    import platform

    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


# --------------------------------------------------------------------------- the experiments'
# Full tables of the experiment runner reuse :class:`ResultTable` with a leading ``source``
# label column (``paper`` / ``ours``). The depth ablation and the leave-one-scene-out test are
# published as medians only; :class:`MedianTable` prints our medians (mean ± std over seeds)
# next to them.


def ours(row: TableRow) -> TableRow:
    """``row`` with the label ``ours`` prepended."""
    return TableRow(("ours", *row.labels), row.cells, row.std, row.runs)


def interleave(paper: dict[tuple[str, ...], TableRow],
               mine: dict[tuple[str, ...], TableRow]) -> list[TableRow]:
    """Rows ordered by key, the paper's row (when it has one) right above ours."""
    out: list[TableRow] = []
    for key in dict.fromkeys([*paper, *mine]):
        if key in paper:
            out.append(paper[key])
        if key in mine:
            out.append(mine[key])
    return out


@dataclass
class MedianRow:
    """Median rotation / translation-direction errors of one setting.

    ``rot`` and ``tdir`` hold one value per seed; ``paper`` the paper's (rot, tdir), if any.
    """

    label: str
    rot: list[float]
    tdir: list[float]
    paper: tuple[float, float] | None = None
    graphs: int = 0


def _mean_std(v: Sequence[float], digits: int) -> str:
    if not v:
        return "—"
    m = statistics.fmean(v)
    text = "nan" if math.isnan(m) else f"{m:.{digits}f}"
    if len(v) > 1:
        text += f" ± {statistics.stdev(v):.{digits}f}"
    return text


@dataclass
class MedianTable:
    """Medians (degrees) of several settings, ours beside the paper's."""

    setting: str
    rows: list[MedianRow] = field(default_factory=list)
    title: str | None = None
    note: str | None = None

    def to_markdown(self, digits: int = 2) -> str:
        """Markdown: one row per setting, our median ± std and the paper's for each metric."""
        lines = [f"**{self.title}**", ""] if self.title else []
        lines.append(f"| {self.setting} | rot η (ours) | rot η (paper) | tdir η (ours) | "
                     "tdir η (paper) | graphs | runs |")
        lines.append("|---|---:|---:|---:|---:|---:|---:|")
        for r in self.rows:
            p = ("—", "—") if r.paper is None else tuple(f"{x:.2f}" for x in r.paper)
            lines.append(f"| {r.label} | {_mean_std(r.rot, digits)} | {p[0]} | "
                         f"{_mean_std(r.tdir, digits)} | {p[1]} | {r.graphs} | {len(r.rot)} |")
        lines += ["", "rot: relative orientation error, tdir: translation direction error "
                      "(degrees); η: median over graphs; ours: mean ± sample std over runs."]
        if self.note:
            lines.append(self.note)
        return "\n".join(lines) + "\n"

    def to_csv(self) -> str:
        """CSV: setting, our mean/std per metric, the paper's value, graphs, runs."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow([self.setting, "rot_median", "rot_median_std", "rot_median_paper",
                    "tdir_median", "tdir_median_std", "tdir_median_paper", "graphs", "runs"])
        for r in self.rows:
            vals: list[object] = [r.label]
            for k, v in enumerate((r.rot, r.tdir)):
                vals += [statistics.fmean(v) if v else "",
                         statistics.stdev(v) if len(v) > 1 else 0.0,
                         "" if r.paper is None else r.paper[k]]
            w.writerow([*vals, r.graphs, len(r.rot)])
        return buf.getvalue()

    def write(self, out_dir: str | os.PathLike[str], stem: str = "table",
              digits: int = 2) -> tuple[Path, Path]:
        """Write ``{stem}.md`` and ``{stem}.csv`` atomically; return both paths."""
        out = Path(out_dir)
        return (atomic_write_text(out / f"{stem}.md", self.to_markdown(digits)),
                atomic_write_text(out / f"{stem}.csv", self.to_csv()))

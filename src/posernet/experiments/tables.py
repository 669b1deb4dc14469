"""Tables of the experiment runner: paper rows beside ours, and median-only comparisons.

Full tables reuse :class:`posernet.report.ResultTable` with a leading ``source`` label column
(``paper`` / ``ours``). The depth ablation and the leave-one-scene-out test are published as
medians only; :class:`MedianTable` prints our medians (mean ± std over seeds) next to them.
"""

from __future__ import annotations

import csv
import io
import math
import os
import statistics
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ..io import atomic_write_text
from ..report import TableRow

__all__ = ["MedianRow", "MedianTable", "interleave", "ours"]


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

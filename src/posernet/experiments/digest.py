"""A one-page digest of a run: the medians of every table, ours beside the paper's.

Built only from the CSV files the experiments wrote (``<out>/<experiment>/*.csv``), so the numbers
quoted in docs/results.md can be checked against the runner's output.
"""

from __future__ import annotations

import csv
from pathlib import Path

from ..io import atomic_write_text

__all__ = ["digest_markdown", "write_digest"]

# experiment folder, csv, heading, (metric key, column title, unit digits)
_PAIRED = [
    ("table1", "table.csv", "Table 1: relative poses, small graphs (median over graphs, deg)",
     [("rot", "rotation", 1), ("tdir", "transl. direction", 1)]),
    ("table2", "table.csv", "Table 2: small vs large graphs, KP (median over graphs, deg)",
     [("rot", "rotation", 1), ("tdir", "transl. direction", 1)]),
    ("table3", "table.csv", "Table 3: motion averaging, absolute poses (median over graphs)",
     [("rot", "rotation (deg)", 1), ("trans", "position (m)", 3)]),
]
_MEDIANS = [
    ("depth", "table.csv", "Depth ablation, KP (median over graphs, deg)"),
    ("depth", "alpha.csv", "Loss weight alpha, KP (median over graphs, deg)"),
    ("loo", "table.csv", "Leave one scene out, KP (median over graphs, deg)"),
]


def _read(path: Path) -> list[dict[str, str]]:
    with path.open(newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def _cell(row: dict[str, str] | None, key: str, digits: int) -> str:
    """``value ± std`` (std only when the row averages several runs and it is non-zero)."""
    if row is None or not row.get(key):
        return ""
    text = f"{float(row[key]):.{digits}f}"
    std = row.get(f"{key}_std")
    if std and int(float(row.get("runs") or 1)) > 1:
        text += f" ± {float(std):.{digits}f}"
    return text


def _paired(rows: list[dict[str, str]], metrics: list[tuple[str, str, int]]) -> list[str]:
    labels = [k for k in rows[0] if k not in ("source", "runs")
              and not any(k.startswith(f"{m}_") for m, _, _ in metrics)]
    keyed: dict[tuple[str, ...], dict[str, dict[str, str]]] = {}
    for r in rows:
        keyed.setdefault(tuple(r[k] for k in labels), {})[r["source"]] = r
    head = [*labels]
    for _, title, _ in metrics:
        head += [f"{title} ours", f"{title} paper"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(labels)
             + "---:|" * (2 * len(metrics))]
    for key, by_src in keyed.items():
        cells = list(key)
        for m, _, digits in metrics:
            cells += [_cell(by_src.get("ours"), f"{m}_median", digits),
                      _cell(by_src.get("paper"), f"{m}_median", digits)]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _medians(rows: list[dict[str, str]]) -> list[str]:
    label = next(iter(rows[0]))
    lines = [f"| {label} | rotation ours | rotation paper | transl. direction ours | "
             "transl. direction paper |", "|---|---:|---:|---:|---:|"]
    for r in rows:
        cells = [r[label]]
        for m in ("rot", "tdir"):
            cells += [_cell(r, f"{m}_median", 1),
                      f"{float(r[f'{m}_median_paper']):.1f}" if r.get(f"{m}_median_paper")
                      else ""]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def digest_markdown(out: str | Path) -> str:
    """Markdown with the median columns of every table found under ``out`` (ours vs paper)."""
    out = Path(out)
    parts: list[str] = []
    for folder, name, heading, metrics in _PAIRED:
        path = out / folder / name
        if path.is_file() and (rows := _read(path)):
            parts += [f"**{heading}**", "", *_paired(rows, metrics), ""]
    for folder, name, heading in _MEDIANS:
        path = out / folder / name
        if path.is_file() and (rows := _read(path)):
            parts += [f"**{heading}**", "", *_medians(rows), ""]
    if not parts:
        raise FileNotFoundError(f"{out}: no experiment tables (*/table.csv) to digest")
    return "\n".join(parts)


def write_digest(out: str | Path) -> Path:
    """Write :func:`digest_markdown` to ``<out>/digest.md`` atomically; returns its path."""
    return atomic_write_text(Path(out) / "digest.md", digest_markdown(out))

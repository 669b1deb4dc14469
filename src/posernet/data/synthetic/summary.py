"""Dataset statistics in the paper's formats: composition (Table 1) and initial errors (Table 2).

Per-graph errors are the mean over a graph's edges; a row gives the % of graphs below 3, 5, 10,
30 and 45 degrees and the median over graphs (``eta``), like the paper.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

from ...metrics import ANGLE_THRESHOLDS_DEG, threshold_row

__all__ = [
    "PAPER_INITIAL",
    "aggregate_stats",
    "composition_row",
    "error_table",
    "format_summary",
]

# Paper, Table 2 ("Initial" rows), 8-node test graphs of 7-Scenes: % below 3/5/10/30/45, median.
PAPER_INITIAL: dict[str, dict[str, list[float]]] = {
    "kp": {"rot": [0.74, 4.01, 11.16, 41.46, 62.53, 36.26],
           "tdir": [0.00, 0.03, 0.10, 1.37, 5.49, 87.23]},
    "bb": {"rot": [0.00, 0.00, 0.00, 0.16, 1.44, 96.48],
           "tdir": [0.00, 0.00, 0.00, 0.00, 0.00, 89.30]},
}  # fmt: skip

_COUNTERS = (
    "graphs",
    "nodes",
    "edges",
    "detections",
    "matched_pairs",
    "pairs_checked",
    "image_pairs_matched",
    "dropped_kp",
    "dropped_bb",
    "wrong_box_matches",
    "kp_correspondences",
    "kp_outliers",
)


def aggregate_stats(stats: Iterable[Mapping[str, Any]]) -> dict[str, Any]:
    """Sum chunk statistics (counters add up, per-graph error lists concatenate)."""
    out: dict[str, Any] = {k: 0 for k in _COUNTERS}
    out["errors"] = {}
    for s in stats:
        for k in _COUNTERS:
            out[k] += int(s.get(k, 0))
        for k, v in s.get("errors", {}).items():
            out["errors"].setdefault(k, []).extend(v)
    return out


def _ratio(a: float, b: float) -> float:
    return float(a) / float(b) if b else float("nan")


def composition_row(s: Mapping[str, Any]) -> dict[str, float]:
    """Counts of Table 1 plus matching details, from aggregated statistics."""
    return {
        "graphs": s["graphs"],
        "nodes": s["nodes"],
        "edges": s["edges"],
        "nodes_per_graph": _ratio(s["nodes"], s["graphs"]),
        "edges_per_graph": _ratio(s["edges"], s["graphs"]),
        "edges_per_node": _ratio(s["edges"], s["nodes"]),
        "matched_pairs_per_edge": _ratio(s["matched_pairs"], s["edges"]),
        "detections_per_node": _ratio(s["detections"], s["nodes"]),
        "kp_correspondences_per_edge": _ratio(s["kp_correspondences"], s["edges"]),
        "kp_outlier_fraction": _ratio(s["kp_outliers"], s["kp_correspondences"]),
        "wrong_box_match_fraction": _ratio(s["wrong_box_matches"], s["matched_pairs"]),
        "dropped_edges_kp": s["dropped_kp"],
        "dropped_edges_bb": s["dropped_bb"],
    }


def error_table(errors: Mapping[str, list[float]]) -> dict[str, dict[str, dict[str, float]]]:
    """``{input: {"rot"|"tdir": {"<3": %, ..., "median": eta, "count": n}}}`` (NaN-free)."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    for inp in ("kp", "bb"):
        out[inp] = {}
        for m in ("rot", "tdir"):
            row = threshold_row(errors.get(f"{inp}_{m}", []), ANGLE_THRESHOLDS_DEG)
            d = row.as_dict()
            d["count"] = row.count
            out[inp][m] = {
                k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in d.items()
            }
    return out


def _fmt(v: Any, width: int = 7, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-".rjust(width)
    return f"{v:{width}.{digits}f}"


def _row_values(cell: Mapping[str, Any]) -> list[Any]:
    return [cell.get(f"<{t:g}") for t in ANGLE_THRESHOLDS_DEG] + [cell.get("median")]


def format_summary(manifest: Mapping[str, Any]) -> str:
    """Short human-readable report of a dataset manifest (composition + initial errors)."""
    lines = [
        f"posernet synthetic dataset {manifest.get('preset')!r} "
        f"(seed {manifest.get('seed')}) at {manifest.get('root', '?')}"
    ]
    head = (
        f"{'size':6}{'split':6}{'graphs':>8}{'nodes':>9}{'edges':>9}{'nodes/g':>9}"
        f"{'edges/g':>9}{'edges/n':>9}{'pairs/e':>9}{'kp/e':>7}{'dropped kp/bb':>15}"
    )
    lines += ["", head]
    comp = manifest.get("composition", {})
    for size, splits in comp.items():
        for split, c in splits.items():
            lines.append(
                f"{size:6}{split:6}{c['graphs']:>8}{c['nodes']:>9}{c['edges']:>9}"
                f"{_fmt(c['nodes_per_graph'], 9, 1)}{_fmt(c['edges_per_graph'], 9, 1)}"
                f"{_fmt(c['edges_per_node'], 9, 2)}{_fmt(c['matched_pairs_per_edge'], 9, 1)}"
                f"{_fmt(c['kp_correspondences_per_edge'], 7, 0)}"
                f"{c['dropped_edges_kp']:>9}/{c['dropped_edges_bb']:<5}"
            )
    stats = manifest.get("statistics", {})
    # The paper's table is on small test graphs; fall back to whatever exists.
    order = [(s, p) for s in ("small", "large") for p in ("test", "val", "train")]
    main = next(((s, p) for s, p in order if stats.get(s, {}).get(p)), None)
    if main is None:
        return "\n".join(lines)
    size, split = main
    tab = stats[size][split]
    ths = "".join(f"{t:>7g}" for t in ANGLE_THRESHOLDS_DEG)
    lines += [
        "",
        f"Initial relative poses, {size} {split} graphs: % of graphs whose mean error is below "
        f"each threshold, eta = median over graphs (deg)",
        f"{'':12}{'orientation error':^43}      {'translation direction error':^43}",
        f"{'input':12}{ths}{'eta':>8}      {ths}{'eta':>8}",
    ]
    for inp in ("kp", "bb"):
        for who, rot, tdir in (
            ("ours", _row_values(tab[inp]["rot"]), _row_values(tab[inp]["tdir"])),
            ("paper", PAPER_INITIAL[inp]["rot"], PAPER_INITIAL[inp]["tdir"]),
        ):
            r = "".join(_fmt(v) for v in rot[:-1]) + _fmt(rot[-1], 8)
            t = "".join(_fmt(v) for v in tdir[:-1]) + _fmt(tdir[-1], 8)
            lines.append(f"{inp.upper():4}{who:8}{r}      {t}")
    others = [(s, p) for s, p in order if (s, p) != main and stats.get(s, {}).get(p)]
    for s, p in others:
        t = stats[s][p]
        lines.append(
            f"  {s} {p}: eta KP {_fmt(t['kp']['rot']['median'], 0, 1)} / "
            f"{_fmt(t['kp']['tdir']['median'], 0, 1)}, BB {_fmt(t['bb']['rot']['median'], 0, 1)}"
            f" / {_fmt(t['bb']['tdir']['median'], 0, 1)} (rot / tdir)"
        )
    return "\n".join(lines)

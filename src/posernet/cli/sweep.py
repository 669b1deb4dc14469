"""One table across the jobs of a ``-m`` sweep, written when the sweep ends.

A Hydra callback (``hydra.callbacks.sweep_summary`` in ``posernet/conf/train.yaml``): after
``posernet-train -m model.net.depth=2,3 ...`` every job folder of the sweep holds its
``metrics.json`` and ``.hydra/overrides.yaml``; :class:`SweepSummary` reads them and writes
``summary.md`` and ``summary.csv`` into the sweep folder (one row per job: the swept values,
the best value of the optimised metric, epochs and the best checkpoint), best first. Jobs that
wrote no metrics (failed, interrupted) are listed with a note, not dropped.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback

from ..io import atomic_write_text

__all__ = ["SweepSummary", "sweep_rows", "write_sweep_summary"]


def _overrides(job: Path) -> dict[str, str]:
    path = job / ".hydra" / "overrides.yaml"
    if not path.is_file():
        return {}
    from omegaconf import OmegaConf

    out = {}
    for item in OmegaConf.load(path):
        key, _, value = str(item).lstrip("+~").partition("=")
        out[key] = value
    return out


def sweep_rows(sweep_dir: str | Path) -> tuple[list[str], list[dict[str, Any]]]:
    """The swept keys (those whose values differ between jobs) and one row per job folder:
    ``job``, the swept values, ``best``, ``metric``, ``epochs``, ``checkpoint``, ``note``."""
    jobs = sorted((p for p in Path(sweep_dir).iterdir()
                   if p.is_dir() and not p.name.startswith(".")),
                  key=lambda p: (len(p.name.split("_", 1)[0]), p.name))
    overrides = {job: _overrides(job) for job in jobs}
    keys = sorted({k for o in overrides.values() for k in o})
    swept = [k for k in keys if len({o.get(k) for o in overrides.values()}) > 1]
    rows = []
    for job in jobs:
        row: dict[str, Any] = {"job": job.name.split("_", 1)[0],
                               **{k: overrides[job].get(k, "") for k in swept}}
        metrics = job / "metrics.json"
        try:
            m = json.loads(metrics.read_text(encoding="utf-8"))
            best = m.get("best")
            row.update(best=best if best is not None else math.nan,
                       metric=m.get("optimized_metric", ""), epochs=m.get("epochs"),
                       checkpoint=m.get("best_checkpoint") or "", note="")
        except (OSError, ValueError):
            row.update(best=math.nan, metric="", epochs=None, checkpoint="",
                       note="no metrics.json (failed or interrupted)")
        rows.append(row)
    rows.sort(key=lambda r: (math.isnan(r["best"]), r["best"] if not math.isnan(r["best"])
                             else 0.0))
    return swept, rows


def write_sweep_summary(sweep_dir: str | Path) -> tuple[Path, Path] | None:
    """Write ``summary.md`` and ``summary.csv`` of the sweep in ``sweep_dir`` (atomically);
    None when it holds no job folder."""
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        return None
    swept, rows = sweep_rows(sweep_dir)
    if not rows:
        return None
    cols = ["job", *swept, "best", "metric", "epochs", "checkpoint", "note"]

    def cell(v: Any) -> str:
        if isinstance(v, float):
            return "-" if math.isnan(v) else f"{v:.4f}"
        return "" if v is None else str(v)

    metric = next((r["metric"] for r in rows if r["metric"]), "best")
    md = [f"# Sweep {sweep_dir.name}: {len(rows)} jobs, best {metric} first", "",
          "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    md += ["| " + " | ".join(cell(r.get(c)) for c in cols) + " |" for r in rows]
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(cols)
    w.writerows([[cell(r.get(c)) for c in cols] for r in rows])
    return (atomic_write_text(sweep_dir / "summary.md", "\n".join(md) + "\n"),
            atomic_write_text(sweep_dir / "summary.csv", buf.getvalue()))


class SweepSummary(Callback):
    """Hydra callback: :func:`write_sweep_summary` of the sweep folder when a ``-m`` run ends."""

    def on_multirun_end(self, config: Any, **kwargs: Any) -> None:
        paths = write_sweep_summary(str(config.hydra.sweep.dir))
        if paths:
            print(f"sweep summary: {paths[0]}")

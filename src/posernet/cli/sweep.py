"""One table across the jobs of a ``-m`` sweep, written when the sweep ends.

A Hydra callback (``hydra.callbacks.sweep_summary`` in ``posernet/conf/train.yaml``): after
``posernet-train -m model.net.depth=2,3 ...`` every job folder of the sweep holds its
``metrics.json`` and ``.hydra/overrides.yaml``; :class:`SweepSummary` reads them and writes
``summary.md`` and ``summary.csv`` into the sweep folder (one row per job: the swept values,
the validation rotation error at the job's best checkpoint, the best value of the optimised
metric, epochs and the best checkpoint). Jobs are ranked by that rotation error
(:data:`RANK_METRICS`): the optimised metric, ``val/loss`` by default, weighs its terms by
``model.loss.alpha`` and so cannot compare jobs with different loss weights. Jobs that wrote
no metrics (failed, interrupted) are listed with a note, not dropped, and make the command's
exit status 1.
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
import sys
import time
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback

from ..io import atomic_write_text

__all__ = ["RANK_METRICS", "SweepSummary", "sweep_rows", "write_sweep_summary"]

#: what the summary ranks jobs by: the first of these (median validation errors in degrees,
#: at each job's best checkpoint) that some job recorded; else the optimised metric
RANK_METRICS = ("val/rot_err_deg", "val/abs_rot_err_deg")

#: a job folder written less than this long before the sweep started still counts as its own
#: (clocks of cluster nodes and file servers differ a little)
_CLOCK_SLACK_S = 60.0

_FAILED = "no metrics.json (failed or interrupted)"


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


def _job_dirs(sweep_dir: Path, since: float | None) -> list[Path]:
    """The job folders below ``sweep_dir``: those holding a Hydra record (``.hydra/``), at any
    depth (``hydra.sweep.subdir`` may nest them), written at or after ``since`` (seconds since
    the epoch; None: any)."""
    found: list[Path] = []
    todo = [sweep_dir]
    while todo:
        folder = todo.pop()
        for p in folder.iterdir():
            if not p.is_dir() or p.is_symlink() or p.name.startswith("."):
                continue
            record = p / ".hydra"
            if record.is_dir():  # Hydra rewrites its files when a job (re)starts
                written = max([record.stat().st_mtime,
                               *(f.stat().st_mtime for f in record.iterdir())])
                if since is None or written >= since:
                    found.append(p)
            else:
                todo.append(p)
    return found


def _job_name(job: Path, sweep_dir: Path) -> str:
    """``3`` for Hydra's default ``3_<overrides>`` folder, else the path below the sweep."""
    rel = job.relative_to(sweep_dir).as_posix()
    number = re.match(r"(\d+)_", rel)
    return number.group(1) if number and "/" not in rel else rel


def _lowest_first(value: float) -> tuple[bool, float]:
    return (math.isnan(value), 0.0 if math.isnan(value) else value)


def _rank_metric(rows: list[dict[str, Any]]) -> str | None:
    """The first of :data:`RANK_METRICS` that some row has a value of."""
    return next((m for m in RANK_METRICS if any(not math.isnan(r[m]) for r in rows)), None)


def sweep_rows(sweep_dir: str | Path,
               since: float | None = None) -> tuple[list[str], list[dict[str, Any]]]:
    """The swept keys (those whose values differ between jobs) and one row per job folder
    (written at or after ``since``, when given): ``job``, the swept values, each of
    :data:`RANK_METRICS` at the best checkpoint, ``best``, ``metric``, ``epochs``,
    ``checkpoint``, ``note``. Ranked: jobs with metrics first, by the first rank metric any
    job has, then by ``best``."""
    sweep_dir = Path(sweep_dir)
    jobs = _job_dirs(sweep_dir, since)
    overrides = {job: _overrides(job) for job in jobs}
    keys = sorted({k for o in overrides.values() for k in o})
    swept = [k for k in keys if len({o.get(k) for o in overrides.values()}) > 1]
    rows = []
    for job in jobs:
        row: dict[str, Any] = {"job": _job_name(job, sweep_dir),
                               **{k: overrides[job].get(k, "") for k in swept}}
        try:
            m = json.loads((job / "metrics.json").read_text(encoding="utf-8"))
            best = m.get("best")
            at_best = m.get("best_metrics") or {}
            row.update({k: float(at_best.get(k, math.nan)) for k in RANK_METRICS},
                       best=best if best is not None else math.nan,
                       metric=m.get("optimized_metric", ""), epochs=m.get("epochs"),
                       checkpoint=m.get("best_checkpoint") or "", note="")
        except (OSError, ValueError, TypeError, AttributeError):
            row.update({k: math.nan for k in RANK_METRICS}, best=math.nan, metric="",
                       epochs=None, checkpoint="", note=_FAILED)
        rows.append(row)
    rank = _rank_metric(rows)
    rows.sort(key=lambda r: (r["note"] != "",
                             *(_lowest_first(r[rank]) if rank else ()),
                             *_lowest_first(r["best"]),
                             int(r["job"]) if r["job"].isdigit() else math.inf, r["job"]))
    return swept, rows


def write_sweep_summary(sweep_dir: str | Path,
                        since: float | None = None) -> tuple[Path, Path] | None:
    """Write ``summary.md`` and ``summary.csv`` of the sweep in ``sweep_dir`` (atomically; its
    jobs written at or after ``since``, when given); None when it holds no job folder."""
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        return None
    return _write_summary(sweep_dir, *sweep_rows(sweep_dir, since))


def _write_summary(sweep_dir: Path, swept: list[str],
                   rows: list[dict[str, Any]]) -> tuple[Path, Path] | None:
    if not rows:
        return None
    rank = _rank_metric(rows)
    metrics = sorted({r["metric"] for r in rows if r["metric"]})
    shown = rank if rank and metrics != [rank] else None  # else it is the "best" column
    cols = ["job", *swept, *([shown] if shown else []), "best", "metric", "epochs", "checkpoint",
            "note"]

    def cell(v: Any) -> str:
        if isinstance(v, float):
            return "-" if math.isnan(v) else f"{v:.4f}"
        return "" if v is None else str(v)

    failed = sum(bool(r["note"]) for r in rows)
    order = (f"lowest {rank or ' / '.join(metrics)} first" if metrics
             else "none wrote metrics")
    md = [f"# Sweep {sweep_dir.name}: {len(rows)} job{'s' if len(rows) != 1 else ''}"
          + (f", {failed} without metrics" if failed and metrics else "") + f", {order}", ""]
    if shown:
        md += [f"`{shown}`: median validation error in degrees at each job's best checkpoint "
               f"(comparable across loss weights); `best`: that checkpoint's "
               f"{' / '.join(metrics)}.", ""]
    md += ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    md += ["| " + " | ".join(cell(r.get(c)) for c in cols) + " |" for r in rows]
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(cols)
    w.writerows([[cell(r.get(c)) for c in cols] for r in rows])
    return (atomic_write_text(sweep_dir / "summary.md", "\n".join(md) + "\n"),
            atomic_write_text(sweep_dir / "summary.csv", buf.getvalue()))


class SweepSummary(Callback):
    """Hydra callback: :func:`write_sweep_summary` of this sweep's jobs when a ``-m`` run
    ends; exit status 1 when a job wrote no metrics."""

    def __init__(self) -> None:
        self.started: float | None = None

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        self.started = time.time()

    def on_multirun_end(self, config: Any, **kwargs: Any) -> None:
        sweep_dir = Path(str(config.hydra.sweep.dir))
        if not sweep_dir.is_dir():
            return
        since = None if self.started is None else self.started - _CLOCK_SLACK_S
        swept, rows = sweep_rows(sweep_dir, since)
        paths = _write_summary(sweep_dir, swept, rows)
        if not paths:
            return
        print(f"sweep summary: {paths[0]}")
        failed = [r["job"] for r in rows if r["note"]]
        if failed:
            print(f"posernet-train: error: {len(failed)} job(s) of the sweep wrote no "
                  f"metrics.json (failed or interrupted): {', '.join(failed)}; see {paths[0]}",
                  file=sys.stderr)
            raise SystemExit(1)

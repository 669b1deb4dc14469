"""The table across a sweep's jobs (posernet.cli.sweep), on job folders written here."""

from __future__ import annotations

import json
from pathlib import Path

from posernet.cli.sweep import sweep_rows, write_sweep_summary


def _job(root: Path, name: str, overrides: list[str], best: float | None) -> None:
    job = root / name
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    if best is not None:
        (job / "metrics.json").write_text(json.dumps(
            {"optimized_metric": "val/loss", "best": best, "epochs": 3,
             "best_checkpoint": str(job / "best.ckpt")}))


def test_rows_best_first_swept_keys_only_failed_jobs_kept(tmp_path: Path) -> None:
    common = "data.root=/d"
    _job(tmp_path, "0_depth=2", [common, "model.net.depth=2"], 0.5)
    _job(tmp_path, "1_depth=3", [common, "model.net.depth=3"], 0.25)
    _job(tmp_path, "2_depth=4", [common, "model.net.depth=4"], None)  # failed
    _job(tmp_path, "10_depth=5", [common, "model.net.depth=5"], 0.75)
    (tmp_path / ".submitit").mkdir()  # not a job
    swept, rows = sweep_rows(tmp_path)
    assert swept == ["model.net.depth"]  # data.root is the same everywhere
    assert [r["job"] for r in rows] == ["1", "0", "10", "2"]
    assert rows[-1]["note"].startswith("no metrics.json")
    md, csv = write_sweep_summary(tmp_path)
    text = md.read_text()
    assert "| 1 | 3 | 0.2500 | val/loss | 3 |" in text and "| 2 | 4 | - |" in text
    header = csv.read_text().splitlines()[0]
    assert header == "job,model.net.depth,best,metric,epochs,checkpoint,note"
    assert write_sweep_summary(tmp_path / "nope") is None

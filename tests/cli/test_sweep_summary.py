"""The table across a sweep's jobs (posernet.cli.sweep), on job folders written here."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from posernet.cli.sweep import SweepSummary, sweep_rows, write_sweep_summary
from posernet.conf import compose, path_safe


def _job(root: Path, name: str, overrides: list[str], best: float | None,
         metric: str = "val/loss", **at_best: float) -> Path:
    job = root / name
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    if best is not None:
        (job / "metrics.json").write_text(json.dumps(
            {"optimized_metric": metric, "best": best, "epochs": 3,
             "best_checkpoint": str(job / "best.ckpt"),
             "best_metrics": {f"val/{k}": v for k, v in at_best.items()}}))
    return job


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


def test_ranked_by_the_rotation_error_not_the_loss(tmp_path: Path) -> None:
    """val/loss depends on model.loss.alpha: the table ranks by the validation rotation error
    at each job's best checkpoint and shows the loss next to it."""
    _job(tmp_path, "0_a=0.1", ["model.loss.alpha=0.1"], 0.2, rot_err_deg=9.0, loss=0.2)
    _job(tmp_path, "1_a=1.0", ["model.loss.alpha=1.0"], 0.9, rot_err_deg=3.0, loss=0.9)
    _job(tmp_path, "2_a=0.5", ["model.loss.alpha=0.5"], None)
    _, rows = sweep_rows(tmp_path)
    assert [r["job"] for r in rows] == ["1", "0", "2"]
    md, csv = write_sweep_summary(tmp_path)
    lines = md.read_text().splitlines()
    assert lines[0] == f"# Sweep {tmp_path.name}: 3 jobs, 1 without metrics, lowest " \
                       "val/rot_err_deg first"
    assert "| 1 | 1.0 | 3.0000 | 0.9000 | val/loss | 3 |" in md.read_text()
    assert csv.read_text().splitlines()[0] == (
        "job,model.loss.alpha,val/rot_err_deg,best,metric,epochs,checkpoint,note")


def test_heading_names_the_metric_or_says_none_wrote_any(tmp_path: Path) -> None:
    _job(tmp_path, "0_x", ["model.net.depth=1"], None)
    _job(tmp_path, "1_x", ["model.net.depth=2"], None)
    heading = write_sweep_summary(tmp_path)[0].read_text().splitlines()[0]
    assert heading == f"# Sweep {tmp_path.name}: 2 jobs, none wrote metrics"
    assert "best best" not in heading


def test_job_folders_found_at_any_depth(tmp_path: Path) -> None:
    """A job folder is one with a Hydra record; a hydra.sweep.subdir with a "/" nests it."""
    _job(tmp_path, "kp-d2/seed0", ["model.net.depth=2"], 0.5, metric="val/rot_err_deg",
         rot_err_deg=0.5)
    _job(tmp_path, "kp-d3/seed0", ["model.net.depth=3"], 0.25, metric="val/rot_err_deg",
         rot_err_deg=0.25)
    _, rows = sweep_rows(tmp_path)
    assert [(r["job"], r["note"]) for r in rows] == [("kp-d3/seed0", ""), ("kp-d2/seed0", "")]
    # the rank metric is the optimised one: no second column of the same numbers
    assert "| job | model.net.depth | best | metric |" in write_sweep_summary(
        tmp_path)[0].read_text()


def test_a_value_with_a_slash_names_one_folder() -> None:
    """Job folders are named by the job's overrides with path separators replaced, so
    ``optimized_metric=val/rot_err_deg`` does not nest the job's folder."""
    assert path_safe("a=1,optimized_metric=val/rot_err_deg") == \
        "a=1,optimized_metric=val_rot_err_deg"
    cfg = compose("train", ["optimized_metric=val/rot_err_deg"], return_hydra_config=True)
    from omegaconf import open_dict, read_write

    with read_write(cfg), open_dict(cfg):
        cfg.hydra.job.num = 3
        cfg.hydra.job.override_dirname = "model.loss.alpha=0.5,optimized_metric=val/rot_err_deg"
    assert cfg.hydra.sweep.subdir == "3_model.loss.alpha=0.5,optimized_metric=val_rot_err_deg"


def test_callback_exits_1_when_a_job_of_the_sweep_failed(tmp_path: Path, capsys) -> None:
    config = SimpleNamespace(hydra=SimpleNamespace(sweep=SimpleNamespace(dir=str(tmp_path))))
    old = _job(tmp_path, "7_old", ["model.net.depth=9"], None)  # an earlier sweep's job
    stamp = time.time() - 3600
    for f in [old / ".hydra", *(old / ".hydra").iterdir()]:
        os.utime(f, (stamp, stamp))
    callback = SweepSummary()
    callback.on_multirun_start(config)
    _job(tmp_path, "0_a", ["model.net.depth=1"], 0.5, rot_err_deg=2.0)
    callback.on_multirun_end(config)  # this sweep's jobs all finished
    assert "sweep summary:" in capsys.readouterr().out
    assert "| 7 |" not in (tmp_path / "summary.md").read_text()
    _job(tmp_path, "1_b", ["model.net.depth=2"], None)
    with pytest.raises(SystemExit) as exc:
        callback.on_multirun_end(config)
    assert exc.value.code == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("posernet-train: error: 1 job(s) of the sweep wrote no metrics.json")
    assert err.count("\n") == 0 and ": 1;" in err

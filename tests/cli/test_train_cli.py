"""End-to-end: Hydra training (fast_dev_run, checkpoints, resume, sweep) and posernet-eval."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

pytest.importorskip(
    "posernet.data.datamodule",
    reason="posernet.data.datamodule is not importable")

from hydra import compose, initialize_config_dir

from posernet.cli import CONFIG_DIR
from posernet.cli.train import train
from posernet.testing import write_random_dataset

pytestmark = [pytest.mark.slow,
              pytest.mark.filterwarnings("ignore::UserWarning", "ignore::DeprecationWarning")]

SCENES = ("chess", "fire")
QUIET = ["trainer.enable_progress_bar=false", "trainer.enable_model_summary=false",
         "num_threads=1", "data.batch_size=4"]


def write_dataset(root: Path, per_scene: dict[str, int], seed: int = 0) -> Path:
    """A small dataset in ``posernet-make-data``'s layout (manifest + small/<split>/<scene>.pt)."""
    return write_random_dataset(root, per_scene, SCENES, seed)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("data"), {"train": 8, "val": 3, "test": 3})


def compose_train(overrides: list[str]):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose(config_name="train", overrides=overrides)


def env() -> dict[str, str]:
    return {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0"}


@pytest.fixture(scope="module")
def trained(dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One 2-epoch training run; returns its output folder."""
    out = tmp_path_factory.mktemp("run")
    cfg = compose_train([f"data.root={dataset}", f"out_dir={out}", "trainer.max_epochs=2",
                         *QUIET])
    best = train(cfg)
    assert isinstance(best, float) and best == best  # finite, not NaN
    return out


def test_fast_dev_run(dataset: Path, tmp_path: Path) -> None:
    cfg = compose_train([f"data.root={dataset}", f"out_dir={tmp_path}",
                         "trainer.fast_dev_run=true", "model.net.depth=1", *QUIET])
    assert cfg.model.loss.alpha == 0.1 and cfg.trainer.accelerator == "cpu"
    value = train(cfg)
    assert isinstance(value, float)


def test_train_on_a_list_of_datasets(dataset: Path, tmp_path: Path) -> None:
    """data.root=[A,B] (Hydra list syntax) trains on both datasets' training graphs."""
    other = write_dataset(tmp_path / "other", {"train": 4, "val": 1, "test": 1}, seed=1)
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "posernet.cli.train", f"data.root=[{dataset},{other}]",
         f"hydra.run.dir={out}", "trainer.max_epochs=1", "test_after_training=false", *QUIET],
        capture_output=True, text=True, env=env(), timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    ckpt = torch.load(out / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert ckpt["datamodule_hyper_parameters"]["root"] == [str(dataset), str(other)]
    # 2 scenes x (8 + 4) training graphs, batch 4: 6 steps in the one epoch
    assert ckpt["global_step"] == 6


def test_checkpoints_and_resume(trained: Path, dataset: Path, tmp_path: Path) -> None:
    ckpts = trained / "checkpoints"
    assert (ckpts / "best.ckpt").is_file() and (ckpts / "last.ckpt").is_file()
    summary = json.loads((trained / "metrics.json").read_text())
    assert summary["optimized_metric"] == "val/loss" and summary["epochs"] == 2
    assert summary["num_parameters"] > 1000
    assert (trained / "logs" / "metrics.csv").is_file()
    # Resume from last.ckpt for one more epoch.
    cfg = compose_train([f"data.root={dataset}", f"out_dir={tmp_path}", "trainer.max_epochs=3",
                         f"ckpt_path={ckpts / 'last.ckpt'}", *QUIET])
    train(cfg)
    resumed = json.loads((tmp_path / "metrics.json").read_text())
    assert resumed["epochs"] == 3
    state = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=True)
    assert state["epoch"] == 2 and state["global_step"] > 0


def test_multirun_sweep(dataset: Path, tmp_path: Path) -> None:
    sweep = tmp_path / "sweep"
    cmd = [sys.executable, "-m", "posernet.cli.train", "-m", "model.net.depth=1,2",
           "model.loss.alpha=0.1,0.5", f"data.root={dataset}", "trainer.max_epochs=1",
           f"hydra.sweep.dir={sweep}", *QUIET]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env())
    assert res.returncode == 0, res.stderr[-3000:]
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert len(jobs) == 4, [p.name for p in jobs]
    # One folder per job: "<job number>_<overrides>" (noisy keys such as num_threads excluded).
    assert {p.name.split("_", 1)[0] for p in jobs} == {"0", "1", "2", "3"}
    names = {p.name.split("_", 1)[1] for p in jobs}
    assert names == {f"data.batch_size=4,model.loss.alpha={a},model.net.depth={d},"
                     "trainer.max_epochs=1" for a in ("0.1", "0.5") for d in (1, 2)}
    for job in jobs:
        assert (job / "checkpoints" / "last.ckpt").is_file()
        assert json.loads((job / "metrics.json").read_text())["best"] is not None
    # one table across the jobs with the swept values, ranked by the validation rotation error
    # at each job's best checkpoint (val/loss depends on alpha), the loss beside it
    assert "sweep summary:" in res.stdout
    lines = (sweep / "summary.md").read_text().splitlines()
    assert lines[0].endswith(": 4 jobs, lowest val/rot_err_deg first")
    assert lines[4] == ("| job | model.loss.alpha | model.net.depth | val/rot_err_deg | best | "
                        "metric | epochs | checkpoint | note |")
    rot = [float(ln.split("|")[4]) for ln in lines[6:]]
    assert len(rot) == 4 and rot == sorted(rot)
    assert {ln.split("|")[6].strip() for ln in lines[6:]} == {"val/loss"}
    assert (sweep / "summary.csv").read_text().startswith("job,model.loss.alpha,")
    for job in jobs:  # the rotation error of the best checkpoint's epoch
        m = json.loads((job / "metrics.json").read_text())
        assert m["best_metrics"]["val/loss"] == m["best"]
        assert "val/rot_err_deg" in m["best_metrics"]


def test_multirun_sweep_optimising_a_metric_with_a_slash(dataset: Path, tmp_path: Path) -> None:
    """optimized_metric=val/rot_err_deg: one folder per job all the same (the "/" of the value
    is not a subfolder), every job in the summary, exit status 0."""
    sweep = tmp_path / "sweep"
    cmd = [sys.executable, "-m", "posernet.cli.train", "-m", "model.loss.alpha=0.1,0.5",
           "optimized_metric=val/rot_err_deg", f"data.root={dataset}", "trainer.max_epochs=1",
           f"hydra.sweep.dir={sweep}", *QUIET]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env())
    assert res.returncode == 0, res.stderr[-3000:]
    jobs = sorted(p.name for p in sweep.iterdir() if p.is_dir())
    assert jobs == [f"{k}_data.batch_size=4,model.loss.alpha={a},"
                    "optimized_metric=val_rot_err_deg,trainer.max_epochs=1"
                    for k, a in enumerate(("0.1", "0.5"))]
    text = (sweep / "summary.md").read_text()
    assert text.splitlines()[0].endswith(": 2 jobs, lowest val/rot_err_deg first")
    assert "failed" not in text and "error" not in res.stderr


def test_eval_on_the_datamodule_test_split(trained: Path, dataset: Path, tmp_path: Path) -> None:
    from posernet.cli.evaluate import evaluate

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(config_name="eval", overrides=[
            f"ckpt_path={trained / 'checkpoints' / 'best.ckpt'}", f"data.root={dataset}",
            f"out_dir={tmp_path}", "data.estimate=bb", "sync=eig_se3"])
    res = evaluate(cfg)
    rows = res["table"].rows
    assert [r.labels for r in rows] == [("BB", "Initial"), ("BB", "PoserNet")]
    assert rows[0].cells["rot"].count == 6  # 2 scenes x 3 test graphs
    assert (tmp_path / "table.md").is_file() and (tmp_path / "table.csv").is_file()
    # With a motion-averaging backend the absolute-pose table is written too.
    abs_rows = res["abs_table"].rows
    assert [r.labels[1] for r in abs_rows] == ["eig_se3", "eig_se3 + PoserNet"]
    assert abs_rows[0].cells["trans"].count == 6
    assert (tmp_path / "abs_table.md").is_file() and (tmp_path / "abs_table.csv").is_file()


def test_eval_cli(trained: Path, dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "eval"
    cmd = [sys.executable, "-m", "posernet.cli.evaluate",
           f"ckpt_path={trained / 'checkpoints' / 'best.ckpt'}",
           f"graphs={dataset / 'small' / 'test'}", "estimate=kp",
           f"hydra.run.dir={out}", "num_threads=1"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env())
    assert res.returncode == 0, res.stderr[-3000:]
    assert "| KP | Initial |" in res.stdout and "| KP | PoserNet |" in res.stdout
    assert (out / "table.md").read_text().count("| KP |") == 2
    csv_lines = (out / "table.csv").read_text().splitlines()
    assert csv_lines[0].startswith("input,stage,rot_lt3") and len(csv_lines) == 3
    assert csv_lines[1].endswith(",6,1")  # 6 test graphs (2 scenes x 3), one run


def test_eval_cli_rejects_foreign_checkpoint(dataset: Path, tmp_path: Path) -> None:
    bad = tmp_path / "other.ckpt"
    torch.save({"state_dict": {}, "hparams_name": "kwargs"}, bad)
    cmd = [sys.executable, "-m", "posernet.cli.evaluate", f"ckpt_path={bad}",
           f"data.root={dataset}", f"hydra.run.dir={tmp_path / 'eval'}"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env())
    assert res.returncode != 0
    assert "posernet-eval: error:" in res.stderr and "not a PoserNet checkpoint" in res.stderr
    assert "Traceback" not in res.stderr
    assert not (tmp_path / "eval" / "table.md").exists()


def test_init_from_starts_a_new_run_from_the_weights(trained: Path, dataset: Path,
                                                     tmp_path: Path) -> None:
    """init_from=CKPT: the first step starts from CKPT's network (not a fresh init), at epoch 0
    with a fresh optimiser; the run writes its own checkpoints."""
    from posernet.cli.train import init_weights
    from posernet.lit import PoserNetModule, load_posernet_checkpoint

    source = trained / "checkpoints" / "last.ckpt"
    module = PoserNetModule()
    init_weights(module, str(source))
    want = load_posernet_checkpoint(source).model.state_dict()
    got = module.model.state_dict()
    assert want.keys() == got.keys()
    assert all(torch.equal(want[k], got[k]) for k in want)
    cfg = compose_train([f"data.root={dataset}", f"out_dir={tmp_path}", "trainer.max_epochs=1",
                         f"init_from={source}", *QUIET])
    train(cfg)
    state = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=True)
    assert state["epoch"] == 0  # a new run: one epoch, not the source's third
    # Adam's step counter restarted: one epoch of 2 scenes x 8 graphs at batch 4 = 4 steps
    steps = {int(v["step"]) for v in state["optimizer_states"][0]["state"].values()}
    assert steps == {4}


def test_init_from_the_shipped_checkpoint_needs_its_network(dataset: Path,
                                                            tmp_path: Path) -> None:
    """init_from=shipped with the default (smaller) model.net is one error naming what
    differs, before training; with the shipped network's settings it loads."""
    from posernet.checkpoints import CheckpointError, default_checkpoint, read_checkpoint
    from posernet.cli.train import init_weights
    from posernet.lit import PoserNetModule

    with pytest.raises(CheckpointError, match=r"differs from model.net in depth=3 "
                                              r"\(configured 2\)") as exc:
        init_weights(PoserNetModule(), "shipped")
    # the message ends with the overrides that make it fit: pasted, they load
    hint = str(exc.value).split("; add ", 1)[1].split()
    fixed = {k.removeprefix("model.net."): v for k, v in (h.split("=") for h in hint)}
    net = read_checkpoint(default_checkpoint())["hyper_parameters"]["net"]
    assert {k: str(net[k]) for k in fixed} == fixed
    module = PoserNetModule(net=dict(net))
    assert init_weights(module, "shipped") == default_checkpoint()
    proc = subprocess.run(
        [sys.executable, "-m", "posernet.cli.train", f"data.root={dataset}",
         f"hydra.run.dir={tmp_path / 'run'}", "init_from=shipped", *QUIET],
        capture_output=True, text=True, env=env(), timeout=300)
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines()[-1].startswith(
        "posernet-train: error: init_from=") and "differs from model.net" in proc.stderr
    assert not (tmp_path / "run" / "checkpoints").exists()


@pytest.mark.parametrize("args, message", [
    (["init_from=/nonexistent/model.ckpt"], "init_from=/nonexistent/model.ckpt: checkpoint not"),
    (["init_from=shipped", "ckpt_path=/x/last.ckpt"], "give one"),
])
def test_init_from_bad_values(dataset: Path, tmp_path: Path, args: list[str],
                              message: str) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "posernet.cli.train", f"data.root={dataset}",
         f"hydra.run.dir={tmp_path / 'run'}", *args, *QUIET],
        capture_output=True, text=True, env=env(), timeout=300)
    assert proc.returncode == 1, proc.stderr[-2000:]
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("posernet-train: error:") and message in last


def test_resume_continues_the_run_it_names(dataset: Path, tmp_path: Path) -> None:
    """``ckpt_path=RUN/checkpoints/last.ckpt`` alone, from another folder: the run's own data
    and model settings (not the defaults); a finished run keeps its recorded metrics."""
    run = tmp_path / "run"
    first = subprocess.run(
        [sys.executable, "-m", "posernet.cli.train", f"data.root={dataset}",
         f"hydra.run.dir={run}", "trainer.max_epochs=1", "model.net.depth=1", *QUIET],
        capture_output=True, text=True, env=env(), timeout=300, cwd=tmp_path)
    assert first.returncode == 0, first.stderr[-2000:]
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    last = run / "checkpoints" / "last.ckpt"
    again = subprocess.run(
        [sys.executable, "-m", "posernet.cli.train", f"ckpt_path={last}",
         "trainer.max_epochs=2"], capture_output=True, text=True, env=env(), timeout=300,
        cwd=elsewhere)
    assert again.returncode == 0, again.stderr[-2000:]
    assert (f"continuing {run} with its own settings: data.root={dataset}" in again.stderr
            and "model.net.depth=1" in again.stderr)
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["epochs"] == 2 and metrics["final_metrics"]
    # once more: finished, nothing trained, the recorded metrics stay
    done = subprocess.run(
        [sys.executable, "-m", "posernet.cli.train", f"ckpt_path={last}"],
        capture_output=True, text=True, env=env(), timeout=300, cwd=elsewhere)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "the run had finished" in done.stdout
    assert json.loads((run / "metrics.json").read_text()) == metrics

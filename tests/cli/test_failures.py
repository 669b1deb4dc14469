"""Every posernet-* command on its typical bad inputs, as a user runs it (a subprocess): exit
status 1, one last line ``posernet-<cmd>: error: ...`` saying what is wrong, no traceback, and
nothing written where the output would go. Plus Ctrl-C: exit status 130, one line, and data
that ``resume=true`` finishes.

The rows run two at a time (each is mostly interpreter and torch start-up).
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

from posernet.checkpoints import default_checkpoint

pytestmark = pytest.mark.slow

NO_CUDA = not torch.cuda.is_available()
SCRIPTS = {"make-data": "make_data", "train": "train", "eval": "evaluate", "refine": "refine",
           "demo": "demo", "reconstruct": "reconstruct"}


@dataclass(frozen=True)
class Row:
    cmd: str  # posernet-<cmd>
    args: str  # {data} {ckpt} {tmp} {out} {run} are filled in
    message: str  # regex on the text after "posernet-<cmd>: error: "
    #: the error is found by a loader once the command runs, after Hydra made its run folder
    #: (hydra.run.dir); without it stderr is that one line and nothing at all is written
    started: bool = False

    def __str__(self) -> str:
        return f"{self.cmd}: {self.args}"


CUDA = "device=cuda but CUDA is not available"

ROWS = [
    # make-data
    Row("make-data", "dataset=tiny workers=abc out_dir={out}",
        r"workers: 'abc' is not an integer >= 1$"),
    Row("make-data", "dataset=tiny dataset.small.graph_size=1 out_dir={out}",
        r"dataset\.small\.graph_size: must be >= 2, got 1"),
    Row("make-data", "source=flickr out_dir={out}",
        r"source: 'flickr' is not one of synthetic, sevenscenes$"),
    Row("make-data", "source=sevenscenes out_dir={out}", r"needs root=DIR"),
    Row("make-data", "source=sevenscenes root={tmp}/nope out_dir={out}", r"does not exist"),
    Row("make-data", "dataset=tiny out_dir=/proc/posernet-x",
        r"out_dir: '/proc/posernet-x' is not a writable folder"),
    # train
    Row("train", "data.root={data} model.net.depth=abc hydra.run.dir={run}",
        r"model\.net\.depth: 'abc' is not an integer >= 1$"),
    Row("train", "data.root={data} model.loss.alpha=abc hydra.run.dir={run}",
        r"model\.loss\.alpha: 'abc' is not a number >= 0$"),
    Row("train", "data.root={data} model.optimizer.lr=-1 hydra.run.dir={run}",
        r"model\.optimizer\.lr: -1 is not a number > 0$"),
    Row("train", "data.root={data} sync=nope hydra.run.dir={run}",
        r"sync: 'nope' is not one of eig_se3, gtsam, learned, none, rotation_translation$"),
    Row("train", "data.root={tmp}/nope hydra.run.dir={run}",
        r"dataset directory not found: .*/nope", started=True),
    Row("train", "data.root={data} out_dir=/proc/posernet-x hydra.run.dir={run}",
        r"out_dir: '/proc/posernet-x' is not a writable folder"),
    Row("train", "data.root={data} trainer=gpu hydra.run.dir={run}",
        r"trainer\.accelerator=gpu but CUDA is not available$"),
    Row("train", "data.root={data} trainer.devices=0 hydra.run.dir={run}",
        r"trainer\.devices: 0 is not an integer >= 1"),
    Row("train", "data.root={data} trainer.accelerator=tpu hydra.run.dir={run}",
        r"trainer\.accelerator: 'tpu' is not one of auto, cpu, gpu, cuda, mps$"),
    Row("train", "data.root={data} +trainer.precision=abc hydra.run.dir={run}",
        r"trainer\.precision: 'abc' is not one of 64, 32"),
    Row("train", "data.root={data} optimized_metric=val/rot_err hydra.run.dir={run}",
        r"optimized_metric: 'val/rot_err' is not a metric the training logs"),
    Row("train", "data.root={data} trainer.max_epochs=0 hydra.run.dir={run}",
        r"trainer\.max_epochs: 0 is not an integer >= 1 \(or -1: no limit\)"),
    Row("train", "data.root={data} +foo=1 hydra.run.dir={run}",
        r"foo: no such option of posernet-train \(see posernet-train --help\)$"),
    Row("train", "data.root={data} seed=abc hydra.run.dir={run}",
        r"^seed: 'abc' is not an integer >= 0$"),
    # eval
    Row("eval", "data.root={data} out_dir={out} hydra.run.dir={run}",
        r"ckpt_path: a value is required"),
    Row("eval", "ckpt_path={ckpt} data.root={data} batch_size=0 out_dir={out} "
        "hydra.run.dir={run}", r"batch_size: 0 is not an integer >= 1$"),
    Row("eval", "ckpt_path={ckpt} data.root={data} sync=eig_se3 sync.scale=bogus out_dir={out} "
        "hydra.run.dir={run}", r"sync\.scale: 'bogus' is not one of unit, given, oracle, free$"),
    Row("eval", "ckpt_path={tmp}/nope.ckpt data.root={data} out_dir={out} hydra.run.dir={run}",
        r"checkpoint not found: .*/nope\.ckpt", started=True),
    Row("eval", "ckpt_path={ckpt} data.root={data} out_dir=/proc/posernet-x "
        "hydra.run.dir={run}", r"out_dir: '/proc/posernet-x' is not a writable folder"),
    Row("eval", "ckpt_path={ckpt} data.root={data} device=cuda out_dir={out} "
        "hydra.run.dir={run}", CUDA),
    # refine
    Row("refine", "output={out}/r.json hydra.run.dir={run}", r"input: a value is required"),
    Row("refine", "input={tmp}/missing.json output={out}/r.json hydra.run.dir={run}",
        r"graph JSON not found: .*/missing\.json", started=True),
    Row("refine", "input={data}/small/test estimate=xx output={out}/r.json hydra.run.dir={run}",
        r"estimate: 'xx' is not one of kp, bb, free, gt or null$"),
    Row("refine", "input={data}/small/test num_threads=0 output={out}/r.json "
        "hydra.run.dir={run}", r"num_threads: 0 is not an integer >= 1 or null$"),
    Row("refine", "input={data}/small/test output=/proc/posernet-x/refined.json "
        "hydra.run.dir={run}",
        r"output: '/proc/posernet-x/refined\.json' is not a writable file"),
    Row("refine", "input={data}/small/test device=cuda output={out}/r.json hydra.run.dir={run}",
        CUDA),
    # demo
    Row("demo", "dataset=tiny images.frames=abc out_dir={out}",
        r"images\.frames: 'abc' is not an integer >= 2$"),
    Row("demo", "dataset=tiny estimate=xx out_dir={out}", r"estimate: 'xx' is not one of kp, bb$"),
    Row("demo", "dataset=tiny ckpt_path={tmp}/nope.ckpt out_dir={out}",
        r"checkpoint not found: .*/nope\.ckpt"),
    Row("demo", "dataset=tiny out_dir=/proc/posernet-x",
        r"out_dir: '/proc/posernet-x' is not a writable folder"),
    Row("demo", "dataset=tiny device=cuda out_dir={out}", CUDA),
    # reconstruct
    Row("reconstruct", "intrinsics=585,585,320,240 out_dir={out}", r"images: a value is required"),
    Row("reconstruct", "images={tmp}/photos intrinsics=585,585,320,240 out_dir={out}",
        r"image folder not found"),
    Row("reconstruct", "images={tmp} intrinsics=585,585,320,240 workers=-2 out_dir={out}",
        r"workers: -2 is not an integer >= 0$"),
    Row("reconstruct", "images={tmp} intrinsics=585,585,320,240 matcher=orb out_dir={out}",
        r"matcher: 'orb' is not one of auto, sift, sift_xfeat, xfeat, xfeat_lighterglue$"),
    Row("reconstruct", "images={tmp} intrinsics=585,585,320,240 out_dir=/proc/posernet-x",
        r"out_dir: '/proc/posernet-x' is not a writable folder"),
    Row("reconstruct", "images={tmp} intrinsics=585,585,320,240 device=cuda out_dir={out}",
        CUDA),
]


def _needs_cuda_absent(row: Row) -> bool:
    return "CUDA is not available" in row.message


def _run(args: list[str], **kw) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "HYDRA_FULL_ERROR": "0", "OMP_NUM_THREADS": "1"}
    return subprocess.run(args, capture_output=True, text=True, timeout=300, env=env, **kw)


def _cli(cmd: str) -> list[str]:
    return [sys.executable, "-m", f"posernet.cli.{SCRIPTS[cmd]}"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("data") / "tiny"
    r = _run([*_cli("make-data"), "dataset=tiny", f"out_dir={out}", "progress=false"])
    assert r.returncode == 0, r.stderr
    return out


@pytest.fixture(scope="module")
def results(request: pytest.FixtureRequest, dataset: Path,
            tmp_path_factory: pytest.TempPathFactory) -> dict[int, tuple]:
    """Run the selected rows, two at a time; row index -> (result, paths)."""
    wanted = sorted({item.callspec.params["k"] for item in request.session.items
                     if item.module is request.module and hasattr(item, "callspec")
                     and "k" in item.callspec.params})

    def one(k: int) -> tuple:
        row = ROWS[k]
        tmp = tmp_path_factory.mktemp(f"row{k}")
        paths = {"data": dataset, "ckpt": default_checkpoint(), "tmp": tmp,
                 "out": tmp / "out", "run": tmp / "run"}
        args = row.args.format(**paths).split()
        return _run([*_cli(row.cmd), *args], cwd=tmp), paths

    with ThreadPoolExecutor(max_workers=2) as pool:
        return dict(zip(wanted, pool.map(one, wanted), strict=True))


@pytest.mark.parametrize("k", range(len(ROWS)), ids=[str(r) for r in ROWS])
def test_bad_input_is_one_line_exit_1_and_writes_nothing(k: int, results) -> None:
    row = ROWS[k]
    if _needs_cuda_absent(row) and not NO_CUDA:
        pytest.skip("CUDA is available here")
    r, paths = results[k]
    prefix = f"posernet-{row.cmd}: error: "
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 1, (r.stdout[-2000:], r.stderr[-2000:])
    assert "Traceback" not in r.stderr, r.stderr
    assert lines and lines[-1].startswith(prefix), r.stderr
    assert re.search(row.message, lines[-1][len(prefix):]), lines[-1]
    assert not paths["out"].exists(), sorted(paths["out"].rglob("*"))
    # a run folder holding only Hydra's log is removed after a user error too
    assert not paths["run"].exists(), sorted(paths["run"].rglob("*"))
    if not row.started:  # found before any work: that line is all
        assert len(lines) == 1, r.stderr
        assert list(paths["tmp"].iterdir()) == []  # the working folder too


def test_every_command_has_rows() -> None:
    assert {r.cmd for r in ROWS} == set(SCRIPTS)
    for cmd in SCRIPTS:
        assert sum(r.cmd == cmd for r in ROWS) >= 5, cmd


# ------------------------------------------------------------------------- Ctrl-C


def _interrupt_when(cmd: list[str], ready, cwd: Path) -> subprocess.CompletedProcess[str]:
    """Start ``cmd`` in its own process group, send SIGINT to the group (what Ctrl-C does in
    a terminal) once ``ready()`` holds, and wait."""
    from helpers import as_from_a_terminal

    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         cwd=cwd, start_new_session=True,
                         env={**os.environ, "OMP_NUM_THREADS": "1"},
                         preexec_fn=as_from_a_terminal)
    deadline = time.monotonic() + 120
    while not ready() and p.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    if p.poll() is None:
        os.killpg(p.pid, signal.SIGINT)
    out, err = p.communicate(timeout=120)
    return subprocess.CompletedProcess(cmd, p.returncode, out, err)


def test_make_data_ctrl_c_is_one_line_and_resume_finishes(dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "ds"
    cmd = [*_cli("make-data"), "dataset=tiny", f"out_dir={out}", "progress=false", "workers=1"]
    r = _interrupt_when(cmd, lambda: any(out.rglob("*.pt")), tmp_path)
    if r.returncode == 0:
        pytest.skip("the run finished before the interrupt")
    assert r.returncode == 130, r.stderr
    assert "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines() == [
        f"posernet-make-data: interrupted; the complete files in {out} are kept: run it again "
        f"with resume=true to finish"]
    assert not (out / "manifest.json").exists()  # not mistaken for a complete dataset

    r = _run([*cmd, "resume=true"])
    assert r.returncode == 0, r.stderr
    made = sorted(p.relative_to(out) for p in out.rglob("*.pt"))
    assert made == sorted(p.relative_to(dataset) for p in dataset.rglob("*.pt"))
    for rel in made:  # bit-identical to an uninterrupted run
        assert (out / rel).read_bytes() == (dataset / rel).read_bytes(), rel


def test_refine_writes_no_empty_log(dataset: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    r = _run([*_cli("refine"), f"input={dataset}/small/test", f"hydra.run.dir={run}",
              "sync=none"])
    assert r.returncode == 0, r.stderr
    assert (run / "refined.json").is_file()
    assert not list(run.glob("*.log"))


def test_train_error_after_start_is_the_only_output(tmp_path: Path) -> None:
    """An error found once training starts (a dataset folder that does not exist) is the one
    line on stderr: nothing before it on either stream (no "Seed set to 0")."""
    r = _run([*_cli("train"), f"data.root={tmp_path}/nope", f"hydra.run.dir={tmp_path}/run"],
             cwd=tmp_path)
    assert r.returncode == 1, r.stderr
    assert r.stdout == ""
    assert r.stderr.splitlines() == [
        f"posernet-train: error: dataset directory not found: {tmp_path}/nope"]

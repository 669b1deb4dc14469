"""Distributed data parallel training: two CPU processes (gloo) through the console script.

Regression test: DDP used to stop on the second optimiser step with "parameters that were not
used in producing the loss" (the last round's node MLP fed nothing). Each rank here takes two
steps (4 training graphs, 2 ranks, batch size 1).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

pytestmark = pytest.mark.slow

BIN = Path(sys.executable).parent


def run(cmd: list[str], cwd: Path, timeout: int = 180) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "1"}
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)


def test_two_process_cpu_ddp_training(tmp_path: Path) -> None:
    for tool in ("posernet-make-data", "posernet-train"):
        if not (BIN / tool).is_file():
            pytest.skip(f"console script {tool} is not installed next to {sys.executable}")
    data, out = tmp_path / "data", tmp_path / "run"
    made = run([str(BIN / "posernet-make-data"), "dataset=tiny", f"out_dir={data}",
                f"hydra.run.dir={tmp_path / 'make_data'}"], tmp_path)
    assert made.returncode == 0, made.stderr[-3000:]

    # The command shown in docs/architecture.md, "Scaling out" (plus quiet flags and paths).
    cmd = [str(BIN / "posernet-train"), "trainer=ddp", "trainer.devices=2",
           "trainer.accelerator=cpu", "trainer.max_epochs=1", f"data.root={data}",
           "data.batch_size=1", f"hydra.run.dir={out}",
           "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false"]
    res = run(cmd, tmp_path)
    log = res.stdout + res.stderr
    assert res.returncode == 0, log[-4000:]
    assert "not used in producing the loss" not in log
    assert "distributed_backend=gloo" in log and "Starting with 2 processes" in log

    last = torch.load(out / "checkpoints" / "last.ckpt", weights_only=True)
    assert (out / "checkpoints" / "best.ckpt").is_file()
    assert last["epoch"] == 0 and last["global_step"] >= 2  # the second step used to fail
    summary = json.loads((out / "metrics.json").read_text())
    assert summary["epochs"] == 1 and math.isfinite(summary["best"])

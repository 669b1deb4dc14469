"""Resuming ``posernet-train`` from ``RUN/checkpoints/last.ckpt`` continues the run in ``RUN``.

Regression test: a resumed run used to start a new timestamped folder, where ``best.ckpt`` and
``metrics.json`` only knew the epochs after the resume (a worse model than the true best left in
the old folder), because Lightning restores the best-so-far score only into the same folder.
"""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
import types
from pathlib import Path

import pytest
import torch

from posernet.cli.resume import relocation_callback, resume_overrides, run_dir_of_checkpoint

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning", "ignore::DeprecationWarning")

SCENES = ("chess", "fire")
QUIET = ["trainer.enable_progress_bar=false", "trainer.enable_model_summary=false",
         "data.batch_size=4"]


# --------------------------------------------------------------------------- fast checks


def test_resume_overrides(tmp_path: Path) -> None:
    run = tmp_path / "outputs" / "train" / "2024-01-01" / "12-00-00"
    (run / "checkpoints").mkdir(parents=True)
    last = run / "checkpoints" / "last.ckpt"
    last.write_bytes(b"")
    base = ["data.root=x", "trainer.max_epochs=5"]
    added = resume_overrides([*base, f"ckpt_path={last}"])[3:]
    assert added[0] == f'hydra.run.dir="{run.resolve()}"'
    assert added[1].startswith("hydra.output_subdir=.hydra/resume_") and len(added) == 2
    assert resume_overrides([f"++ckpt_path='{last}'"])[1] == added[0]  # quoted, ++ form
    assert run_dir_of_checkpoint(last) == run.resolve()
    # the user's own folder, sweeps, no or missing checkpoints: unchanged
    other = tmp_path / "elsewhere.ckpt"
    other.write_bytes(b"")
    for argv in ([f"ckpt_path={last}", "hydra.run.dir=somewhere"],
                 [f"ckpt_path={last}", "out_dir=somewhere"],
                 ["-m", f"ckpt_path={last}", "model.net.depth=1,2"],
                 base, ["ckpt_path=null"], ["ckpt_path=last"],
                 [f"ckpt_path={run / 'checkpoints' / 'missing.ckpt'}"],
                 [f"ckpt_path={other}"]):
        assert resume_overrides(argv) == argv, argv


def test_moved_run_folder_keeps_its_best_score(tmp_path: Path) -> None:
    """Lightning drops the best-so-far state when the folder's path changed (moved/copied
    run); the resume callback re-bases the saved paths so it is kept."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    old_dir, new_dir = tmp_path / "old" / "checkpoints", tmp_path / "new" / "checkpoints"
    saved = ModelCheckpoint(dirpath=old_dir, filename="best", monitor="val/loss")
    saved.best_model_score = torch.tensor(0.25)
    saved.best_model_path = saved.kth_best_model_path = str(old_dir / "best.ckpt")
    saved.best_k_models = {str(old_dir / "best.ckpt"): torch.tensor(0.25)}
    saved.kth_value = torch.tensor(0.25)

    def restored(relocate: bool) -> ModelCheckpoint:
        cb = ModelCheckpoint(dirpath=new_dir, filename="best", monitor="val/loss")
        checkpoint = {"callbacks": {cb.state_key: saved.state_dict()}}
        if relocate:
            trainer = types.SimpleNamespace(checkpoint_callbacks=[cb])
            relocation_callback(str(new_dir / "last.ckpt")).on_load_checkpoint(
                trainer, None, checkpoint)
        cb.load_state_dict(checkpoint["callbacks"][cb.state_key])
        return cb

    with pytest.warns(UserWarning, match="dirpath has changed"):
        assert restored(relocate=False).best_model_score is None  # what Lightning does alone
    cb = restored(relocate=True)
    assert float(cb.best_model_score) == 0.25
    assert cb.best_model_path == os.path.join(cb.dirpath, "best.ckpt")
    assert list(cb.best_k_models) == [cb.best_model_path]


# --------------------------------------------------------------------------- end to end


def write_dataset(root: Path, per_scene: dict[str, int], seed: int = 0) -> Path:
    """A small dataset in ``posernet-make-data``'s layout (manifest + small/<split>/<scene>.pt)."""
    from posernet.testing import write_random_dataset

    return write_random_dataset(root, per_scene, SCENES, seed, rot_noise_deg=20.0)


def train_cli(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "posernet.cli.train", *args, *QUIET]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "1"}
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


def best_state(path: Path) -> dict:
    """The state of the monitored ModelCheckpoint callback saved in a checkpoint."""
    ckpt = torch.load(path, weights_only=False)
    (state,) = [v for k, v in ckpt["callbacks"].items()
                if k.startswith("ModelCheckpoint") and v.get("monitor")]
    return state


def val_losses(run: Path) -> dict[int, float]:
    with (run / "logs" / "metrics.csv").open(newline="") as f:
        return {int(float(r["epoch"])): float(r["val/loss"]) for r in csv.DictReader(f)
                if r.get("val/loss")}


@pytest.mark.slow
def test_resume_continues_the_run_and_keeps_the_best(tmp_path: Path) -> None:
    data = write_dataset(tmp_path / "data", {"train": 6, "val": 3, "test": 1})
    first = train_cli([f"data.root={data}", "trainer.max_epochs=1"], tmp_path)
    assert first.returncode == 0, first.stderr[-3000:]
    (run,) = (tmp_path / "outputs" / "train").glob("*/*")
    first_best = float(best_state(run / "checkpoints" / "best.ckpt")["best_model_score"])

    # resume with a relative path, as users type it
    ckpt = run.relative_to(tmp_path) / "checkpoints" / "last.ckpt"
    second = train_cli([f"data.root={data}", "trainer.max_epochs=2", f"ckpt_path={ckpt}"],
                       tmp_path)
    assert second.returncode == 0, second.stderr[-3000:]
    assert f"continuing the run in {run.resolve()}" in second.stdout
    assert [p.resolve() for p in (tmp_path / "outputs" / "train").glob("*/*")] == \
        [run.resolve()]  # still a single run folder

    assert torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)["epoch"] == 1
    losses = val_losses(run)  # the first run's epoch is still in the log
    assert sorted(losses) == [0, 1]
    assert losses[0] == pytest.approx(first_best)
    true_best = min(losses.values())
    summary = json.loads((run / "metrics.json").read_text())
    assert summary["epochs"] == 2 and summary["best"] == pytest.approx(true_best)
    assert Path(summary["best_checkpoint"]).parent == (run / "checkpoints").resolve()
    state = best_state(run / "checkpoints" / "best.ckpt")
    assert float(state["best_model_score"]) == pytest.approx(true_best)
    assert true_best <= first_best
    assert math.isfinite(summary["best"])
    # the original Hydra config stays; the resumed job's goes next to it
    assert "max_epochs: 1" in (run / ".hydra" / "config.yaml").read_text()
    assert any("max_epochs: 2" in c.read_text()
               for c in (run / ".hydra").glob("resume_*/config.yaml"))

    # Whichever epoch was better above, the best-so-far must survive a resume. Make it
    # unbeatable: as if the run so far had found an excellent model, last.ckpt now carries a
    # tiny best score. Kept, no later epoch replaces best.ckpt; lost, a real val/loss would.
    last = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)
    state = next(v for k, v in last["callbacks"].items()
                 if k.startswith("ModelCheckpoint") and v.get("monitor"))
    score, best_path = torch.tensor(1e-3), state["best_model_path"]
    best_epoch = torch.load(best_path, weights_only=False)["epoch"]
    state.update(best_model_score=score, kth_value=score, best_k_models={best_path: score})
    torch.save(last, run / "checkpoints" / "last.ckpt")
    third = train_cli([f"data.root={data}", "trainer.max_epochs=3", f"ckpt_path={ckpt}"],
                      tmp_path)
    assert third.returncode == 0, third.stderr[-3000:]
    assert json.loads((run / "metrics.json").read_text())["best"] == pytest.approx(1e-3)
    assert torch.load(best_path, weights_only=False)["epoch"] == best_epoch
    assert float(best_state(run / "checkpoints" / "last.ckpt")["best_model_score"]) == \
        pytest.approx(1e-3)
    assert sorted(val_losses(run)) == [0, 1, 2]

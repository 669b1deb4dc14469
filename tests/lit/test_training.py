"""posernet.lit.trainer: the one Trainer builder and its determinism policy, for every caller."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest
import torch
from helpers import posernet_train_callbacks
from hydra import compose, initialize_config_dir
from lightning.pytorch.callbacks import ModelCheckpoint

from posernet.cli import CONFIG_DIR
from posernet.lit.trainer import (
    build_trainer,
    determinism_policy,
    trainer_from_config,
)

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning", "ignore::DeprecationWarning")


@pytest.fixture(autouse=True)
def _restore_determinism():
    before = torch.are_deterministic_algorithms_enabled()
    warn_only = torch.is_deterministic_algorithms_warn_only_enabled()
    yield
    torch.use_deterministic_algorithms(before, warn_only=warn_only)


def test_policy_cpu_true_cuda_warn() -> None:
    assert determinism_policy("cpu") is True
    assert determinism_policy("gpu") == "warn" and determinism_policy("cuda") == "warn"
    assert determinism_policy("auto") == ("warn" if torch.cuda.is_available() else True)


def test_build_trainer_applies_the_policy_and_overrides(tmp_path: Path) -> None:
    build_trainer(max_epochs=1, default_root_dir=tmp_path, enable_progress_bar=False)
    assert torch.are_deterministic_algorithms_enabled()
    assert not torch.is_deterministic_algorithms_warn_only_enabled()
    build_trainer(max_epochs=1, deterministic="warn", default_root_dir=tmp_path)
    assert torch.is_deterministic_algorithms_warn_only_enabled()


def test_checkpoint_callbacks_best_and_last(tmp_path: Path) -> None:
    best, last = posernet_train_callbacks(tmp_path)
    assert isinstance(best, ModelCheckpoint) and best.monitor == "val/loss"
    assert last.monitor is None and last.filename == "last"
    assert best.dirpath == last.dirpath == str(tmp_path / "checkpoints")


@pytest.mark.parametrize("group", ["cpu", "gpu", "ddp"])
def test_trainer_configs_use_the_builder_and_its_policy(group: str) -> None:
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"trainer={group}", "out_dir=x"])
    assert cfg.trainer._target_ == "posernet.lit.build_trainer"
    assert cfg.trainer.deterministic is None  # the policy decides


def test_trainer_from_config(tmp_path: Path) -> None:
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=[
            f"out_dir={tmp_path}", "trainer.max_epochs=3", "trainer.gradient_clip_val=10",
            "trainer.gradient_clip_algorithm=value", "trainer.enable_progress_bar=false"])
    cbs = posernet_train_callbacks(tmp_path)
    trainer = trainer_from_config(cfg.trainer, callbacks=cbs, logger=False)
    assert trainer.max_epochs == 3 and trainer.gradient_clip_val == 10
    assert trainer.gradient_clip_algorithm == "value"
    assert [c for c in trainer.callbacks if isinstance(c, ModelCheckpoint)] == cbs
    assert trainer.logger is None and torch.are_deterministic_algorithms_enabled()


def test_callers_build_their_trainers_with_the_builder() -> None:
    from posernet.cli import demo, train
    from posernet.experiments import collect, models

    for mod in (demo, train, collect, models):
        src = inspect.getsource(mod)
        assert "L.Trainer(" not in src and "instantiate(cfg.trainer" not in src, mod.__name__
    # the demo's fallback model trains through posernet-train's train(cfg), the experiments
    # through posernet-train multiruns
    src = inspect.getsource(demo)
    assert "build_trainer" not in src and "from .train import train" in src
    assert '"posernet.cli.train"' in inspect.getsource(models)

"""The Hydra ``experiment/`` configs compose with ``posernet-train``'s config."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from posernet.cli import CONFIG_DIR

EXPERIMENTS = sorted(p.stem for p in (Path(CONFIG_DIR) / "experiment").glob("*.yaml"))


def cfg(*overrides: str):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose(config_name="train", overrides=list(overrides), return_hydra_config=True)


@pytest.mark.parametrize("name,estimate,size,lr,epochs", [
    ("table1_kp", "kp", "small", 0.001, 50),
    ("table1_bb", "bb", "small", 0.001, 50),
    ("large_graphs", "kp", "large", 0.01, 150),
])
def test_experiment_overrides(name, estimate, size, lr, epochs):
    c = cfg(f"+experiment={name}", "data.root=/tmp/x")
    assert c.data.estimate == estimate and c.data.size == size
    assert c.model.optimizer.lr == lr and c.trainer.max_epochs == epochs
    assert c.data.root == "/tmp/x"  # command-line overrides still win


def test_sweep_experiments_declare_their_sweeps():
    c = cfg("+experiment=depth_sweep")
    assert c.hydra.sweeper.params["model.net.depth"] == "2,3,4,5"
    c = cfg("+experiment=alpha_sweep")
    assert c.hydra.sweeper.params["model.loss.alpha"] == "0.1,0.5,1"
    c = cfg("+experiment=leave_one_out")
    assert "redkitchen" in c.hydra.sweeper.params["data.leave_out_scene"]
    assert c.test_after_training is True


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    from posernet.data.synthetic import generate_dataset

    root = tmp_path_factory.mktemp("tiny")
    generate_dataset("tiny", root, workers=1, progress=False, echo=None)
    return root


@pytest.mark.slow
@pytest.mark.parametrize("name", EXPERIMENTS)
def test_every_experiment_file_trains_with_fast_dev_run(name, tiny_data, tmp_path):
    """Every ``experiment/*.yaml`` (found by glob) runs through ``posernet-train``'s own
    ``train(cfg)`` for one fast_dev_run step (a sweep file: its base values)."""
    import math

    from hydra.core.hydra_config import HydraConfig

    from posernet.cli.train import train

    assert len(EXPERIMENTS) >= 6
    overrides = [f"+experiment={name}", f"data.root={tiny_data}", "trainer.fast_dev_run=true",
                 f"out_dir={tmp_path}", "data.num_workers=0", "hydra.mode=RUN"]
    if name == "leave_one_out":
        overrides.append("data.leave_out_scene=fire")
    if name == "large_graphs":
        overrides.append("data.val_size=small")
    c = cfg(*overrides)
    hydra_config = HydraConfig.instance()
    before = hydra_config.cfg
    hydra_config.set_config(c)
    try:
        result = train(c)
    finally:
        hydra_config.cfg = before  # later tests compose without this run's Hydra config
    assert isinstance(result, float) and (math.isnan(result) or result >= 0)

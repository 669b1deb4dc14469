"""The Hydra ``experiment/`` configs compose with ``posernet-train``'s config."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir

from posernet.cli import CONFIG_DIR


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
    assert c.model.lr == lr and c.trainer.max_epochs == epochs
    assert c.data.root == "/tmp/x"  # command-line overrides still win


def test_sweep_experiments_declare_their_sweeps():
    c = cfg("+experiment=depth_sweep")
    assert c.hydra.sweeper.params["model.depth"] == "2,3,4,5"
    c = cfg("+experiment=leave_one_out")
    assert "redkitchen" in c.hydra.sweeper.params["data.leave_out_scene"]
    assert c.test_after_training is True

"""``posernet-demo`` end to end on the tiny preset with the shipped checkpoint."""

from __future__ import annotations

import subprocess
import sys

import pytest

from posernet.checkpoints import default_checkpoint


def test_shipped_checkpoint_loads():
    from posernet import PoserNet

    model = PoserNet.from_checkpoint(default_checkpoint())
    assert sum(p.numel() for p in model.parameters()) > 1000
    with pytest.raises(FileNotFoundError, match="'nope.ckpt' not found"):
        default_checkpoint("nope.ckpt")


@pytest.mark.slow
def test_demo_runs_the_whole_pipeline(tmp_path):
    out = tmp_path / "demo"
    cmd = [sys.executable, "-m", "posernet.cli.demo", f"out_dir={out}", "dataset=tiny",
           "camera_plots=2", "images.frames=6", "images.width=320", "images.height=240",
           "images.focal=292.5", "images.matcher=sift"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    for name in ("table.md", "table.csv", "abs_table.md", "abs_table.csv",
                 "errors_sorted.png", "cameras_0.png", "cameras_1.png", "data/manifest.json"):
        assert (out / name).is_file(), name
    assert "| KP | PoserNet |" in (out / "table.md").read_text()
    assert "eig_se3 + PoserNet" in (out / "abs_table.md").read_text()
    # the image part: a rendered scene through posernet-reconstruct
    for name in ("scene/office/render.json", "reconstruct/poses.json", "reconstruct/cameras.png",
                 "reconstruct/matches_0.png", "reconstruct/abs_table.md"):
        assert (out / name).is_file(), name
    assert "rendering 6 frames" in r.stdout
    # A second run reuses the dataset (resume) and gives the same tables.
    first = (out / "table.md").read_text()
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (out / "table.md").read_text() == first
    assert "rendering" not in r.stdout  # the rendered scene is reused too


def test_demo_without_a_shipped_checkpoint_trains_with_posernet_train(tmp_path, monkeypatch):
    """The demo's fallback model comes from posernet-train's own train(cfg), into OUT/train."""
    from omegaconf import OmegaConf

    import posernet.checkpoints as shipped
    from posernet.cli.demo import _model
    from posernet.testing import write_random_dataset

    def missing(name: str = "x.ckpt"):
        raise FileNotFoundError(f"shipped checkpoint {name!r} not found")

    monkeypatch.setattr(shipped, "default_checkpoint", missing)
    data = write_random_dataset(tmp_path / "data", {"train": 4, "val": 2, "test": 1})
    cfg = OmegaConf.create({"train_epochs": 1, "estimate": "kp", "num_threads": 1})
    model, source = _model(cfg, data, tmp_path / "out", "cpu")
    assert source.startswith("trained here: ") and source.endswith("best.ckpt")
    assert (tmp_path / "out" / "train" / "metrics.json").is_file()
    assert (tmp_path / "out" / "train" / "logs" / "metrics.csv").is_file()
    assert model.depth == 2 and not model.training

"""One rule for naming a checkpoint in every command: a path, ``shipped`` (the default shipped
one), ``shipped:NAME`` or a shipped file's bare name (so a wheel install can name each)."""

from __future__ import annotations

from pathlib import Path

import pytest

from posernet.checkpoints import (
    DEFAULT_CHECKPOINT,
    default_checkpoint,
    resolve_checkpoint,
    shipped_checkpoints,
)


def test_names_of_shipped_checkpoints(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no file of that name here
    names = shipped_checkpoints()
    assert DEFAULT_CHECKPOINT in names and "posernet_synthetic_kp_v1.ckpt" in names
    assert resolve_checkpoint(None) == resolve_checkpoint("shipped") == default_checkpoint()
    v1 = default_checkpoint("posernet_synthetic_kp_v1.ckpt")
    assert resolve_checkpoint("shipped:posernet_synthetic_kp_v1.ckpt") == v1
    assert resolve_checkpoint("posernet_synthetic_kp_v1.ckpt") == v1
    with pytest.raises(FileNotFoundError, match="'nope.ckpt' not found.*shipped"):
        resolve_checkpoint("shipped:nope.ckpt")
    # a path is a path, even with a shipped file's name when such a file exists here
    (tmp_path / "posernet_synthetic_kp_v1.ckpt").write_bytes(b"x")
    assert resolve_checkpoint("posernet_synthetic_kp_v1.ckpt") == Path(
        "posernet_synthetic_kp_v1.ckpt")
    assert resolve_checkpoint("runs/x/last.ckpt") == Path("runs/x/last.ckpt")


def test_python_loaders_take_the_same_names(tmp_path, monkeypatch):
    """``load_refiner`` and ``PoserNet.from_checkpoint`` read what a command's ``ckpt_path``
    names; an unknown name is one error listing the names that exist."""
    import torch

    from posernet.checkpoints import CheckpointError
    from posernet.guard import load_refiner
    from posernet.nn import PoserNet

    monkeypatch.chdir(tmp_path)
    model, _ = load_refiner("shipped")
    default, _ = load_refiner(default_checkpoint())
    for a, b in zip(model.state_dict().values(), default.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    v1 = PoserNet.from_checkpoint("shipped:posernet_synthetic_kp_v1.ckpt")
    assert not v1.confidence and load_refiner("posernet_synthetic_kp_v1.ckpt")[0].depth == v1.depth
    with pytest.raises(CheckpointError) as exc:
        load_refiner("shiped")
    message = str(exc.value)
    assert message.startswith("checkpoint not found: shiped")
    assert all(name in message for name in ("shipped", "shipped:NAME", *shipped_checkpoints()))

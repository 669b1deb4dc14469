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

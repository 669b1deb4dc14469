"""PoserNet checkpoint files: reading them, and the ones shipped inside the package.

Checkpoints are Lightning checkpoints written by :class:`posernet.lit.PoserNetModule`, tagged
with :data:`CHECKPOINT_TAG`. :func:`read_checkpoint` reads one with torch alone
(``weights_only=True``: no pickled code runs); :meth:`posernet.nn.PoserNet.from_checkpoint`
turns it into the network and :func:`posernet.lit.load_posernet_checkpoint` into the Lightning
module.

``posernet_synthetic_kp.ckpt`` is a small input-adaptive PoserNet (``model=adaptive``: gate,
confidence head, cycle-consistency feature) trained on the *synthetic* ``paper`` preset with a
mixture of initial-pose qualities, then fine-tuned with the relative do-no-harm hinge
(``loss.harm``, ``loss.harm_scale``), then on the ``paper`` preset plus generator variants
(``research/conf/dataset/vary_*.yaml`` in the source tree: three, nine, then twelve) -- not
on 7-Scenes. It exists so that ``posernet-refine`` and ``make demo`` work out of the box; train
your own for real data.
``posernet_synthetic_kp_v1.ckpt`` is the checkpoint shipped before it (residual PoserNet trained
on KP input only, which regresses every input towards its error floor). ``docs/model-card.md``
gives the commands that reproduce both.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

__all__ = ["CHECKPOINT_TAG", "DEFAULT_CHECKPOINT", "CheckpointError", "checkpoint_names",
           "default_checkpoint", "network_hparams", "read_checkpoint", "resolve_checkpoint",
           "shipped_checkpoints"]

DEFAULT_CHECKPOINT = "posernet_synthetic_kp.ckpt"

#: written into every checkpoint by ``PoserNetModule`` so loaders can tell ours from others
CHECKPOINT_TAG = "posernet.PoserNetModule"


class CheckpointError(ValueError):
    """A checkpoint file is missing, unreadable or not a PoserNet checkpoint."""


def default_checkpoint(name: str = DEFAULT_CHECKPOINT) -> Path:
    """Path of a shipped checkpoint; ``FileNotFoundError`` naming it when it is absent."""
    path = Path(__file__).resolve().parent / name
    if not path.is_file():
        raise FileNotFoundError(f"shipped checkpoint {name!r} not found in {path.parent} "
                                f"({checkpoint_names()})")
    return path


def checkpoint_names() -> str:
    """What may name a checkpoint (:func:`resolve_checkpoint`), with the shipped files."""
    shipped = ", ".join(shipped_checkpoints()) or "none"
    return (f"give a path, shipped (= {DEFAULT_CHECKPOINT}), or shipped:NAME or NAME for a "
            f"shipped file: {shipped}")


def shipped_checkpoints() -> list[str]:
    """File names of the checkpoints shipped inside the package (also in a wheel install)."""
    return sorted(p.name for p in Path(__file__).resolve().parent.glob("*.ckpt"))


def resolve_checkpoint(value: str | os.PathLike[str] | None) -> Path:
    """The checkpoint a command option names: ``None`` or ``"shipped"`` -> the default shipped
    one; ``"shipped:NAME"`` or a shipped file name (``posernet_synthetic_kp_v1.ckpt``, when no
    such file exists where it is run) -> that shipped checkpoint; anything else a path. The same
    rule for ``ckpt_path`` and ``init_from`` of every command."""
    if value is None or str(value) in ("", "shipped"):
        return default_checkpoint()
    text = str(value)
    if text.startswith("shipped:"):
        return default_checkpoint(text.split(":", 1)[1])
    path = Path(text)
    if not path.exists() and path.name == text and text in shipped_checkpoints():
        return default_checkpoint(text)
    return path


def read_checkpoint(path: str | os.PathLike[str], tag: str = CHECKPOINT_TAG) -> dict[str, Any]:
    """Load a checkpoint dict on the CPU and check that the module tagged ``tag`` wrote it
    (default ``PoserNetModule``; the learned synchronisation has its own tag).

    ``path`` is a path or a shipped checkpoint's name (:func:`resolve_checkpoint`). Uses
    ``torch.load(weights_only=True)``. Raises :class:`CheckpointError` naming the file for a
    missing (with the valid names), unreadable or foreign checkpoint.
    """
    import torch

    p = resolve_checkpoint(path)
    if not p.is_file():
        raise CheckpointError(f"checkpoint not found: {p} ({checkpoint_names()})")
    try:
        ckpt = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt or foreign files
        first = (str(exc).strip().splitlines() or [""])[0]
        raise CheckpointError(f"{p}: not a readable checkpoint ({type(exc).__name__}: "
                              f"{first})") from exc
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt:
        raise CheckpointError(f"{p}: not a Lightning checkpoint (no 'state_dict')")
    found = ckpt.get("posernet", {}).get("tag") if isinstance(ckpt.get("posernet"), dict) \
        else None
    if found != tag:
        writer = found or ckpt.get("hparams_name") or "another model"
        what = "PoserNet" if tag == CHECKPOINT_TAG else tag.rsplit(".", 1)[-1]
        raise CheckpointError(f"{p}: not a {what} checkpoint (written by {writer}, "
                              f"no {tag!r} tag)")
    return ckpt


def network_hparams(ckpt: dict[str, Any]) -> dict[str, Any]:
    """The network's arguments stored in a checkpoint: its ``hyper_parameters["net"]``;
    :class:`CheckpointError` when there is no such section."""
    net = dict(ckpt.get("hyper_parameters") or {}).get("net")
    if not isinstance(net, dict):
        raise CheckpointError("checkpoint has no 'net' hyper-parameters (not written by "
                              "posernet.lit.PoserNetModule)")
    return dict(net)

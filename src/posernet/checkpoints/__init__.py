"""Checkpoints shipped inside the package.

``posernet_synthetic_kp.ckpt`` is a small PoserNet (default architecture) trained on the
*synthetic* ``paper`` preset with KP initial poses -- not on 7-Scenes. It exists so that
``posernet-refine`` and ``make demo`` work out of the box; train your own for real data.
``README.md`` (section "Shipped checkpoint") gives the command that reproduces it.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["DEFAULT_CHECKPOINT", "default_checkpoint"]

DEFAULT_CHECKPOINT = "posernet_synthetic_kp.ckpt"


def default_checkpoint(name: str = DEFAULT_CHECKPOINT) -> Path:
    """Path of a shipped checkpoint; ``FileNotFoundError`` naming it when it is absent."""
    path = Path(__file__).resolve().parent / name
    if not path.is_file():
        shipped = sorted(p.name for p in path.parent.glob("*.ckpt"))
        raise FileNotFoundError(f"shipped checkpoint {name!r} not found in {path.parent} "
                                f"(shipped: {shipped or 'none'}); pass ckpt_path=... instead")
    return path

"""Hydra command-line entry points (``posernet-make-data``, ``-train``, ``-eval``, ``-refine``).

The configs live in the repository's top-level ``conf/`` directory; ``POSERNET_CONFIG_DIR``
overrides the location (e.g. for a non-editable install with a copied ``conf/``).
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["CONFIG_DIR"]


def _config_dir() -> str:
    env = os.environ.get("POSERNET_CONFIG_DIR")
    if env:
        return str(Path(env).resolve())
    return str(Path(__file__).resolve().parents[3] / "conf")


# Absolute path handed to ``hydra.main(config_path=...)``.
CONFIG_DIR = _config_dir()

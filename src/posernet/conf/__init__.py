"""The Hydra configs of the posernet commands, shipped inside the package.

This folder holds ``<command>.yaml`` (``make_data``, ``train``, ``eval``, ``refine``, ``demo``,
``reconstruct``) and the config groups (``dataset/``, ``model/``, ``sync/``, ...). The commands
hand :data:`CONFIG_DIR`-style paths from :func:`config_dir` to Hydra; code that reads a yaml file
itself (the synthetic dataset presets) goes through :func:`config_root`, an
:mod:`importlib.resources` traversable, so both see the same files.

``POSERNET_CONFIG_DIR=/path/to/conf`` replaces the whole tree (e.g. an edited copy of it).
"""

from __future__ import annotations

import os
import sys
from importlib.resources import files
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    if sys.version_info >= (3, 11):
        from importlib.resources.abc import Traversable
    else:
        from importlib.abc import Traversable

__all__ = ["ENV_VAR", "config_dir", "config_root"]

#: environment variable naming a config folder to use instead of the shipped one
ENV_VAR = "POSERNET_CONFIG_DIR"


def config_root() -> Traversable:
    """The config tree: ``$POSERNET_CONFIG_DIR`` when set, else this package's resources."""
    env = os.environ.get(ENV_VAR)
    if env:
        return Path(env).expanduser().resolve()
    return files(__name__)


def config_dir() -> str:
    """Absolute file-system path of the config tree, as Hydra's ``config_path`` wants it."""
    root = config_root()
    if not isinstance(root, Path):  # e.g. imported from a zip file
        raise RuntimeError(f"posernet's configs are not a folder on disk ({root}); "
                           f"install posernet unzipped or set {ENV_VAR}=/path/to/conf")
    return str(root.resolve())

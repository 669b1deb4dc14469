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
import re
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from importlib.resources import files
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    if sys.version_info >= (3, 11):
        from importlib.resources.abc import Traversable
    else:
        from importlib.abc import Traversable

__all__ = ["ENV_VAR", "compose", "config_dir", "config_root", "initialized", "path_safe",
           "quote_value", "register_resolvers"]

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


def path_safe(value: object) -> str:
    """``value`` as one folder name: each path separator (``/``, ``\\``) becomes ``_`` (the
    configs' ``${posernet.path_safe:...}``, e.g. a sweep job's folder named by its overrides
    such as ``optimized_metric=val/rot_err_deg``)."""
    return str(value).replace("/", "_").replace("\\", "_")


def register_resolvers() -> None:
    """Register the resolvers the configs use (``posernet.path_safe``), once per process."""
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver("posernet.path_safe"):
        OmegaConf.register_new_resolver("posernet.path_safe", path_safe)


def compose(config_name: str, overrides: Sequence[str] = (),
            return_hydra_config: bool = False) -> Any:
    """A command's config (``"train"``, ``"eval"``, ...) composed with Hydra ``overrides``, as
    the command would see it, from Python: what ``python -m posernet.experiments`` uses to run
    ``posernet-train``'s own ``train(cfg)``.

    Works inside a running Hydra app too (its global state is set aside and restored).
    """
    from hydra import compose as hydra_compose

    with initialized(config_name):
        return hydra_compose(config_name, overrides=list(overrides),
                             return_hydra_config=return_hydra_config)


@contextmanager
def initialized(config_name: str, directory: str | os.PathLike[str] | None = None
                ) -> Iterator[None]:
    """Hydra initialised on the config tree (or ``directory``) for ``config_name``, inside a
    running Hydra app too (its global state is set aside and restored on exit)."""
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    register_resolvers()
    global_hydra = GlobalHydra.instance()
    outer = global_hydra.hydra if global_hydra.is_initialized() else None
    global_hydra.clear()
    try:
        with initialize_config_dir(config_dir=str(directory or config_dir()),
                                   version_base="1.3", job_name=config_name):
            yield
    finally:
        global_hydra.clear()
        if outer is not None:
            global_hydra.initialize(outer)


def quote_value(value: object) -> str:
    """``value`` as a quoted Hydra override value that reads back as ``str(value)`` (paths with
    spaces, ``=``, quotes, backslashes or ``${``)."""
    # Hydra reads a backslash as an escape only in front of a quote (or of the closing quote)
    text = re.sub(r"(\\*)('|$)", lambda m: m.group(1) * 2 + ("\\" + m.group(2) if m.group(2)
                                                               else ""), str(value))
    return "'" + text.replace("${", "\\${") + "'"  # no interpolation either

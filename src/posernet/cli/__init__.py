"""Hydra command-line entry points (``posernet-make-data``, ``-train``, ``-eval``, ``-refine``).

The configs ship inside the package (``posernet/conf/``, see :mod:`posernet.conf`);
``POSERNET_CONFIG_DIR`` replaces them with another folder of the same layout.
"""

from __future__ import annotations

from ..conf import config_dir, register_resolvers

__all__ = ["CONFIG_DIR"]

register_resolvers()  # before Hydra resolves a config (a sweep job's folder name uses one)

# Absolute path handed to ``hydra.main(config_path=...)``.
CONFIG_DIR = config_dir()

"""The paper's experiments, one command each: ``python -m posernet.experiments``.

``table1`` (KP/BB refinement), ``table2`` (small/large graphs), ``table3`` (motion averaging),
``depth`` (GNN depth and alpha sweeps), ``loo`` (leave-one-scene-out) and ``plots`` (the
supplementary's figures), at scale ``quick`` (tiny synthetic data, minutes on a CPU),
``medium`` (the ``paper`` preset with a tenth of its small graphs, about an hour on 2 cores) or
``paper`` (the ``paper`` synthetic preset, three seeds, the paper's epochs). See
:func:`run_experiments`; :func:`write_digest` condenses a run's tables into ``digest.md``.
"""

from __future__ import annotations

from .digest import digest_markdown, write_digest
from .runner import (
    EXPERIMENTS,
    MODELS,
    SCALES,
    Scale,
    parse_only,
    required_models,
    run_experiments,
    train_models,
)

__all__ = ["EXPERIMENTS", "MODELS", "SCALES", "Scale", "digest_markdown", "parse_only",
           "required_models", "run_experiments", "train_models", "write_digest"]

"""The paper's experiments, one command each: ``python -m posernet.experiments``.

``table1`` (KP/BB refinement), ``table2`` (small/large graphs), ``table3`` (motion averaging),
``depth`` (GNN depth and alpha sweeps), ``loo`` (leave-one-scene-out) and ``plots`` (the
supplementary's figures), at a scale of ``conf/scale/``: ``quick`` (tiny synthetic data,
minutes on a CPU), ``medium`` (the ``paper`` preset with a tenth of its small graphs, about an
hour on 2 cores) or ``paper``. The models are trained by ``posernet-train`` Hydra multiruns
(:mod:`~posernet.experiments.models`, any Hydra launcher plugin) and collected into tables by
:func:`run_experiments`; :func:`write_digest` condenses a run's tables into ``digest.md``.
"""

from __future__ import annotations

from .collect import TABLES, run_experiments
from .digest import digest_markdown, write_digest
from .models import (
    EXPERIMENTS,
    ModelSpec,
    Multirun,
    Scale,
    load_scale,
    multirun_commands,
    parse_only,
    required_models,
    scale_names,
)

__all__ = ["EXPERIMENTS", "TABLES", "ModelSpec", "Multirun", "Scale", "digest_markdown",
           "load_scale", "multirun_commands", "parse_only", "required_models",
           "run_experiments", "scale_names", "write_digest"]

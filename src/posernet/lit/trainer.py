"""The one place that builds Lightning Trainers for PoserNet.

``posernet-train`` (``conf/trainer/*.yaml``, via :func:`trainer_from_config`) builds every
Trainer of the project -- the demo's fallback training runs ``posernet-train``'s
``train(cfg)`` and the paper experiments (:mod:`posernet.experiments`) run ``posernet-train``
multiruns -- so they share one determinism policy:

* **CPU**: ``deterministic=True`` (``torch.use_deterministic_algorithms(True)``). Seeded CPU
  runs are bit-for-bit reproducible; the committed ``results/`` tables rely on it.
* **CUDA** (any non-CPU accelerator): ``deterministic="warn"``. Deterministic kernels are used
  where they exist, and an op without one warns instead of stopping a long run
  (``tests/test_cuda.py`` checks that PoserNet's own ops have one).

``deterministic=None`` (the default, and the trainer configs' value) applies this policy; an
explicit ``True``/``False``/``"warn"`` overrides it. ``accelerator="auto"`` counts as CUDA when
CUDA is available. Lightning sets the flag for the whole process (it is not reset after
``fit``).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any, Literal

__all__ = ["build_trainer", "determinism_policy", "trainer_from_config"]

Determinism = bool | Literal["warn"]


def determinism_policy(accelerator: str = "cpu") -> Determinism:
    """``True`` on the CPU, ``"warn"`` on CUDA (see the module docstring)."""
    acc = str(accelerator).lower()
    if acc == "auto":
        import torch

        acc = "gpu" if torch.cuda.is_available() else "cpu"
    return True if acc == "cpu" else "warn"


def build_trainer(*, accelerator: str = "cpu", devices: int | str = 1,
                  deterministic: Determinism | None = None,
                  callbacks: Iterable[Any] | None = None, logger: Any = False,
                  **kwargs: Any) -> Any:
    """A ``lightning.Trainer`` with the project's determinism policy.

    Args:
        accelerator, devices: as for ``lightning.Trainer`` (default: one CPU).
        deterministic: ``None`` applies :func:`determinism_policy` for ``accelerator``.
        callbacks: Lightning callbacks (``posernet-train`` builds them from
            ``conf/callbacks/*.yaml``); with none, Lightning's default checkpointing applies
            unless ``enable_checkpointing=False`` is passed.
        logger: a Lightning logger, or ``False`` (default) for none.
        **kwargs: any other ``lightning.Trainer`` argument (``max_epochs``, ``gradient_clip_val``,
            ``enable_progress_bar``, ``default_root_dir``, ``strategy``, ...), passed unchanged.
    """
    import lightning as L

    if deterministic is None:
        deterministic = determinism_policy(accelerator)
    trainer = L.Trainer(accelerator=accelerator, devices=devices, deterministic=deterministic,
                        callbacks=list(callbacks) if callbacks is not None else None,
                        logger=logger, **kwargs)
    if deterministic is True:
        import torch

        # Deterministic mode also fills every new tensor with NaN (to expose reads of
        # uninitialised memory): ~17 % of a CPU training step here. Nothing in posernet reads
        # uninitialised memory, so results stay bit-for-bit reproducible without the fill.
        torch.utils.deterministic.fill_uninitialized_memory = False
    return trainer


def trainer_from_config(cfg: Mapping[str, Any], callbacks: Iterable[Any] | None = None,
                        logger: Any = False) -> Any:
    """:func:`build_trainer` from a ``conf/trainer`` config (its ``_target_`` is ignored)."""
    from omegaconf import DictConfig, OmegaConf

    values = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) \
        else dict(cfg)
    assert isinstance(values, dict)
    values.pop("_target_", None)
    return build_trainer(callbacks=callbacks, logger=logger, **{str(k): v for k, v in
                                                                 values.items()})

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

:class:`TrainerOptions` declares the Trainer arguments that ``conf/trainer/*.yaml`` set (the
arguments are Lightning's; the config check applies these rules to ``trainer.*`` before any
work, and ``--help`` prints their meaning); others pass to Lightning unchecked.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from ..options import Rule, boolean, choice, integer, is_int, one_of, option, path

__all__ = ["TrainerOptions", "build_trainer", "determinism_policy", "trainer_from_config"]

Determinism = bool | Literal["warn"]

_PRECISIONS = ("64", "32", "16", "bf16", "64-true", "32-true", "16-true", "bf16-true", "16-mixed",
               "bf16-mixed")
_DEVICES = one_of(Rule("", lambda v: is_int(v) and (v == -1 or v >= 1)), choice("auto"),
                  Rule("a list of integers", lambda v: isinstance(v, list) and bool(v)
                       and all(is_int(x) for x in v)),
                  expected="an integer >= 1 (or -1: all), a list of integers or auto")
_PRECISION = one_of(choice(*_PRECISIONS), Rule("", lambda v: is_int(v) and v in (16, 32, 64)),
                    expected=f"one of {', '.join(_PRECISIONS)}")
_EPOCHS = Rule("an integer >= 1 (or -1: no limit)", lambda v: is_int(v) and (v == -1 or v >= 1))


@dataclass(frozen=True, kw_only=True)
class TrainerOptions:
    """The ``lightning.Trainer`` arguments of ``conf/trainer/*.yaml`` (``trainer.*``), with
    ``cpu.yaml``'s defaults (Lightning's for those it leaves out). A declaration only: the
    values go to :func:`build_trainer` as they are."""

    accelerator: str = option("cpu", choices=("auto", "cpu", "gpu", "cuda", "mps"),
                              help="the device type")
    devices: int | str | Sequence[int] = option(
        1, rule=_DEVICES, help="devices to use (auto: every one of the accelerator)")
    precision: int | str = option("32-true", rule=_PRECISION, help="floating-point precision")
    strategy: str = option("auto", help="distribution strategy (ddp: several devices)")
    max_epochs: int | None = option(50, rule=_EPOCHS, help="epochs to train (paper: 50 on small "
                                                           "graphs, 150 on large ones)")
    min_epochs: int | None = option(1, ge=0, help="epochs before early stopping may end a run")
    max_steps: int = option(-1, ge=-1, help="optimiser steps at most (-1: no limit)")
    fast_dev_run: bool | int = option(
        False, rule=one_of(boolean(), integer(0)),
        help="true (or N): one (N) batch of train + val as a smoke test")
    gradient_clip_val: float | None = option(None, ge=0, help="e.g. 10 with "
                                             "gradient_clip_algorithm=value (the authors' code)")
    gradient_clip_algorithm: str | None = option("norm", choices=("norm", "value"),
                                                 help="how gradients are clipped")
    deterministic: bool | str | None = option(
        None, rule=one_of(boolean(null=True), choice("warn")),
        help="null: the project's policy (CPU true, CUDA \"warn\"; posernet.lit.trainer)")
    log_every_n_steps: int = option(10, ge=1, help="training steps between logged metrics")
    check_val_every_n_epoch: int | None = option(1, ge=1, help="epochs between validations")
    num_sanity_val_steps: int = option(2, ge=-1, help="validation batches run before training "
                                                      "(-1: all)")
    enable_progress_bar: bool = option(True, help="show a progress bar")
    enable_model_summary: bool = option(True, help="print the model summary at the start")
    enable_checkpointing: bool = option(True, help="write checkpoints (which ones: the callbacks "
                                                   "group)")
    default_root_dir: str | None = option(None, rule=path(),
                                          help="folder of logs and checkpoints")


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


build_trainer.Options = TrainerOptions  # type: ignore[attr-defined]


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

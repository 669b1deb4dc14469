"""``posernet-train``: train PoserNet with Lightning, configured by Hydra
(``posernet/conf/train.yaml``).

Config groups: ``data`` (dataset directory, KP/BB input, leave-one-scene-out), ``model``
(depth, widths, alpha, lr, residual, ...), ``trainer`` (cpu, gpu, ddp), ``callbacks``
(best + last checkpoints) and ``sync`` (motion averaging, used by evaluation). Examples::

    posernet-train data.root=outputs/data/tiny
    posernet-train data.root=... ckpt_path=outputs/train/.../checkpoints/last.ckpt   # resume
    posernet-train data.root=... model=adaptive ... init_from=shipped   # fine-tune, fresh optimiser
    posernet-train -m data.root=... model.net.depth=2,3,4,5 model.loss.alpha=0.1,0.5  # sweep

Each run writes ``checkpoints/best.ckpt``, ``checkpoints/last.ckpt``, ``logs/metrics.csv`` and
``metrics.json`` (with ``best_metrics``, every validation metric of the best checkpoint's
epoch) into its Hydra output folder (one subfolder per job in a sweep, summarised by
:mod:`posernet.cli.sweep`). The task function returns the best value of ``optimized_metric``
(default ``val/loss``) so sweepers can minimise it.

Resuming (``ckpt_path=RUN/checkpoints/last.ckpt``) continues the run in its own folder ``RUN``
(unless ``hydra.run.dir`` or ``out_dir`` is given); ``ckpt_path=last`` resumes the output
folder's own ``checkpoints/last.ckpt`` when there is one and starts afresh otherwise (what a
multirun that may have been interrupted wants): the best checkpoint keeps competing with the
best model found before the interruption, ``metrics.json`` is rewritten there, the new epochs
are appended to ``logs/metrics.csv`` and the resumed job's Hydra config goes to
``RUN/.hydra/resume_<date>_<time>`` (the original ``.hydra`` files stay). What Hydra and
Lightning do not do for this themselves is in :mod:`posernet.cli.resume`.

Fine-tuning (``init_from=PATH``, or ``init_from=shipped`` for the shipped checkpoint) starts a
new run (epoch 0, a fresh optimiser and scheduler, the configured loss) from the network
weights of a checkpoint; ``model.net`` must describe the same network (a mismatch is one error
naming the differing values). ``ckpt_path`` and ``init_from`` exclude each other.
"""

from __future__ import annotations

import math
import re
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from ..options import ConfigValueError, Rule, option, path
from . import CONFIG_DIR
from .common import check_config, quiet_lightning, run_app, run_task, set_threads
from .resume import continues_run, kept_csv_log, relocation_callback, resume_overrides

__all__ = ["TrainSettings", "init_weights", "main", "train"]

#: a metric the training logs (what the 'best' checkpoint may monitor)
METRIC = Rule("a metric the training logs (val/loss, val/loss_<term>, val/rot_err_deg, "
              "val/tdir_err_deg, val/abs_rot_err_deg, val/abs_pos_err, their _init)",
              lambda v: isinstance(v, str) and re.fullmatch(
                  r"(val|train)/(loss(_\w+)?|(abs_)?(rot|tdir)_err_deg(_init)?"
                  r"|abs_pos_err(_init)?)", v) is not None)


@dataclass(frozen=True, kw_only=True)
class TrainSettings:
    """``posernet-train``'s own keys (``conf/train.yaml``; its groups declare theirs)."""

    seed: int = option(0, ge=0, help="lightning.seed_everything(seed, workers=True)")
    ckpt_path: str | None = option(None, rule=path(), help="resume training from this "
                                   "checkpoint (e.g. .../checkpoints/last.ckpt)")
    init_from: str | None = option(None, rule=path(), help="fine-tune: start from this "
                                   "checkpoint's network weights (a path, or shipped), fresh "
                                   "optimiser at epoch 0; model.net must match it")
    optimized_metric: str = option("val/loss", rule=METRIC, help="monitored by the 'best' "
                                   "checkpoint and returned to sweepers")
    test_after_training: bool = option(False, help="also run the test split with the best "
                                       "checkpoint")
    num_threads: int | None = option(1, ge=1, help="torch CPU threads (null: torch default); 1 "
                                     "is fastest for 8-node graphs "
                                     "(benchmarks/results/train_epoch.md: 30 s vs 93 s per epoch)")
    out_dir: str = option("${hydra:runtime.output_dir}", rule=path(),
                          help="the run's folder: checkpoints, logs, metrics.json")

    @staticmethod
    def cross_check(values: Mapping[str, Any]) -> None:
        """Across keys (``values``: those the config sets): resuming a run and fine-tuning
        from weights are two different starts."""
        init, resume = values.get("init_from"), values.get("ckpt_path")
        if init is not None and resume is not None:
            raise ConfigValueError(f"init_from={init} and ckpt_path={resume}: give one "
                                   f"(ckpt_path resumes a run, init_from starts a new one from "
                                   f"its weights)")

def _scalars(metrics: dict[str, Any]) -> dict[str, float]:
    """The finite one-element tensors of a Lightning metrics mapping, as floats."""
    import torch

    return {k: float(v) for k, v in metrics.items()
            if torch.is_tensor(v) and v.numel() == 1 and math.isfinite(float(v))}


def _validation_history() -> Any:
    """A callback keeping every validation epoch's metrics (``.epochs``: ``epoch`` and each
    ``val/`` metric), so the run can record those of the epoch its best checkpoint is from."""
    from lightning.pytorch.callbacks import Callback

    class _History(Callback):
        def __init__(self) -> None:
            self.epochs: list[dict[str, float]] = []

        def on_validation_end(self, trainer: Any, pl_module: Any) -> None:
            if not trainer.sanity_checking:
                metrics = _scalars(trainer.callback_metrics)
                self.epochs.append({"epoch": int(trainer.current_epoch),
                                    **{k: v for k, v in metrics.items()
                                       if k.startswith("val/")}})

    return _History()


def init_weights(module: Any, init_from: str) -> Path:
    """Load the network weights of checkpoint ``init_from`` (a path, or ``shipped``) into
    ``module.model``; return the file read.

    Raises :class:`posernet.checkpoints.CheckpointError` naming the file when it is not a
    PoserNet checkpoint or when its network differs from the configured ``model.net`` (the
    differing arguments listed), so nothing is half-loaded.
    """
    import inspect

    from ..checkpoints import (
        CheckpointError,
        network_hparams,
        read_checkpoint,
        resolve_checkpoint,
    )
    from ..nn import PoserNet

    path = resolve_checkpoint(init_from)
    net = getattr(module, "model", None)
    if not isinstance(net, PoserNet):
        raise CheckpointError(f"init_from={init_from}: this model ({type(module).__name__}) "
                              f"has no PoserNet to initialise")
    try:
        ckpt = read_checkpoint(path)
    except (CheckpointError, FileNotFoundError) as exc:  # name the option, then the cause
        raise type(exc)(f"init_from={init_from}: {exc}") from None
    params = inspect.signature(PoserNet).parameters

    def args(hp: Any) -> dict[str, Any]:
        hp = dict(hp or {})
        return {n: hp.get(n, p.default) for n, p in params.items()}

    want = args(getattr(module, "hparams", {}).get("net"))
    have = args(network_hparams(ckpt))
    differ = [n for n in params if have[n] != want[n]]
    if differ:
        raise CheckpointError(
            f"init_from={path}: its network differs from model.net in "
            + ", ".join(f"{n}={have[n]!r} (configured {want[n]!r})" for n in differ)
            + "; add " + " ".join(f"model.net.{n}={have[n]}" for n in differ))
    try:  # the one reader of the weights (drops a legacy layout's unused ones)
        loaded = PoserNet.from_checkpoint_dict(ckpt, path)
    except CheckpointError as exc:
        raise CheckpointError(f"init_from={init_from}: {exc}") from None
    net.load_state_dict(loaded.state_dict())
    return path


def _instantiate_dict(cfg: DictConfig | None) -> list[Any]:
    """Instantiate every ``_target_`` entry of a mapping (e.g. the ``callbacks`` group)."""
    if not cfg:
        return []
    return [hydra.utils.instantiate(v) for v in cfg.values()
            if isinstance(v, DictConfig) and "_target_" in v]


def train(cfg: DictConfig) -> float:
    """Train from a composed config; return the best ``cfg.optimized_metric`` (NaN if none)."""
    import warnings

    import lightning as L
    from lightning.pytorch.callbacks import ModelCheckpoint

    from ..checkpoints import CHECKPOINT_TAG, read_checkpoint
    from ..io import atomic_write_json
    from ..lit import trainer_from_config

    check_config(cfg, "train")  # every value, CUDA, a writable out_dir: before any output
    quiet_lightning()
    set_threads(cfg.get("num_threads"))
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)  # the seed is in the config
    out_dir = Path(cfg.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    ckpt_path = cfg.get("ckpt_path")
    if ckpt_path == "last":  # this run folder's own last checkpoint, when it has one
        found = out_dir / "checkpoints" / "last.ckpt"
        ckpt_path = str(found) if found.is_file() else None
    in_place = continues_run(ckpt_path, out_dir)

    datamodule = hydra.utils.instantiate(cfg.data)
    model: L.LightningModule = hydra.utils.instantiate(cfg.model)
    if not isinstance(model, L.LightningModule):
        raise TypeError(f"model config must build a LightningModule (e.g. "
                        f"posernet.lit.PoserNetModule), got {type(model).__name__}")
    resumed: dict[str, Any] = {}
    if ckpt_path not in (None, "last"):  # a clear error before Lightning's deep one
        resumed = read_checkpoint(ckpt_path, getattr(model, "CHECKPOINT_TAG", CHECKPOINT_TAG))
    init_from = cfg.get("init_from")
    if init_from is not None:
        init_path = init_weights(model, init_from)
    num_parameters = sum(p.numel() for p in model.parameters() if p.requires_grad)
    callbacks = _instantiate_dict(cfg.get("callbacks"))
    history_cb = _validation_history()
    callbacks.append(history_cb)
    if in_place:
        callbacks.append(relocation_callback(str(ckpt_path)))
    logger = hydra.utils.instantiate(cfg.logger) if cfg.get("logger") else False
    trainer: L.Trainer = trainer_from_config(cfg.trainer, callbacks=callbacks, logger=logger)
    if trainer.is_global_zero:
        print(f"{type(model).__name__}: {num_parameters} parameters; output folder {out_dir}")
        if in_place:
            print(f"Resuming from {ckpt_path}: continuing the run in {out_dir}")
        elif ckpt_path not in (None, "last"):
            print(f"Resuming from {ckpt_path} in a new folder {out_dir}")
        if init_from is not None:
            print(f"Fine-tuning the network of {init_path} (fresh optimiser, epoch 0)")
        if in_place:  # expected when a run continues in its folder
            warnings.filterwarnings("ignore", message=r"Checkpoint directory .* not empty")

    keep_log = in_place and trainer.is_global_zero
    with kept_csv_log(logger if keep_log else None, int(resumed.get("epoch", 0)),
                      int(resumed.get("global_step", 0))):
        trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt_path)

    checkpoints = [c for c in trainer.callbacks if isinstance(c, ModelCheckpoint)]
    # the monitored one keeps the best model; one without a monitor keeps the latest epoch
    ckpt_cb = next((c for c in checkpoints if c.monitor), checkpoints[0] if checkpoints else None)
    last_cb = next((c for c in checkpoints if not c.monitor), None)
    metric_name = str(cfg.optimized_metric)
    best: float = math.nan
    if ckpt_cb is not None and ckpt_cb.best_model_score is not None:
        best = float(ckpt_cb.best_model_score)
    elif metric_name in trainer.callback_metrics:
        best = float(trainer.callback_metrics[metric_name])

    test_metrics: dict[str, float] = {}
    if cfg.get("test_after_training"):
        best_path = ckpt_cb.best_model_path if ckpt_cb is not None else ""
        results = trainer.test(model, datamodule=datamodule, ckpt_path=best_path or None)
        test_metrics = {k: float(v) for r in results for k, v in r.items()}

    previous = out_dir / "metrics.json"
    if (trainer.is_global_zero and not trainer.callback_metrics and cfg.get("ckpt_path")
            and previous.is_file()):
        # resuming a finished run trains nothing: keep what it recorded
        print(f"the run had finished (epoch {int(trainer.current_epoch)} of "
              f"trainer.max_epochs={cfg.trainer.get('max_epochs')}): nothing to continue; "
              f"{previous} kept (raise trainer.max_epochs to train further)")
        return best
    if trainer.is_global_zero:
        summary = {
            "optimized_metric": metric_name,
            "best": None if math.isnan(best) else best,
            "best_checkpoint": ckpt_cb.best_model_path if ckpt_cb is not None else None,
            "last_checkpoint": (last_cb.best_model_path if last_cb is not None
                                else ckpt_cb.last_model_path if ckpt_cb is not None else None)
                               or None,
            "epochs": int(trainer.current_epoch),
            "num_parameters": num_parameters,
            "seed": int(cfg.seed),
            "train_seconds": round(time.perf_counter() - t_start, 3),
            "final_metrics": _scalars(trainer.callback_metrics),
            # every validation metric of the epoch the best checkpoint is from (e.g. the
            # rotation error, comparable across loss weights); {} when that epoch ran before
            # a resume
            "best_metrics": next((m for m in reversed(history_cb.epochs)
                                  if m.get(metric_name) == best), {}),
            "test": {k: v for k, v in test_metrics.items() if math.isfinite(v)},
        }
        atomic_write_json(out_dir / "metrics.json", summary)
        print(f"best {metric_name} = {best:.4f}"
              + (f" ({summary['best_checkpoint']})" if summary["best_checkpoint"] else ""))
    return best


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="train")
def _hydra_main(cfg: DictConfig) -> float:
    return run_task("posernet-train", train, cfg, resume_hint=_resume_hint)


def _resume_hint(cfg: DictConfig) -> str | None:
    """After Ctrl-C: the checkpoint to resume from, when the run wrote one."""
    last = Path(str(cfg.out_dir)) / "checkpoints" / "last.ckpt"
    return f"resume with ckpt_path={last}" if last.is_file() else None


def main() -> None:
    """Console-script entry point (``posernet-train``)."""
    sys.argv[1:] = resume_overrides(sys.argv[1:])
    run_app("posernet-train", "train", _hydra_main)


if __name__ == "__main__":
    main()

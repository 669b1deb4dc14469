"""``posernet-train``: train PoserNet with Lightning, configured by Hydra (``conf/train.yaml``).

Config groups: ``data`` (dataset directory, KP/BB input, leave-one-scene-out), ``model``
(depth, widths, alpha, lr, residual, ...), ``trainer`` (cpu, gpu, ddp), ``callbacks``
(best + last checkpoints) and ``sync`` (motion averaging, used by evaluation). Examples::

    posernet-train data.root=outputs/data/tiny
    posernet-train data.root=... ckpt_path=outputs/train/.../checkpoints/last.ckpt   # resume
    posernet-train -m data.root=... model.depth=2,3,4,5 model.alpha=0.1,0.5          # sweep

Each run writes ``checkpoints/best.ckpt``, ``checkpoints/last.ckpt``, ``logs/metrics.csv`` and
``metrics.json`` into its Hydra output folder (one subfolder per job in a sweep). The task
function returns the best value of ``optimized_metric`` (default ``val/loss``) so sweepers can
minimise it.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from . import CONFIG_DIR
from .common import quiet_lightning, report_error, set_threads, user_errors

__all__ = ["main", "train"]


def _instantiate_dict(cfg: DictConfig | None) -> list[Any]:
    """Instantiate every ``_target_`` entry of a mapping (e.g. the ``callbacks`` group)."""
    if not cfg:
        return []
    return [hydra.utils.instantiate(v) for v in cfg.values()
            if isinstance(v, DictConfig) and "_target_" in v]


def train(cfg: DictConfig) -> float:
    """Train from a composed config; return the best ``cfg.optimized_metric`` (NaN if none)."""
    import lightning as L
    import torch
    from lightning.pytorch.callbacks import ModelCheckpoint

    from ..io import atomic_write_json
    from ..lit import PoserNetModule, read_posernet_checkpoint

    quiet_lightning()
    set_threads(cfg.get("num_threads"))
    L.seed_everything(int(cfg.seed), workers=True)
    out_dir = Path(cfg.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if cfg.get("ckpt_path") not in (None, "last"):
        read_posernet_checkpoint(cfg.ckpt_path)  # clear error before Lightning's deep one

    datamodule = hydra.utils.instantiate(cfg.data)
    model: PoserNetModule = hydra.utils.instantiate(cfg.model)
    if not isinstance(model, PoserNetModule):
        raise TypeError(f"model config must build a PoserNetModule, got {type(model).__name__}")
    callbacks = _instantiate_dict(cfg.get("callbacks"))
    logger = hydra.utils.instantiate(cfg.logger) if cfg.get("logger") else False
    trainer: L.Trainer = hydra.utils.instantiate(cfg.trainer, callbacks=callbacks, logger=logger)
    if trainer.is_global_zero:
        print(f"PoserNet: {model.num_parameters} parameters; output folder {out_dir}")

    trainer.fit(model, datamodule=datamodule, ckpt_path=cfg.get("ckpt_path"))

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

    if trainer.is_global_zero:
        summary = {
            "optimized_metric": metric_name,
            "best": None if math.isnan(best) else best,
            "best_checkpoint": ckpt_cb.best_model_path if ckpt_cb is not None else None,
            "last_checkpoint": (last_cb.best_model_path if last_cb is not None
                                else ckpt_cb.last_model_path if ckpt_cb is not None else None)
                               or None,
            "epochs": int(trainer.current_epoch),
            "num_parameters": model.num_parameters,
            "seed": int(cfg.seed),
            "final_metrics": {k: float(v) for k, v in trainer.callback_metrics.items()
                              if torch.is_tensor(v) and v.numel() == 1
                              and math.isfinite(float(v))},
            "test": {k: v for k, v in test_metrics.items() if math.isfinite(v)},
        }
        atomic_write_json(out_dir / "metrics.json", summary)
        print(f"best {metric_name} = {best:.4f}"
              + (f" ({summary['best_checkpoint']})" if summary["best_checkpoint"] else ""))
    return best


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="train")
def _hydra_main(cfg: DictConfig) -> float:
    try:
        return train(cfg)
    except user_errors() as exc:
        report_error("posernet-train", exc)
        sys.exit(1)


def main() -> None:
    """Console-script entry point (``posernet-train``)."""
    _hydra_main()


if __name__ == "__main__":
    main()

"""What posernet's Lightning modules share: hyper-parameters in sections of plain values, the
epoch medians of per-graph errors, Adam with reduce-on-plateau, and the checkpoint tag.

:class:`~posernet.lit.PoserNetModule` (relative poses) and
:class:`~posernet.lit.LearnedSyncModule` (the learned synchronisation) subclass
:class:`SectionedModule`; each declares its ``SECTIONS`` (the sections of its model config with
their defaults), its ``CHECKPOINT_TAG`` and the names of the per-graph errors its
``_collect`` stores (``MEDIAN_METRICS``).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any, ClassVar

import lightning as L
import torch
from torch import Tensor, nn

from .. import __version__

__all__ = ["SectionedModule", "fill_sections"]


def fill_sections(spec: Mapping[str, Mapping[str, Any]], owner: str,
                  given: Mapping[str, Mapping[str, Any] | None]) -> dict[str, dict[str, Any]]:
    """Every section of ``spec`` filled with its defaults, updated from ``given``.

    ``TypeError`` naming ``owner`` for an unknown section, a section that is not a mapping or an
    unknown key.
    """
    unknown = [s for s in given if s not in spec]
    if unknown:
        raise TypeError(f"unknown {owner} section(s) {unknown}; sections: {list(spec)}")
    out = {name: dict(defaults) for name, defaults in spec.items()}
    for section, values in given.items():
        if values is None:
            continue
        if not isinstance(values, Mapping):
            raise TypeError(f"{owner} {section}= must be a mapping, got {type(values).__name__}")
        bad = [k for k in values if k not in spec[section]]
        if bad:
            raise TypeError(f"unknown {section} hyper-parameter(s) {bad}; known: "
                            f"{list(spec[section])}")
        out[section].update({str(k): v for k, v in values.items()})
    return out


class SectionedModule(L.LightningModule):
    """A LightningModule with sectioned plain hyper-parameters (``optimizer``: Adam's ``lr``,
    ``weight_decay``; ``scheduler``: plateau ``patience``, ``factor``, ``min_lr`` on
    ``val/loss``) and per-graph errors logged as epoch medians."""

    #: written into its checkpoints; ``posernet.checkpoints.read_checkpoint`` checks it
    CHECKPOINT_TAG: ClassVar[str] = "posernet.SectionedModule"
    #: names of the columns ``_collect`` stores per graph, logged as ``split/<name>`` medians
    MEDIAN_METRICS: ClassVar[tuple[str, ...]] = ()
    #: how many of them go to the progress bar
    MEDIAN_PROG_BAR: ClassVar[int] = 1

    def __init__(self) -> None:
        super().__init__()
        self._errors: dict[str, list[Tensor]] = {}

    def trainable_parameters(self) -> Iterator[nn.Parameter]:
        """The parameters the optimiser updates (default: all of the module's)."""
        return self.parameters()

    @property
    def num_parameters(self) -> int:
        """Number of trainable parameters."""
        return sum(p.numel() for p in self.trainable_parameters() if p.requires_grad)

    # ------------------------------------------------------------------ steps
    def _step(self, batch: Any, split: str) -> Tensor:
        """The loss of one batch of ``split`` (train / val / test), logged."""
        raise NotImplementedError

    def training_step(self, batch: Any, batch_idx: int) -> Tensor:
        return self._step(batch, "train")

    def validation_step(self, batch: Any, batch_idx: int) -> Tensor:
        return self._step(batch, "val")

    def test_step(self, batch: Any, batch_idx: int) -> Tensor:
        return self._step(batch, "test")

    def predict_step(self, batch: Any, batch_idx: int) -> Tensor:
        return self(batch)

    # ------------------------------------------------------------------ epoch medians
    def _store(self, split: str, per_graph: Tensor) -> None:
        """Keep ``per_graph [B, len(MEDIAN_METRICS)]`` errors for the epoch's medians."""
        self._errors.setdefault(split, []).append(per_graph)

    def _log_medians(self, split: str) -> None:
        chunks = self._errors.pop(split, [])
        if not chunks:
            return
        errs = torch.cat(chunks)
        trainer = self._trainer  # None outside a Trainer (``self.trainer`` would raise)
        if trainer is not None and trainer.world_size > 1:
            # pad to a common length so every rank can all_gather, then drop the padding
            n = torch.tensor(errs.shape[0], device=errs.device)
            max_n = int(self.all_gather(n).max())
            pad = errs.new_full((max_n - errs.shape[0], errs.shape[1]), float("nan"))
            errs = self.all_gather(torch.cat((errs, pad))).reshape(-1, errs.shape[1])
        errs = errs.float()
        for k, name in enumerate(self.MEDIAN_METRICS):
            col = errs[:, k]
            col = col[~torch.isnan(col)]
            if col.numel():
                # every rank holds the gathered errors: no further sync is needed
                self.log(f"{split}/{name}", col.quantile(0.5), prog_bar=k < self.MEDIAN_PROG_BAR)

    def on_validation_epoch_start(self) -> None:
        self._errors.pop("val", None)

    def on_validation_epoch_end(self) -> None:
        self._log_medians("val")

    def on_test_epoch_start(self) -> None:
        self._errors.pop("test", None)

    def on_test_epoch_end(self) -> None:
        self._log_medians("test")

    # ------------------------------------------------------------------ optimiser
    def configure_optimizers(self) -> dict[str, Any]:
        opt_hp, sched_hp = self.hparams.optimizer, self.hparams.scheduler
        opt = torch.optim.Adam(self.trainable_parameters(), lr=opt_hp["lr"],
                               weight_decay=opt_hp["weight_decay"])
        sched = torch.optim.lr_scheduler.ReduceLROnPlateau(
            opt, mode="min", factor=sched_hp["factor"], patience=sched_hp["patience"],
            min_lr=sched_hp["min_lr"])
        # strict=False: runs without validation (e.g. limit_val_batches=0) only warn.
        return {"optimizer": opt,
                "lr_scheduler": {"scheduler": sched, "monitor": "val/loss", "interval": "epoch",
                                 "strict": False}}

    # ------------------------------------------------------------------ checkpoints
    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["posernet"] = {"tag": self.CHECKPOINT_TAG, "version": __version__}

"""Lightning training module for PoserNet.

:class:`PoserNetModule` takes plain hyper-parameters and builds the network itself, so
``PoserNetModule.load_from_checkpoint(path)`` works without Hydra. One shared step serves
train / val / test; logged names read ``split/metric``:

* ``train/loss``, ``val/loss``, ``test/loss`` (and the four loss terms);
* ``val/rot_err_deg``, ``val/tdir_err_deg`` (and ``test/...``): median over graphs of each
  graph's mean edge error, as in the paper's tables; ``..._init`` the same for the input poses.

Optimiser: Adam with reduce-on-plateau on ``val/loss`` (paper: patience 3 epochs).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..checkpoints import CHECKPOINT_TAG, CheckpointError, read_checkpoint
from ..graph import GraphBatch
from ..metrics import relative_errors_per_graph
from ..nn import PoserNet
from ..nn.loss import relative_objective
from ..options import option
from .base import SectionedModule, fill_sections

__all__ = ["SECTIONS", "LossOptions", "OptimizerOptions", "PoserNetModule",
           "SchedulerOptions", "load_posernet_checkpoint", "module_hparams"]


@dataclass(frozen=True)
class LossOptions:
    """``model.loss``: the training loss's weights (see :class:`PoserNetModule`)."""

    alpha: float = option(0.1, ge=0, help="weight of the loss's normalisation terms")
    raw: float = option(0.0, ge=0, help="the same loss on the pre-gate prediction")
    confidence: float = option(0.0, ge=0, help="heteroscedastic error-scale loss")
    correction: float = option(0.0, ge=0, help="small-correction prior (radians)")
    harm: float = option(0.0, ge=0, help="do-no-harm hinge (radians)")
    harm_scale: float = option(0.0, ge=0, help="> 0: the hinge relative to the input error "
                                               "plus this (radians)")
    end_to_end: bool = option(False, help="add a loss on absolute poses through a "
                                          "differentiable synchronisation")
    relative_weight: float = option(1.0, ge=0, help="end to end: the relative-pose loss")
    absolute_weight: float = option(1.0, ge=0, help="end to end: the absolute rotation loss")
    position_weight: float = option(1.0, ge=0, help="end to end: times the camera-centre loss")


@dataclass(frozen=True)
class OptimizerOptions:
    """``model.optimizer``: Adam's."""

    lr: float = option(1e-3, gt=0, help="learning rate")
    weight_decay: float = option(0.0, ge=0, help="weight decay")


@dataclass(frozen=True)
class SchedulerOptions:
    """``model.scheduler``: reduce-on-plateau on ``val/loss``."""

    patience: int = option(3, ge=0, help="epochs without improvement")
    factor: float = option(0.316, gt=0, lt=1, help="multiplicative factor")
    min_lr: float = option(1e-6, ge=0, help="lower bound of the learning rate")


#: the options dataclass of each section of a model config (``PoserNetModule``'s arguments)
SECTION_OPTIONS: dict[str, type] = {"net": PoserNet.Options, "loss": LossOptions,
                                    "optimizer": OptimizerOptions,
                                    "scheduler": SchedulerOptions}

#: the sections of a model config and of ``PoserNetModule``'s hyper-parameters, with defaults
#: (each section's options dataclass's)
SECTIONS: dict[str, dict[str, Any]] = {
    name: {f.name: f.default for f in dataclasses.fields(owner)}
    for name, owner in SECTION_OPTIONS.items()}

def module_hparams(net: Mapping[str, Any] | None = None, loss: Mapping[str, Any] | None = None,
                   optimizer: Mapping[str, Any] | None = None,
                   scheduler: Mapping[str, Any] | None = None) -> dict[str, dict[str, Any]]:
    """``PoserNetModule``'s hyper-parameters as plain nested dicts, every value filled in;
    ``TypeError`` naming an unknown section key."""
    given = {"net": net, "loss": loss, "optimizer": optimizer, "scheduler": scheduler}
    return fill_sections(SECTIONS, "PoserNetModule", given)


class PoserNetModule(SectionedModule):
    """PoserNet + its loss + optimiser, for Lightning.

    The arguments mirror ``conf/model/posernet.yaml``, one plain mapping per section, so a
    checkpoint's hyper-parameters load with ``weights_only=True`` and without Hydra:

    Args:
        net: arguments of :class:`posernet.nn.PoserNet` (``depth``, ``node_hidden``,
            ``edge_hidden``, ``mlp_hidden``, ``mlp_layers``, ``negative_slope``,
            ``shared_weights``, ``residual``, ``unit_output``, ``nested_mean``).
        loss: ``alpha``, the weight of the normalisation terms of the loss (default 0.1);
            ``raw``: weight of the same loss on the pre-gate prediction (gated networks);
            ``confidence``: weight of the heteroscedastic error-scale loss
            (:func:`posernet.nn.adaptive.heteroscedastic_nll`); ``correction``: weight of the
            small-correction prior, the mean rotation angle between output and input (radians);
            ``harm``: weight of the do-no-harm hinge, the mean excess of each edge's output
            rotation and direction errors over its input's (radians, 0 where the output is
            better), which makes the network leave an edge alone where it cannot tell that it
            would improve it (with a gate it trains the gate only); ``harm_scale`` (radians,
            default 0): when positive, each edge's excess is divided by its input error plus
            ``harm_scale`` (a relative hinge: harm done to good inputs weighs most), and the
            hinge trains the whole network. The weights default to 0
            (the paper's loss). ``end_to_end`` (default False) adds a loss on absolute poses
            through a differentiable synchronisation
            (:func:`posernet.sync.differentiable.differentiable_sync`, ground-truth baselines
            while training) after gauge alignment: ``relative_weight * relative +
            absolute_weight * (rotation + position_weight * position)``; the batches then need
            ``pose_gt``.
        optimizer: Adam's ``lr`` (default 1e-3; the paper uses 1e-2 for large graphs) and
            ``weight_decay`` (0).
        scheduler: reduce-on-plateau on ``val/loss``: ``patience`` epochs without improvement
            (3), multiplicative ``factor`` (0.316), lower bound ``min_lr`` (1e-6).
    """

    CHECKPOINT_TAG = CHECKPOINT_TAG
    MEDIAN_METRICS = ("rot_err_deg", "tdir_err_deg", "rot_err_deg_init", "tdir_err_deg_init")
    MEDIAN_PROG_BAR = 2

    def __init__(self, net: Mapping[str, Any] | None = None,
                 loss: Mapping[str, Any] | None = None,
                 optimizer: Mapping[str, Any] | None = None,
                 scheduler: Mapping[str, Any] | None = None) -> None:
        super().__init__()
        hp = module_hparams(net, loss, optimizer, scheduler)
        self.save_hyperparameters(hp)
        self.model = PoserNet(**hp["net"])

    # ------------------------------------------------------------------ inference
    def forward(self, batch: GraphBatch, edge_pose: Tensor | None = None) -> Tensor:
        """Refined relative poses ``[E, 7]`` of a ``GraphBatch`` (its ``edge_pose`` by default)."""
        return self.model(batch, edge_pose=edge_pose)

    # ------------------------------------------------------------------ steps
    def _step(self, batch: GraphBatch, split: str) -> Tensor:
        if batch.edge_pose_gt is None:
            raise ValueError(f"{split} batch has no 'edge_pose_gt': cannot compute the loss")
        lh = self.hparams.loss
        gt = batch.edge_pose_gt
        extras = self.model(batch, return_extras=True) if self.model.adaptive else None
        pred = extras.pose if extras is not None else self(batch)
        total, out, terms = relative_objective(pred, gt, batch.edge_pose, extras, lh)
        if lh.get("end_to_end", False):
            terms["abs_rot"], terms["abs_pos"] = self._absolute_loss(batch, pred)
            total = lh["relative_weight"] * total + lh["absolute_weight"] * (
                terms["abs_rot"] + lh["position_weight"] * terms["abs_pos"])
        n = batch.num_graphs
        on_step = split == "train"
        self.log(f"{split}/loss", total, batch_size=n, on_step=on_step, on_epoch=True,
                 prog_bar=True, sync_dist=split != "train")
        for name in ("orient", "tr_dir", "q_norm", "t_norm"):
            self.log(f"{split}/loss_{name}", getattr(out, name), batch_size=n, on_step=False,
                     on_epoch=True, sync_dist=split != "train")
        for name, value in terms.items():
            self.log(f"{split}/loss_{name}", value, batch_size=n, on_step=False,
                     on_epoch=True, sync_dist=split != "train")
        if split != "train":
            self._collect(split, batch, pred.detach())
        return total

    def _absolute_loss(self, batch: GraphBatch, pred: Tensor) -> tuple[Tensor, Tensor]:
        """Mean aligned rotation / position losses of the absolute poses synchronised from
        ``pred`` (float64: the spectral step and the SO(3) projection need it)."""
        from ..sync.differentiable import aligned_pose_loss, differentiable_sync

        if batch.pose_gt is None or batch.edge_pose_gt is None:
            raise ValueError("loss.end_to_end needs batches with pose_gt and edge_pose_gt")
        norm = batch.edge_pose_gt[:, 4:].double().norm(dim=-1)
        poses, solved = differentiable_sync(batch.edge_index, pred.double(), batch.num_nodes,
                                            batch.node_batch, batch.num_graphs,
                                            translation_norm=norm)
        rot, pos = aligned_pose_loss(poses, batch.pose_gt.double(), batch.node_batch,
                                     batch.num_graphs, solved)
        return rot.mean().to(pred.dtype), pos.mean().to(pred.dtype)

    # ------------------------------------------------------------------ per-graph metrics
    def _collect(self, split: str, batch: GraphBatch, pred: Tensor) -> None:
        """Store each graph's mean edge errors (refined and initial) for the epoch's median."""
        n = batch.num_graphs
        rows = []
        for pose in (pred, batch.edge_pose):  # the tables' per-graph errors (posernet.metrics)
            per_graph = relative_errors_per_graph(pose, batch.edge_pose_gt, batch.edge_batch, n)
            rows += [per_graph["rot"], per_graph["tdir"]]
        self._store(split, torch.stack(rows, dim=-1))  # [B, 4]

    # ------------------------------------------------------------------ checkpoints
    def on_fit_start(self) -> None:
        # statistics of the training inputs, saved with the checkpoint for the OOD guard
        dm = getattr(self.trainer, "datamodule", None) if self._trainer is not None else None
        graphs = getattr(dm, "train_graphs", None)
        if graphs:
            from ..guard import input_statistics

            self.input_stats = input_statistics(graphs)

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        super().on_save_checkpoint(checkpoint)
        stats = getattr(self, "input_stats", None)
        if stats:
            checkpoint["posernet"]["input_stats"] = stats


def load_posernet_checkpoint(path: str | os.PathLike[str],
                             map_location: str | torch.device = "cpu") -> PoserNetModule:
    """:class:`PoserNetModule` from a checkpoint, in eval mode, with clear errors.

    Equivalent to ``PoserNetModule.load_from_checkpoint(path)`` for good files; a missing file,
    another model's checkpoint or mismatching weights raise :class:`CheckpointError`. The file
    is read by :func:`posernet.checkpoints.read_checkpoint` and its weights by
    :meth:`PoserNet.from_checkpoint_dict`, the same code as :meth:`PoserNet.from_checkpoint`.
    """
    ckpt = read_checkpoint(path)
    network = PoserNet.from_checkpoint_dict(ckpt, path)  # the one reader of the weights
    try:
        module = PoserNetModule(**dict(ckpt.get("hyper_parameters") or {}))
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: checkpoint does not fit this PoserNet ({exc})") from exc
    module.model = network
    return module.to(map_location).eval()

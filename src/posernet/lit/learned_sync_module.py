"""Lightning training module for the learned synchronisation (:mod:`posernet.sync.learned`).

:class:`LearnedSyncModule` takes plain hyper-parameters, one mapping per section, like
:class:`posernet.lit.PoserNetModule`, so its checkpoints load with ``weights_only=True`` and
without Hydra; ``posernet-train model=learned_sync data.root=DATASET`` trains it with the same
stack, and ``sync=learned sync.ckpt_path=RUN/checkpoints/best.ckpt`` uses it as a backend.

Input: the batch's ``edge_pose`` ("raw input", the KP/BB estimate) or, with
``input.refiner_ckpt`` set, the edge poses refined by that frozen PoserNet ("refined input").

Logged (``split/metric``): ``loss`` (weighted over rounds) with ``loss_rot``, ``loss_tdir`` (the
last round's terms) and ``loss_init`` (the spectral / identity start); for val and test also
``abs_rot_err_deg`` and ``abs_pos_err`` -- the median over graphs of each graph's mean
absolute error after the project's alignment (:func:`posernet.metrics.absolute_errors_per_graph`,
similarity on the camera centres, rotations by the rotation gauge) -- and ``..._init`` the same
for the initial solution.
"""

from __future__ import annotations

import inspect
from collections.abc import Iterator, Mapping
from typing import Any

import torch
from torch import Tensor, nn

from ..graph import GraphBatch
from ..metrics import absolute_errors_per_graph
from ..sync.components import connected_components
from ..sync.learned import LEARNED_SYNC_TAG, LearnedSyncNet, all_pairs, learned_sync_loss
from .base import SectionedModule, fill_sections

__all__ = ["SECTIONS", "LearnedSyncModule", "sync_module_hparams"]

#: the sections of ``conf/model/learned_sync.yaml`` and their defaults (``net``: the arguments
#: of :class:`LearnedSyncNet`, defaults from its signature)
SECTIONS: dict[str, dict[str, Any]] = {
    "net": {k: p.default for k, p in inspect.signature(LearnedSyncNet).parameters.items()},
    "loss": {"gamma": 0.8, "translation_weight": 1.0},
    "optimizer": {"lr": 1e-3, "weight_decay": 0.0},
    "scheduler": {"patience": 3, "factor": 0.316, "min_lr": 1e-6},
    "input": {"refiner_ckpt": None},
}

def sync_module_hparams(**sections: Mapping[str, Any] | None) -> dict[str, dict[str, Any]]:
    """Every section filled with its defaults; ``TypeError`` naming unknown sections / keys."""
    out = fill_sections(SECTIONS, "LearnedSyncModule", sections)
    ref = out["input"]["refiner_ckpt"]
    if ref is not None and (not isinstance(ref, str) or not ref):
        raise TypeError(f"input.refiner_ckpt must be a path or null, got {ref!r}")
    if ref is not None:
        out["input"]["refiner_ckpt"] = str(ref)
    return out


class LearnedSyncModule(SectionedModule):
    """:class:`LearnedSyncNet` + :func:`learned_sync_loss` + Adam, for Lightning.

    Args:
        net: :class:`LearnedSyncNet`'s arguments (``hidden``, ``rounds``, ``mlp_layers``,
            ``init``, ``step_scale``, ``use_confidence``, ``negative_slope``).
        loss: ``gamma`` (round ``k`` of ``K`` weighted ``gamma^(K-1-k)``; default 0.8) and
            ``translation_weight`` (of the direction term; default 1).
        optimizer: Adam's ``lr`` (1e-3) and ``weight_decay`` (0).
        scheduler: reduce-on-plateau on ``val/loss``: ``patience``, ``factor``, ``min_lr``.
        input: ``refiner_ckpt``: a PoserNet checkpoint whose refined edge poses (frozen, no
            gradient) are the input; ``None`` (default) uses the batch's ``edge_pose``.
    """

    #: written into its checkpoints (``read_checkpoint(path, LearnedSyncModule.CHECKPOINT_TAG)``)
    CHECKPOINT_TAG = LEARNED_SYNC_TAG
    MEDIAN_METRICS = ("abs_rot_err_deg", "abs_pos_err", "abs_rot_err_deg_init",
                      "abs_pos_err_init")

    def __init__(self, net: Mapping[str, Any] | None = None,
                 loss: Mapping[str, Any] | None = None,
                 optimizer: Mapping[str, Any] | None = None,
                 scheduler: Mapping[str, Any] | None = None,
                 input: Mapping[str, Any] | None = None) -> None:
        super().__init__()
        hp = sync_module_hparams(net=net, loss=loss, optimizer=optimizer, scheduler=scheduler,
                                 input=input)
        self.save_hyperparameters(hp)
        self.net = LearnedSyncNet(**hp["net"])
        # The refiner is not a submodule: its weights stay out of this module's checkpoint and
        # optimiser (it is frozen, and the backend gets already refined poses from its caller).
        self._refiner: Any = None

    # ------------------------------------------------------------------ input
    @property
    def refiner(self) -> Any:
        """The frozen PoserNet of ``input.refiner_ckpt`` (loaded on first use), or None."""
        path = self.hparams.input["refiner_ckpt"]
        if path is None:
            return None
        if self._refiner is None:
            from ..nn import PoserNet

            # object.__setattr__: nn.Module would register it as a submodule
            object.__setattr__(self, "_refiner",
                               PoserNet.from_checkpoint(path).requires_grad_(False))
        return self._refiner

    def input_poses(self, batch: GraphBatch) -> Tensor:
        """The synchronisation input ``[E, 7]``: refined (no gradient) or the batch's."""
        refiner = self.refiner
        if refiner is None:
            return batch.edge_pose
        refiner.to(batch.edge_pose.device).eval()
        with torch.no_grad():
            return refiner(batch).to(batch.edge_pose.dtype)

    def setup(self, stage: str) -> None:
        _ = self.refiner  # a bad refiner_ckpt fails before the first step

    # ------------------------------------------------------------------ inference
    def forward(self, batch: GraphBatch, edge_pose: Tensor | None = None,
                return_all: bool = False) -> Tensor | list[Tensor]:
        """Absolute world-to-camera poses ``[N, 4, 4]`` (float64) of a batch, from
        ``edge_pose`` (default: :meth:`input_poses`)."""
        if edge_pose is None:
            edge_pose = self.input_poses(batch)
        return self.net(batch, edge_pose, return_all=return_all)

    # ------------------------------------------------------------------ steps
    def _step(self, batch: GraphBatch, split: str) -> Tensor:
        if batch.pose_gt is None:
            raise ValueError(f"{split} batch has no 'pose_gt': cannot compute the loss")
        edge_pose = self.input_poses(batch)
        init = self.net.initial_poses(batch, edge_pose)
        outs = self.net(batch, edge_pose, init_pose=init, return_all=True)
        hp = self.hparams.loss
        pairs = all_pairs(batch.ptr)
        out = learned_sync_loss(outs, batch.pose_gt, batch.ptr, hp["gamma"],
                                hp["translation_weight"], pairs)
        n = batch.num_graphs
        on_step = split == "train"
        sync = split != "train"
        self.log(f"{split}/loss", out.loss, batch_size=n, on_step=on_step, on_epoch=True,
                 prog_bar=True, sync_dist=sync)
        with torch.no_grad():
            start = learned_sync_loss(init, batch.pose_gt, batch.ptr, hp["gamma"],
                                      hp["translation_weight"], pairs)
        for name, value in (("rot", out.rotation), ("tdir", out.translation),
                            ("init", start.loss)):
            self.log(f"{split}/loss_{name}", value, batch_size=n, on_step=False,
                     on_epoch=True, sync_dist=sync)
        if split != "train":
            self._collect(split, batch, outs[-1].detach(), init)
        return out.loss

    # ------------------------------------------------------------------ per-graph metrics
    def _collect(self, split: str, batch: GraphBatch, poses: Tensor, init: Tensor) -> None:
        """Each graph's mean aligned absolute errors (learned, initial) for the epoch median."""
        B = batch.num_graphs
        comps = connected_components(batch.edge_index, batch.num_nodes, batch.node_batch, B)
        solved = comps.size[comps.comp] > 1
        gt = batch.pose_gt.double()
        cols = []
        for est in (poses, init):
            e = absolute_errors_per_graph(est.double(), gt, batch.node_batch, B,
                                          alignment="similarity", component=comps.comp,
                                          solved=solved)
            cols += [e["rot"], e["trans"]]
        self._store(split, torch.stack(cols, dim=-1))  # [B, 4]

    def trainable_parameters(self) -> Iterator[nn.Parameter]:
        return self.net.parameters()  # the frozen refiner is not a submodule anyway

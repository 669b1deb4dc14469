"""Out-of-distribution guard for ``posernet-refine``.

A refiner trained on one kind of graph can make other graphs much worse (the authors'-schema
test file: 10 -> 108 degrees), and a user cannot tell in advance. Two checks, no ground truth:

* **Inputs unlike the training data.** Training stores per-graph summaries of its inputs
  (:func:`input_statistics`: node attributes, rotation magnitudes, detection and matched-pair
  statistics, rotation cycle inconsistency) in the checkpoint. A refine run computes the same
  summaries and flags every feature for which a large share of its graphs falls outside the
  training range (:func:`check_inputs`). The cycle inconsistency is flagged only upwards:
  inputs *better* than the training inputs are no reason to worry.
* **Refinement made the graph less consistent.** The refined poses' rotation cycle
  inconsistency must not exceed the input's (:func:`cycle_inconsistency`).

Both are reported in one warning line (:func:`warning_line`). With a confidence head, the
model's own error scales decide per edge whether to keep the input
(:func:`keep_input_mask`, ``guard=true`` of ``posernet-refine`` and ``posernet-reconstruct``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from .graph import REF_FOCAL, REF_HEIGHT, REF_K1, REF_WIDTH, GraphBatch, ViewGraph
from .nn.adaptive import cycle_features
from .scatter import scatter_count, scatter_mean

if TYPE_CHECKING:
    from .nn import PoserNet

__all__ = ["FEATURES", "Guard", "check_inputs", "cycle_inconsistency", "graph_features",
           "graph_made_worse", "input_statistics", "keep_input_mask", "load_refiner",
           "refinement_check", "warning_line"]

#: per-graph summaries compared with the training data; the last is only flagged upwards
FEATURES = ("node_width", "node_height", "node_focal", "node_k1", "rotation_deg",
            "boxes_per_image", "box_area", "pairs_per_edge", "edges_per_node", "cycle_deg")
_UPPER_ONLY = {"cycle_deg"}
#: quantiles of the training summaries kept in the checkpoint
_LO, _HI = 0.005, 0.995
#: a feature is flagged when more than this share of the input graphs lies outside the
#: training range widened by ``_MARGIN`` of its width on each side
_SHARE, _MARGIN = 0.25, 0.1
#: the node features are stored normalised (:func:`posernet.graph.node_attributes`); the
#: warning names them in the units a user knows (pixels, the distortion coefficient)
_DISPLAY = {
    "node_width": lambda v: (v + 1.0) * REF_WIDTH,
    "node_height": lambda v: (v + 1.0) * REF_HEIGHT,
    "node_focal": lambda v: (v + 1.0) * REF_FOCAL,
    "node_k1": lambda v: v * REF_K1,
}


def cycle_inconsistency(batch: GraphBatch, edge_pose: Tensor) -> Tensor:
    """Per-graph mean rotation cycle discrepancy (degrees) over edges on a triangle ``[B]``
    (0 for a graph without triangles)."""
    cyc = cycle_features(batch.edge_index, edge_pose, batch.num_nodes)
    has = cyc[:, 2] > 0
    eb = batch.edge_batch[has]
    mean = scatter_mean(torch.rad2deg(cyc[has, 0])[:, None], eb, 0, batch.num_graphs)[:, 0]
    return mean


def graph_made_worse(batch: GraphBatch, edge_pose: Tensor, refined: Tensor,
                     tolerance_deg: float = 0.5) -> Tensor:
    """``[B]`` booleans: graphs whose refined poses have a larger mean rotation cycle
    discrepancy than their input (by more than ``tolerance_deg``). Ground-truth free."""
    before = cycle_inconsistency(batch, edge_pose)
    after = cycle_inconsistency(batch, refined.to(edge_pose.dtype))
    return after > before + tolerance_deg


def graph_features(batch: GraphBatch, edge_pose: Tensor | None = None) -> Tensor:
    """The :data:`FEATURES` of every graph of ``batch`` ``[B, F]`` (``edge_pose`` defaults to
    the batch's input poses)."""
    pose = batch.edge_pose if edge_pose is None else edge_pose
    B, dt = batch.num_graphs, torch.float64
    nb, eb = batch.node_batch, batch.edge_batch
    node = scatter_mean(batch.node_attr.to(dt), nb, 0, B)  # [B, 4]
    q = pose[:, :4].to(dt)
    rot = torch.rad2deg(2.0 * torch.atan2(q[:, 1:].norm(dim=-1), q[:, 0].abs()))
    rot_g = scatter_mean(rot[:, None], eb, 0, B)[:, 0]
    n_nodes = scatter_count(nb, B).to(dt).clamp_min(1.0)
    n_edges = scatter_count(eb, B).to(dt)
    det_g = nb[batch.det_node]
    boxes = scatter_count(det_g, B).to(dt) / n_nodes
    box = batch.det_box.to(dt)
    area = scatter_mean((box[:, 2] * box[:, 3])[:, None], det_g, 0, B)[:, 0]
    pairs = scatter_count(eb[batch.pair_edge], B).to(dt) / n_edges.clamp_min(1.0)
    cyc = cycle_inconsistency(batch, pose).to(dt)
    return torch.stack((node[:, 0], node[:, 1], node[:, 2], node[:, 3], rot_g, boxes, area,
                        pairs, n_edges / n_nodes, cyc), dim=-1)


def _batches(graphs: Sequence[ViewGraph], size: int = 256) -> list[GraphBatch]:
    return [GraphBatch.from_graphs(graphs[i:i + size]) for i in range(0, len(graphs), size)]


def input_statistics(graphs: Sequence[ViewGraph]) -> dict[str, Any]:
    """Plain-float summary of training inputs for the checkpoint: per feature the
    ``[0.5%, 99.5%]`` quantiles of the per-graph values and their median."""
    if not graphs:
        raise ValueError("input_statistics: no graphs")
    feats = torch.cat([graph_features(b) for b in _batches(list(graphs))])
    lo = torch.quantile(feats, _LO, dim=0)
    hi = torch.quantile(feats, _HI, dim=0)
    med = feats.median(dim=0).values
    return {"features": list(FEATURES), "graphs": int(feats.shape[0]),
            "lo": lo.tolist(), "hi": hi.tolist(), "median": med.tolist()}


def check_inputs(stats: Mapping[str, Any] | None, graphs: Sequence[ViewGraph]) -> list[str]:
    """Reasons why ``graphs`` look unlike the training inputs described by ``stats`` (empty
    when they look alike, or when the checkpoint has no statistics)."""
    if not stats or not graphs:
        return []
    names = list(stats["features"])
    lo = torch.tensor(stats["lo"], dtype=torch.float64)
    hi = torch.tensor(stats["hi"], dtype=torch.float64)
    feats = torch.cat([graph_features(b) for b in _batches(list(graphs))])
    if feats.shape[1] != len(names):
        raise ValueError(f"checkpoint input statistics name {len(names)} features, this "
                         f"posernet computes {feats.shape[1]}")
    width = (hi - lo).clamp_min(1e-6)
    lo_m, hi_m = lo - _MARGIN * width, hi + _MARGIN * width
    above = feats > hi_m
    below = feats < lo_m
    reasons = []
    for k, name in enumerate(names):
        out = above[:, k] if name in _UPPER_ONLY else (above[:, k] | below[:, k])
        share = float(out.double().mean())
        if share > _SHARE:
            show = _DISPLAY.get(name, float)
            med, a, b = (show(float(v)) for v in (feats[:, k].median(), lo[k], hi[k]))
            reasons.append(f"{name} median {med:.4g} outside the training range "
                           f"[{a:.4g}, {b:.4g}] in {100 * share:.0f}% of the graphs")
    return reasons


def keep_input_mask(sigma: Tensor) -> Tensor:
    """Where the model's own confidence says refinement would not help: ``[E, 2]`` booleans
    (rotation, direction), True where the predicted error of the input is smaller than that
    of the output. ``sigma [E, 4]`` in :data:`posernet.nn.adaptive.CONFIDENCE_NAMES` order."""
    if sigma.ndim != 2 or sigma.shape[1] != 4:
        raise ValueError(f"sigma must be [E, 4], got {tuple(sigma.shape)}")
    return torch.stack((sigma[:, 2] < sigma[:, 0], sigma[:, 3] < sigma[:, 1]), dim=-1)


def warning_line(reasons: Sequence[str], cycle_in: float, cycle_out: float,
                 tolerance_deg: float = 0.5) -> str | None:
    """One warning line, or ``None`` when nothing is wrong. ``cycle_in`` / ``cycle_out``: mean
    per-graph cycle inconsistency (degrees) of input and refined poses."""
    parts = list(reasons)
    if math.isfinite(cycle_in) and math.isfinite(cycle_out) and \
            cycle_out > cycle_in + tolerance_deg:
        parts.append(f"refined poses are less cycle-consistent than the input "
                     f"({cycle_out:.2f} vs {cycle_in:.2f} deg mean triangle discrepancy)")
    if not parts:
        return None
    return ("WARNING: input unlike this model's training data or made worse by it; refinement "
            "may not help (consider guard=true): " + "; ".join(parts))


def refinement_check(
    stats: Mapping[str, Any] | None, graphs: Sequence[ViewGraph],
    edge_pose: Mapping[str, Sequence[Tensor]],
) -> tuple[str | None, dict[str, Any]]:
    """Both checks for one refine run: the warning line (or ``None``) and a JSON-ready record.

    ``stats``: the checkpoint's training-input statistics (``None``: only the cycle check);
    ``edge_pose``: per stage (``initial``, ``refined``) the ``[E_g, 7]`` poses of each graph,
    as :class:`posernet.refinement.RefineResult` holds them.
    """
    reasons = check_inputs(stats, graphs)
    batch = GraphBatch.from_graphs(list(graphs))  # one batched pass, no loop over graphs
    cyc = {stage: float(cycle_inconsistency(batch, torch.cat(list(poses))
                                            .to(batch.edge_pose.dtype)).mean())
           for stage, poses in edge_pose.items()}
    line = warning_line(reasons, cyc["initial"], cyc.get("refined", float("nan")))
    return line, {"training_stats": stats is not None, "reasons": reasons,
                  "cycle_deg": cyc, "warning": line}


@dataclass(frozen=True)
class Guard:
    """The guard of one refine run: the training-input statistics of the model's checkpoint
    (``None`` when it stores none) and whether to keep the input where the model's confidence
    says refinement would not help (``keep_inputs``, the commands' ``guard=true``)."""

    stats: Mapping[str, Any] | None
    keep_inputs: bool = False

    def check(self, graphs: Sequence[ViewGraph], result: Any) -> tuple[str | None, dict[str, Any]]:
        """:func:`refinement_check` of a refine run's ``result`` (a
        :class:`posernet.refinement.RefineResult`) on ``graphs``."""
        return refinement_check(self.stats, graphs, result.edge_pose)


def load_refiner(path: str | os.PathLike[str], map_location: Any = "cpu",
                 keep_inputs: bool = False) -> tuple[PoserNet, Guard]:
    """The network of checkpoint ``path`` (eval mode) and its :class:`Guard`, from one reading
    of the file. ``path`` is a path or a shipped checkpoint's name (``"shipped"``,
    ``"shipped:NAME"``, a shipped file's name: :func:`posernet.checkpoints.resolve_checkpoint`).
    ``keep_inputs`` needs a confidence head: ``ValueError`` naming the checkpoint otherwise; a
    bad checkpoint or unknown name raises :class:`posernet.checkpoints.CheckpointError`."""
    from .checkpoints import read_checkpoint
    from .nn import PoserNet

    ckpt = read_checkpoint(path)
    model = PoserNet.from_checkpoint_dict(ckpt, path).to(map_location).eval()
    if keep_inputs and not getattr(model, "confidence", False):
        raise ValueError(f"guard=true needs a checkpoint with a confidence head "
                         f"(net.confidence=true); {path} has none")
    return model, Guard((ckpt.get("posernet") or {}).get("input_stats"), bool(keep_inputs))

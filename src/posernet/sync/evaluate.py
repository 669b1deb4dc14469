"""The paper's absolute-pose table (Table 3 format) for a backend on a batch of graphs.

:func:`absolute_table` runs a backend, aligns every graph's estimate to its ground truth
(per connected component; cameras that could not be placed are counted, take no part in the
alignment and are left out of their graph's mean error; a graph with none placed is left out
of the rows) and summarises per-graph mean errors as the percentage of graphs under
3/5/10/30/45 degrees and 0.05/0.1/0.25/0.5/0.75 m plus the medians. Errors and rows come from
the shared table code (:func:`posernet.metrics.absolute_errors_per_graph`,
:func:`posernet.metrics.absolute_rows`). The returned dict records the alignment and the
translation-scale policy (``oracle`` is flagged) so every table can state them.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ..graph import GraphBatch, ViewGraph
from ..metrics import ALIGNMENTS, ThresholdRow, absolute_errors_per_graph, absolute_rows
from .backend import SyncBackend, SyncResult, graph_structure

__all__ = ["absolute_table", "format_absolute_table"]


def absolute_table(batch: GraphBatch | ViewGraph, edge_pose: Tensor | None = None,
                   backend: SyncBackend | str = "eig_se3", alignment: str = "auto",
                   per_component: bool = True, rotation_gauge: str = "rotations",
                   **backend_options: Any) -> dict[str, Any]:
    """Absolute-pose errors of ``backend`` on ``batch`` in the paper's table format.

    ``edge_pose [E, 7]`` relative poses (default ``batch.edge_pose``); ``backend`` an instance
    or a registered name (``backend_options`` then go to its constructor); ``alignment``
    ``"similarity"``, ``"rigid"`` or ``"auto"`` (rigid when the backend's translations are
    metric, i.e. scale ``given``/``oracle``; similarity otherwise). Needs ``batch.pose_gt``.

    Returns a dict with ``rotation_deg`` and ``position_m`` (:class:`ThresholdRow`),
    ``alignment``, ``scale``, ``oracle``, ``backend`` (its ``describe()``), ``graphs``,
    ``cameras``, ``cameras_placed``, ``unlocalised_cameras`` (= cameras - placed),
    ``graphs_with_unplaced``, ``disconnected_graphs``, ``unconverged_graphs``, ``per_graph``
    (the per-graph mean errors over placed cameras, and ``unplaced`` cameras per graph) and
    ``result`` (the :class:`SyncResult`).
    """
    if isinstance(backend, str):
        from . import get_backend

        backend = get_backend(backend, **backend_options)
    elif backend_options:
        raise ValueError("backend options are only accepted together with a backend name")
    if getattr(batch, "pose_gt", None) is None:
        raise ValueError("absolute_table needs ground-truth absolute poses (batch.pose_gt)")
    if alignment == "auto":
        alignment = "rigid" if backend.metric else "similarity"
    if alignment not in ALIGNMENTS:
        raise ValueError(f"alignment={alignment!r}; choose one of {['auto', *ALIGNMENTS]}")
    res: SyncResult = backend.solve_with_info(batch, edge_pose)
    struct = graph_structure(batch)
    B = struct["num_graphs"]
    gt = batch.pose_gt.to(res.poses.device)
    errs = absolute_errors_per_graph(res.poses, gt, struct["node_batch"], B,
                                     alignment=alignment,
                                     component=res.component if per_component else None,
                                     solved=res.solved, rotation_gauge=rotation_gauge)
    rows = absolute_rows(errs)
    unplaced = errs["unplaced"]
    comps_per_graph = torch.zeros(B, dtype=torch.long, device=res.component.device)
    comps_per_graph.scatter_reduce_(0, struct["node_batch"], res.component, reduce="amax")
    first = torch.full((B,), res.component.numel(), dtype=torch.long,
                       device=res.component.device)
    first.scatter_reduce_(0, struct["node_batch"], res.component, reduce="amin")
    return {
        "rotation_deg": rows["rot"],
        "position_m": rows["trans"],
        "alignment": alignment,
        "rotation_gauge": rotation_gauge,
        "per_component": per_component,
        "scale": res.scale,
        "oracle": res.scale == "oracle",
        "backend": backend.describe(),
        "graphs": B,
        "cameras": int(res.solved.numel()),
        "cameras_placed": int(res.solved.bool().sum()),
        "unlocalised_cameras": int((~res.solved.bool()).sum()),
        "graphs_with_unplaced": int((unplaced > 0).sum()),
        "disconnected_graphs": int((comps_per_graph > first).sum()),
        "unconverged_graphs": int((~res.converged).sum()),
        "per_graph": {"rotation_deg": errs["rot"], "position_m": errs["trans"],
                      "unplaced": unplaced},
        "result": res,
    }


def _row(label: str, row: ThresholdRow, unit: str) -> str:
    cells = [f"{p:.2f}" for p in row.percent_below]
    return f"| {label} ({unit}) | " + " | ".join(cells) + f" | {row.median:.3f} | {row.count} |"


def format_absolute_table(table: dict[str, Any], title: str | None = None) -> str:
    """Markdown rendering of :func:`absolute_table`'s result (two rows: rotation, position)."""
    b = table["backend"]
    head = title or f"Absolute poses: {b['backend']}"
    lines = [
        f"**{head}** -- scale: {b['scale_label']}; alignment: {table['alignment']}"
        + (" per connected component" if table.get("per_component") else "")
        + f"; rotations aligned by the {table.get('rotation_gauge', 'rotations')}"
        + (" -- **ORACLE**" if table["oracle"] else ""),
        "",
        "| error | " + " | ".join(f"<{t:g}" for t in table["rotation_deg"].thresholds)
        + " | median | graphs |",
        "|---" * (len(table["rotation_deg"].thresholds) + 3) + "|",
        _row("rotation", table["rotation_deg"], "deg"),
        "| error | " + " | ".join(f"<{t:g}" for t in table["position_m"].thresholds)
        + " | median | graphs |",
        _row("position", table["position_m"], "m"),
    ]
    if "cameras" in table:
        lines += ["", f"Cameras placed: {table['cameras_placed']} of {table['cameras']}."]
    notes = []
    if table["unlocalised_cameras"]:
        notes.append(f"{table['unlocalised_cameras']} camera(s) in "
                     f"{table.get('graphs_with_unplaced', '?')} graph(s) were not localised "
                     "(no edge, or an unsolvable component): they have no pose and are left "
                     "out of their graph's mean error, a graph with none placed is left out of "
                     "the rows")
    if table["disconnected_graphs"]:
        notes.append(f"{table['disconnected_graphs']} graph(s) are disconnected; each "
                     "component was aligned on its own")
    if table["unconverged_graphs"]:
        notes.append(f"{table['unconverged_graphs']} graph(s) hit the IRLS iteration limit")
    if notes:
        lines += ["", "Notes: " + "; ".join(notes) + "."]
    return "\n".join(lines)

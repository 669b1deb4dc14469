"""The one evaluation path of a refine result: per-graph relative and absolute errors of every
stage against the ground truth (:func:`evaluate_result`) and the paper's threshold tables
(:func:`result_tables`), used by ``posernet-refine``, ``-eval``, ``-demo``, ``-reconstruct`` and
the experiments."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from .graph import GraphValidationError
from .metrics import (
    absolute_errors_per_graph,
    absolute_rows,
    relative_errors_per_graph,
    relative_rows,
    unplaced_per_graph,
)
from .refinement import RefineResult

__all__ = ["evaluate_result", "result_tables"]


def _global_components(per_graph: Sequence[Tensor]) -> Tensor:
    """Renumber each graph's component ids 0..k-1 and offset them so no two graphs share one."""
    out, offset = [], 0
    for c in per_graph:
        local = torch.unique(c, return_inverse=True)[1] if c.numel() else c
        out.append(local + offset)
        offset += int(local.max()) + 1 if c.numel() else 0
    return torch.cat(out)


def evaluate_result(result: RefineResult, rotation_gauge: str = "rotations") -> dict[str, Any]:
    """Per-graph errors and threshold rows for every stage present, where ground truth exists.

    Returns ``{"relative": {stage: {"rot": ThresholdRow, "tdir": ThresholdRow}},
    "absolute": {stage: {"rot": ..., "trans": ...}}, "per_graph": {...}, "alignment": str,
    "placed": {stage: {...}}, "graphs": B, "graphs_without_gt": {"relative": n, "absolute": n}}``.
    ``rotation_gauge`` (``centres`` or ``rotations``) picks how absolute rotations are aligned
    (:func:`posernet.metrics.absolute_pose_errors`).

    What is not measurable is skipped and counted, never scored:

    * Relative errors need ``edge_pose_gt``; a graph without it gets NaN per-graph errors (left
      out of the rows) and is counted in ``graphs_without_gt["relative"]``. An edge whose
      estimated or true translation has zero length has no direction: it is left out of its
      graph's mean and counted (``ThresholdRow.skipped``, ``per_graph["rel_tdir_skipped_*"]``).
    * Absolute errors need ``pose_gt`` and a backend; graphs without ``pose_gt`` are counted in
      ``graphs_without_gt["absolute"]``. A camera the backend could not place (``solved``
      False: no edge, or an unsolvable component) has no pose: it takes no part in the
      alignment, a graph's error is the mean over its *placed* cameras, and the unplaced ones
      are counted per graph (``per_graph["abs_unplaced_*"]``) and per stage (``placed``:
      ``cameras``, ``placed``, ``graphs_with_unplaced``, ``graphs_with_none_placed``; a graph
      with no camera placed has NaN errors and is left out of the rows).

    Raises :class:`GraphValidationError` when no graph has any ground truth to measure.
    """
    graphs = result.graphs
    B = len(graphs)
    rel_idx = [k for k, g in enumerate(graphs) if g.edge_pose_gt is not None]
    abs_idx = [k for k, g in enumerate(graphs) if g.pose_gt is not None]
    if not rel_idx and not (result.absolute and abs_idx):
        raise GraphValidationError(
            f"none of the {B} graph(s) has ground truth (edge_pose_gt"
            f"{' or pose_gt' if result.absolute else ''}), e.g. {graphs[0].name!r}; "
            "cannot measure errors")
    out: dict[str, Any] = {"relative": {}, "absolute": {}, "per_graph": {}, "graphs": B,
                           "graphs_without_gt": {"relative": B - len(rel_idx),
                                                 "absolute": B - len(abs_idx)}}
    nan = torch.full((B,), float("nan"), dtype=torch.float64)
    if rel_idx:
        sel = torch.tensor(rel_idx)
        gt = torch.cat([graphs[k].edge_pose_gt.cpu() for k in rel_idx])
        eb = sel.repeat_interleave(torch.tensor([graphs[k].num_edges for k in rel_idx]))
        for s, poses in result.edge_pose.items():
            est = torch.cat([poses[k] for k in rel_idx]).to(gt.dtype)
            rel = relative_errors_per_graph(est, gt, eb, B)
            for key, v in rel.items():  # rel_rot_*, rel_tdir_*, rel_rot_skipped_*, ...
                out["per_graph"][f"rel_{key}_{s}"] = v
            out["relative"][s] = relative_rows(rel)
    if result.absolute and abs_idx:
        metric = bool(result.backend and result.backend.get("scale") in ("given", "oracle"))
        out["alignment"] = "rigid" if metric else "similarity"
        out["rotation_gauge"] = rotation_gauge
        out["placed"] = {}
        sel = torch.tensor(abs_idx)
        n_nodes = torch.tensor([graphs[k].num_nodes for k in abs_idx])
        nb = sel.repeat_interleave(n_nodes)
        gt = torch.cat([graphs[k].pose_gt.cpu() for k in abs_idx]).double()
        all_nb = torch.arange(B).repeat_interleave(torch.tensor([g.num_nodes for g in graphs]))
        for s, poses in result.absolute.items():
            solved = [result.solved[s][k].bool() for k in range(B)]
            comp = _global_components([result.component[s][k] for k in abs_idx])
            abs_err = absolute_errors_per_graph(
                torch.cat([poses[k] for k in abs_idx]).double(), gt, nb, B,
                alignment=out["alignment"], component=comp,
                solved=torch.cat([solved[k] for k in abs_idx]), rotation_gauge=rotation_gauge)
            # Unplaced cameras are counted in every graph, with ground truth or not.
            unplaced = unplaced_per_graph(torch.cat(solved), all_nb, B)
            out["per_graph"][f"abs_rot_{s}"] = abs_err["rot"]
            out["per_graph"][f"abs_pos_{s}"] = abs_err["trans"]
            out["per_graph"][f"abs_unplaced_{s}"] = unplaced
            placed_k = n_nodes - unplaced[sel]
            out["placed"][s] = {"cameras": int(n_nodes.sum()), "placed": int(placed_k.sum()),
                                "graphs_with_unplaced": int((placed_k < n_nodes).sum()),
                                "graphs_with_none_placed": int((placed_k == 0).sum())}
            out["absolute"][s] = absolute_rows(abs_err)
    for s in result.edge_pose:  # keep the per-graph keys present, NaN where not measured
        for key in ("rel_rot", "rel_tdir"):
            out["per_graph"].setdefault(f"{key}_{s}", nan.clone())
    return out


def result_tables(evaluation: dict[str, Any], label: str = "KP",
                  backend: dict[str, Any] | None = None, title: str = "",
                  units: str = "m") -> dict[str, Any]:
    """Paper-style :class:`~posernet.report.ResultTable`\\ s from :func:`evaluate_result`.

    ``relative`` (Table 1 layout: initial vs PoserNet) and, with motion averaging,
    ``absolute`` (Table 3 layout), whose note states the scale policy and alignment and whose
    rows count the cameras placed (``Cameras placed: k of n``; errors are over placed cameras).
    Graphs without ground truth and edges without a measurable error are counted in the notes.
    ``units`` names the ground truth's length unit in the translation columns' title: ``"m"``
    for the datasets' graphs; photos' pose files carry none (a DTU scan's are millimetres).
    """
    from .report import ResultTable, TableRow, absolute_groups

    names = {"initial": "Initial", "refined": "PoserNet"}
    B = evaluation.get("graphs")
    missing = evaluation.get("graphs_without_gt", {})

    def unscored(kind: str, what: str) -> str | None:
        n = int(missing.get(kind, 0))
        return (f"{n} of {B} graph(s) have no ground-truth {what} and are not scored."
                if n else None)

    tables: dict[str, Any] = {}
    if evaluation.get("relative"):
        tables["relative"] = ResultTable(
            rows=[TableRow((label, names[s]), cells) for s, cells in
                  evaluation["relative"].items()],
            title=f"Relative poses{title}", note=unscored("relative", "relative poses"))
    if evaluation.get("absolute"):
        bname = (backend or {}).get("backend", "sync")
        base = {"initial": bname, "refined": f"{bname} + PoserNet"}
        if (backend or {}).get("confidence_weights"):
            base["initial"] = f"{bname} (weighted by PoserNet's confidence)"

        def stage_name(s: str) -> str:  # "<stage>+ba": bundle adjustment after averaging
            head, _, tail = s.partition("+")
            return base.get(head, head) + (" + BA" if tail == "ba" else "")

        gauge = ("rotations aligned by the rotations" if evaluation.get("rotation_gauge") ==
                 "rotations" else "rotations aligned with the centres")
        note = (f"Scale: {(backend or {}).get('scale_label', 'unknown')}; alignment: "
                f"{evaluation.get('alignment')} (Umeyama on camera centres) per connected "
                f"component; {gauge}")
        extra = unscored("absolute", "camera poses")
        if extra:
            note += "\n" + extra
        placed = evaluation.get("placed", {})

        def count(s: str) -> tuple[int, int] | None:
            p = placed.get(s)
            return (int(p["placed"]), int(p["cameras"])) if p else None

        tables["absolute"] = ResultTable(
            rows=[TableRow((label, stage_name(s)), cells, placed=count(s)) for s, cells in
                  evaluation["absolute"].items()],
            groups=absolute_groups(units),
            title=f"Absolute poses after motion averaging{title}",
            note=note)
    return tables

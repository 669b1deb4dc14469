"""One implementation of the paper's tables: every caller gets its rows from posernet.metrics."""

from __future__ import annotations

import math

import torch

from posernet import GraphBatch
from posernet.evaluation import evaluate_result
from posernet.metrics import (
    ANGLE_THRESHOLDS_DEG,
    METRE_THRESHOLDS,
    absolute_errors_per_graph,
    absolute_rows,
    per_graph_mean,
    relative_errors_per_graph,
    relative_pose_errors,
    relative_rows,
    skipped_per_graph,
    threshold_row,
    unplaced_per_graph,
)
from posernet.refinement import refine_graphs
from posernet.report import relative_row
from posernet.sync import get_backend
from posernet.testing import random_view_graph


def _graphs(n: int, seed: int = 0) -> list:
    gen = torch.Generator().manual_seed(seed)
    return [random_view_graph(num_nodes=5 + i % 3, extra_edges=3, generator=gen, name=f"t{i}")
            for i in range(n)]


def _same_row(a, b) -> None:
    assert a.thresholds == b.thresholds and a.count == b.count and a.skipped == b.skipped
    for x, y in zip((*a.percent_below, a.median), (*b.percent_below, b.median), strict=True):
        assert (math.isnan(x) and math.isnan(y)) or x == y


def test_relative_per_graph_errors_and_rows_are_the_building_blocks():
    b = GraphBatch.from_graphs(_graphs(4))
    est = b.edge_pose.clone()
    est[0, 4:] = 0.0  # a zero-length translation: no direction, skipped and counted
    per_graph = relative_errors_per_graph(est, b.edge_pose_gt, b.edge_batch, b.num_graphs)
    rot, tdir = relative_pose_errors(est, b.edge_pose_gt)
    assert torch.equal(per_graph["rot"], per_graph_mean(rot, b.edge_batch, b.num_graphs))
    assert torch.equal(per_graph["tdir"], per_graph_mean(tdir, b.edge_batch, b.num_graphs))
    assert torch.equal(per_graph["tdir_skipped"],
                       skipped_per_graph(tdir, b.edge_batch, b.num_graphs))
    assert int(per_graph["tdir_skipped"].sum()) == 1
    rows = relative_rows(per_graph)
    _same_row(rows["rot"], threshold_row(per_graph["rot"], ANGLE_THRESHOLDS_DEG))
    _same_row(rows["tdir"], threshold_row(per_graph["tdir"], ANGLE_THRESHOLDS_DEG, skipped=1))
    # report.relative_row is the same rows for per-graph errors given without skip counts
    row = relative_row(("KP", "Initial"), per_graph["rot"], per_graph["tdir"])
    _same_row(row.cells["rot"], rows["rot"])
    assert row.cells["tdir"].skipped == 0


def test_absolute_rows_and_unplaced_counts():
    per_graph = {"rot": torch.tensor([1.0, 4.0, float("nan")]),
                 "trans": torch.tensor([0.01, 0.3, float("nan")])}
    rows = absolute_rows(per_graph)
    _same_row(rows["rot"], threshold_row(per_graph["rot"], ANGLE_THRESHOLDS_DEG))
    _same_row(rows["trans"], threshold_row(per_graph["trans"], METRE_THRESHOLDS))
    solved = torch.tensor([True, False, True, False, False])
    nb = torch.tensor([0, 0, 1, 2, 2])
    assert unplaced_per_graph(solved, nb, 4).tolist() == [1, 0, 2, 0]


def test_refine_pipeline_and_batch_evaluation_give_the_same_tables():
    """evaluate_result on all graphs at once and a per-batch accumulation of the per-graph
    errors give identical rows on the same graphs."""
    gs = _graphs(5, seed=3)
    backend = get_backend("eig_se3")
    ev = evaluate_result(refine_graphs(None, gs, backend=backend, batch_size=5, progress=False))
    # posernet-eval: per batch, concatenated, then the rows
    parts: dict[str, list[torch.Tensor]] = {}
    abs_parts: dict[str, list[torch.Tensor]] = {"rot": [], "trans": []}
    for i in range(0, len(gs), 2):
        b = GraphBatch.from_graphs(gs[i:i + 2])
        for k, v in relative_errors_per_graph(b.edge_pose, b.edge_pose_gt, b.edge_batch,
                                              b.num_graphs).items():
            parts.setdefault(k, []).append(v)
        part = evaluate_result(refine_graphs(None, gs[i:i + 2], backend=backend,
                                             progress=False))
        abs_parts["rot"].append(part["per_graph"]["abs_rot_initial"])
        abs_parts["trans"].append(part["per_graph"]["abs_pos_initial"])
    rel = relative_rows({k: torch.cat(v) for k, v in parts.items()})
    for key in ("rot", "tdir"):
        _same_row(rel[key], ev["relative"]["initial"][key])
    ab = absolute_rows({k: torch.cat(v) for k, v in abs_parts.items()})
    for key in ("rot", "trans"):
        a, e = ab[key], ev["absolute"]["initial"][key]
        assert a.count == e.count
        assert torch.allclose(torch.tensor([*a.percent_below, a.median]),
                              torch.tensor([*e.percent_below, e.median]), atol=1e-9)
    # the rows are the absolute_rows of the per-graph errors, computed directly
    b = GraphBatch.from_graphs(gs)
    res = backend.solve_with_info(b, b.edge_pose)
    direct = absolute_errors_per_graph(res.poses, b.pose_gt, b.node_batch, b.num_graphs,
                                       alignment=ev["alignment"], component=res.component,
                                       solved=res.solved)
    assert torch.equal(direct["rot"], ev["per_graph"]["abs_rot_initial"])
    _same_row(ev["absolute"]["initial"]["rot"], absolute_rows(direct)["rot"])
    _same_row(ev["absolute"]["initial"]["trans"], absolute_rows(direct)["trans"])

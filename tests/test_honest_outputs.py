"""Outputs never invent what was not measured: unplaced cameras have no pose and are counted,
inputs without ground truth are refined but not scored, zero-length translations are not
perfect directions."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys

import pytest
import torch

from posernet import geometry as G
from posernet.data import load_posernet_json, save_posernet_json
from posernet.data.inputs import load_input_graphs
from posernet.evaluation import evaluate_result, result_tables
from posernet.graph import GraphValidationError, ViewGraph
from posernet.metrics import (
    per_graph_mean,
    relative_pose_errors,
    skipped_per_graph,
    threshold_row,
    translation_direction_error_deg,
)
from posernet.refinement import refine_graphs, result_to_json
from posernet.report import ResultTable
from posernet.sync import get_backend
from posernet.testing import random_view_graph

F64 = torch.float64


def exact_graph(seed: int, n: int = 6, name: str | None = None) -> ViewGraph:
    """A graph whose initial poses are the exact relative poses (metric translations)."""
    g = random_view_graph(num_nodes=n, extra_edges=3, generator=torch.Generator().manual_seed(seed),
                          dtype=F64, name=name or f"g{seed}")
    return dataclasses.replace(g, edge_pose=g.edge_pose_gt.clone())


def with_isolated_camera(g: ViewGraph) -> ViewGraph:
    """``g`` plus one camera far away that shares no edge (motion averaging cannot place it)."""
    R = G.axis_angle_to_rotation_matrix(torch.tensor([0.3, -1.0, 0.5], dtype=F64))
    far = G.make_se3(R, torch.tensor([5.0, -3.0, 8.0], dtype=F64)).to(g.pose_gt.dtype)
    n = g.num_nodes
    return dataclasses.replace(
        g, node_attr=torch.cat((g.node_attr, g.node_attr[:1])), K=torch.cat((g.K, g.K[:1])),
        image_size=torch.cat((g.image_size, g.image_size[:1])),
        pose_gt=torch.cat((g.pose_gt, far[None])),
        meta={**g.meta, "camera_ids": [f"c{i}" for i in range(n + 1)]})


def strip_gt(g: ViewGraph) -> ViewGraph:
    return dataclasses.replace(g, edge_pose_gt=None, pose_gt=None,
                               estimates={k: v for k, v in g.estimates.items() if k != "gt"})


# --------------------------------------------------------------------------- unplaced cameras


@pytest.fixture(scope="module")
def unplaced_result():
    graphs = [with_isolated_camera(exact_graph(0)), exact_graph(1)]
    res = refine_graphs(None, graphs, backend=get_backend("eig_se3", scale="given"),
                        progress=False)
    assert not bool(res.solved["initial"][0][-1]) and bool(res.solved["initial"][1].all())
    return res


def test_unplaced_camera_has_no_invented_pose_in_refined_json(unplaced_result):
    rec = result_to_json(unplaced_result)
    json.dumps(rec, allow_nan=False)
    g0 = rec["graphs"][0]
    lost = g0["cameras"]["c6"]["initial"]
    assert lost == {"world_to_camera": None, "camera_to_world": None, "q_wxyz": None, "t": None,
                    "solved": False, "component": None}
    placed = g0["cameras"]["c0"]["initial"]
    assert placed["solved"] and len(placed["world_to_camera"]) == 4
    assert g0["cameras_placed"] == {"initial": 6}
    assert rec["cameras_placed"] == {"initial": {"placed": 12, "cameras": 13}}


def test_unplaced_cameras_are_counted_not_scored(unplaced_result):
    ev = evaluate_result(unplaced_result)
    assert ev["placed"]["initial"] == {"cameras": 13, "placed": 12, "graphs_with_unplaced": 1,
                                       "graphs_with_none_placed": 0}
    assert ev["per_graph"]["abs_unplaced_initial"].tolist() == [1, 0]
    # The per-graph error is over the placed cameras (exact input: zero); the identity pose the
    # backend leaves on the unplaced camera would be ~100 degrees / metres off.
    assert float(ev["per_graph"]["abs_rot_initial"].max()) < 1e-3
    assert float(ev["per_graph"]["abs_pos_initial"].max()) < 1e-4
    assert ev["absolute"]["initial"]["rot"].count == 2
    table = result_tables(ev, backend=unplaced_result.backend)["absolute"]
    md = table.to_markdown()
    assert "Cameras placed: 12 of 13 in every row (errors are means over each graph's placed " \
           "cameras" in md
    header, row = table.to_csv().splitlines()
    cols = dict(zip(header.split(","), row.split(","), strict=True))
    assert (cols["cameras_placed"], cols["cameras"]) == ("12", "13")


def test_a_graph_with_no_camera_placed_is_left_out_and_counted():
    g = exact_graph(2)
    res = refine_graphs(None, [g, exact_graph(3)], backend=get_backend("eig_se3", scale="given"),
                        progress=False)
    res.solved["initial"][0] = torch.zeros_like(res.solved["initial"][0])
    ev = evaluate_result(res)
    assert ev["placed"]["initial"]["graphs_with_none_placed"] == 1
    assert math.isnan(float(ev["per_graph"]["abs_rot_initial"][0]))
    assert ev["absolute"]["initial"]["rot"].count == 1
    md = result_tables(ev, backend=res.backend)["absolute"].to_markdown()
    assert "Cameras placed: 6 of 12" in md and "a graph with none placed is left out" in md


def test_tables_with_every_camera_placed_print_as_before_plus_the_count():
    graphs = [exact_graph(4), exact_graph(5)]
    res = refine_graphs(None, graphs, backend=get_backend("eig_se3", scale="given"),
                        progress=False)
    tables = result_tables(evaluate_result(res), backend=res.backend)
    md = tables["absolute"].to_markdown()
    assert "Cameras placed: 12 of 12 in every row." in md
    old = ResultTable(rows=[dataclasses.replace(r, placed=None) for r in tables["absolute"].rows],
                      groups=tables["absolute"].groups, title=tables["absolute"].title,
                      note=tables["absolute"].note).to_markdown()
    assert md.replace("Cameras placed: 12 of 12 in every row.\n", "") == old
    assert "Left out" not in md and "not scored" not in md
    assert tables["relative"].note is None and "Left out" not in tables["relative"].to_markdown()


def test_absolute_table_counts_placed_cameras():
    g = with_isolated_camera(exact_graph(6))
    res = refine_graphs(None, [g], backend=get_backend("eig_se3", scale="given"),
                        progress=False)
    ev = evaluate_result(res)
    assert (ev["placed"]["initial"]["placed"], ev["placed"]["initial"]["cameras"]) == (6, 7)
    md = result_tables(ev, backend=res.backend)["absolute"].to_markdown()
    assert "Cameras placed: 6 of 7" in md and "unplaced cameras have no pose" in md


# --------------------------------------------------------------------------- zero-length vectors


def test_zero_length_translation_is_not_a_perfect_direction():
    t = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0]])
    ref = torch.tensor([[1.0, 0, 0], [0.0, 0, 0], [2.0, 0, 0]])
    err = translation_direction_error_deg(t, ref)
    assert err is not None and torch.isnan(err[:2]).all() and float(err[2]) == 0.0
    assert torch.isnan(G.translation_direction_error_deg(t, ref)[:2]).all()
    est = torch.tensor([[1.0, 0, 0, 0, 0, 0, 0], [0.0, 0, 0, 0, 0, 1, 0],
                        [1.0, 0, 0, 0, 0, 1, 0]])
    gt = torch.tensor([[1.0, 0, 0, 0, 1, 0, 0]] * 3)
    rot, tdir = relative_pose_errors(est, gt)
    assert float(rot[0]) == 0.0 and math.isnan(float(tdir[0]))  # zero t: direction NaN
    assert math.isnan(float(rot[1]))  # zero quaternion: no rotation, NaN
    assert float(tdir[2]) == pytest.approx(90.0)


def test_per_graph_means_skip_nan_edges_and_count_them():
    v = torch.tensor([1.0, float("nan"), 3.0, float("nan")])
    b = torch.tensor([0, 0, 1, 2])
    mean = per_graph_mean(v, b, 3)
    assert mean[:2].tolist() == [1.0, 3.0] and math.isnan(float(mean[2]))
    assert skipped_per_graph(v, b, 3).tolist() == [1, 0, 1]
    row = threshold_row(mean, skipped=2)
    assert row.count == 2 and row.skipped == 2


def test_evaluation_skips_and_reports_zero_translation_edges():
    graphs = [random_view_graph(num_nodes=5, generator=torch.Generator().manual_seed(k),
                                name=f"z{k}") for k in range(2)]
    ep = graphs[0].edge_pose.clone()
    ep[0, 4:] = 0.0  # a failed estimate written as a zero translation
    graphs[0] = dataclasses.replace(graphs[0], edge_pose=ep)
    ev = evaluate_result(refine_graphs(None, graphs, progress=False))
    _, tdir = relative_pose_errors(ep[1:], graphs[0].edge_pose_gt[1:])
    assert float(ev["per_graph"]["rel_tdir_initial"][0]) == pytest.approx(float(tdir.mean()))
    assert ev["per_graph"]["rel_tdir_skipped_initial"].tolist() == [1, 0]
    assert ev["relative"]["initial"]["tdir"].skipped == 1
    assert ev["relative"]["initial"]["rot"].skipped == 0
    table = result_tables(ev)["relative"]
    assert "Left out of the per-graph means (no measurable error, e.g. a zero-length " \
           "translation): KP / Initial tdir 1." in table.to_markdown()
    header, row = table.to_csv().splitlines()
    cols = dict(zip(header.split(","), row.split(","), strict=True))
    assert cols["tdir_skipped"] == "1" and cols["rot_skipped"] == "0"


# --------------------------------------------------------------------------- no ground truth


def test_graphs_without_ground_truth_are_counted_not_scored():
    graphs = [random_view_graph(num_nodes=5, generator=torch.Generator().manual_seed(k),
                                name=f"m{k}") for k in range(3)]
    graphs[1] = strip_gt(graphs[1])
    res = refine_graphs(None, graphs, backend=get_backend("eig_se3"), progress=False)
    ev = evaluate_result(res)
    assert ev["graphs_without_gt"] == {"relative": 1, "absolute": 1}
    assert ev["relative"]["initial"]["rot"].count == 2
    assert ev["absolute"]["initial"]["rot"].count == 2
    assert math.isnan(float(ev["per_graph"]["rel_rot_initial"][1]))
    assert ev["placed"]["initial"]["cameras"] == 10
    tables = result_tables(ev, backend=res.backend)
    assert "1 of 3 graph(s) have no ground-truth relative poses and are not scored." in \
        tables["relative"].to_markdown()
    assert "1 of 3 graph(s) have no ground-truth camera poses" in tables["absolute"].to_markdown()
    with pytest.raises(GraphValidationError, match="none of the 1 graph"):
        evaluate_result(refine_graphs(None, [graphs[1]], progress=False))


def test_json_without_ground_truth_loads_and_refines(tmp_path):
    graphs = [strip_gt(random_view_graph(num_nodes=5, generator=torch.Generator().manual_seed(k),
                                         name=f"n{k}")) for k in range(2)]
    path = save_posernet_json(tmp_path / "nogt.json", {"test": graphs})
    raw = json.loads(path.read_text())
    cam = next(iter(raw["test"][0]["cameras"].values()))
    assert "camera_to_world" not in cam
    pair = next(iter(next(iter(raw["test"][0]["relative_poses"].values())).values()))
    assert "ground_truth" not in pair and "feature_5pt" in pair
    back = load_input_graphs(path)
    assert all(g.pose_gt is None and g.edge_pose_gt is None and "gt" not in g.estimates
               for g in back)
    res = refine_graphs(None, back, backend=get_backend("eig_se3"), progress=False)
    rec = result_to_json(res)
    assert len(rec["graphs"]) == 2 and rec["cameras_placed"]["initial"]["placed"] == 10
    with pytest.raises(GraphValidationError, match="has no ground truth|none of the"):
        evaluate_result(res)
    with pytest.raises(GraphValidationError, match="'ground_truth' estimate"):
        load_posernet_json(path, estimate="ground_truth")


@pytest.mark.slow
def test_refine_cli_without_ground_truth_writes_poses_and_no_tables(tmp_path):
    graphs = [strip_gt(random_view_graph(num_nodes=5, generator=torch.Generator().manual_seed(k),
                                         name=f"c{k}")) for k in range(2)]
    src = save_posernet_json(tmp_path / "nogt.json", {"test": graphs})
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "posernet.cli.refine", f"hydra.run.dir={out}",
                        f"input={src}"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    rec = json.loads((out / "refined.json").read_text())
    assert len(rec["graphs"]) == 2 and "refined" in rec["graphs"][0]["edges"][0]
    assert not list(out.glob("*table*"))
    assert "Relative poses" not in r.stdout and "0.00" not in r.stdout

"""The one evaluation path of absolute poses (posernet.evaluation): rows, labels, honesty."""

from __future__ import annotations

import dataclasses

import torch
from helpers import make_graph

from posernet.evaluation import evaluate_result, result_tables
from posernet.refinement import refine_graphs
from posernet.sync import get_backend


def _absolute(graphs, backend):
    res = refine_graphs(None, graphs, backend=backend, progress=False)
    ev = evaluate_result(res)
    return ev, result_tables(ev, backend=res.backend)["absolute"].to_markdown()


def test_noise_free_table_is_perfect_and_labelled():
    graphs = [make_graph(8, 8, seed=k) for k in range(5)]
    graphs = [dataclasses.replace(g, edge_pose=g.edge_pose_gt) for g in graphs]
    ev, md = _absolute(graphs, get_backend("eig_se3", scale="given"))
    rows = ev["absolute"]["initial"]
    assert all(v == 100.0 for r in rows.values() for v in r.percent_below)
    assert "| KP | eig_se3 |" in md and "alignment: rigid" in md and "Graphs per row: 5." in md


def test_translation_units_name_the_ground_truths():
    """Metres for the datasets' graphs; the unit a caller names (photos' pose files) else."""
    graphs = [make_graph(6, 6, seed=k) for k in range(2)]
    res = refine_graphs(None, graphs, backend=get_backend("eig_se3"), progress=False)
    ev = evaluate_result(res)
    assert "Translation error (m)" in result_tables(ev)["absolute"].to_markdown()
    md = result_tables(ev, units="ground-truth units")["absolute"].to_markdown()
    assert "Translation error (ground-truth units)" in md and "(m)" not in md


def test_oracle_and_similarity_labels():
    graphs = [make_graph(8, 8, seed=10 + k, rot_noise_deg=3.0, trans_noise=0.05)
              for k in range(6)]
    _, md = _absolute(graphs, get_backend("eig_se3", scale="oracle"))
    assert "ORACLE" in md
    ev, md = _absolute(graphs, get_backend("rotation_translation"))
    assert "alignment: similarity" in md and "ORACLE" not in md
    assert 0 < float(ev["per_graph"]["abs_rot_initial"].median()) < 10


def test_disconnected_and_isolated_are_reported():
    g = make_graph(7, 10, seed=20)
    keep = (g.edge_index < 6).all(0)
    z = torch.zeros(0, dtype=torch.long)
    g = dataclasses.replace(g, edge_index=g.edge_index[:, keep], edge_pose=g.edge_pose_gt[keep],
                            edge_pose_gt=g.edge_pose_gt[keep], pair_edge=z, pair_src=z,
                            pair_dst=z)
    ev, md = _absolute([g], get_backend("eig_se3", scale="given"))
    assert "Cameras placed: 6 of 7" in md and "per connected component" in md
    assert float(ev["per_graph"]["abs_rot_initial"].max()) < 1e-6

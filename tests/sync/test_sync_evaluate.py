"""The absolute-pose table helper (paper Table 3 format)."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from helpers import make_graph

from posernet.graph import GraphBatch
from posernet.metrics import METRE_THRESHOLDS
from posernet.sync import get_backend
from posernet.sync.evaluate import absolute_table, format_absolute_table


def test_noise_free_table_is_perfect_and_labelled():
    graphs = [make_graph(8, 8, seed=k) for k in range(5)]
    b = GraphBatch.from_graphs(graphs)
    tab = absolute_table(b, b.edge_pose_gt, "eig_se3", scale="given")
    assert tab["alignment"] == "rigid" and tab["scale"] == "given" and not tab["oracle"]
    assert tab["rotation_deg"].percent_below == (100.0,) * 5
    assert tab["position_m"].thresholds == METRE_THRESHOLDS
    assert tab["position_m"].percent_below == (100.0,) * 5 and tab["graphs"] == 5
    assert tab["rotation_deg"].median < 1e-8
    text = format_absolute_table(tab)
    assert "eig_se3" in text and "alignment: rigid" in text and "| rotation (deg) |" in text


def test_oracle_and_similarity_labels_and_noisy_rows():
    graphs = [make_graph(8, 8, seed=10 + k, rot_noise_deg=3.0, trans_noise=0.05)
              for k in range(6)]
    b = GraphBatch.from_graphs(graphs)
    tab = absolute_table(b, None, get_backend("eig_se3", scale="oracle"))
    assert tab["oracle"] and tab["alignment"] == "rigid"
    assert "ORACLE" in format_absolute_table(tab)
    free = absolute_table(b, None, "rotation_translation")
    assert free["alignment"] == "similarity" and free["scale"] == "free"
    assert 0 < free["rotation_deg"].median < 10
    assert free["per_graph"]["position_m"].shape == (6,)


def test_disconnected_and_isolated_are_reported():
    g = make_graph(7, 10, seed=20)
    keep = (g.edge_index < 6).all(0)
    z = torch.zeros(0, dtype=torch.long)
    g = dataclasses.replace(g, edge_index=g.edge_index[:, keep], edge_pose=g.edge_pose[keep],
                            edge_pose_gt=g.edge_pose_gt[keep], pair_edge=z, pair_src=z,
                            pair_dst=z)
    tab = absolute_table(g, g.edge_pose_gt, "eig_se3", scale="given")
    assert tab["unlocalised_cameras"] == 1 and tab["disconnected_graphs"] == 1
    assert tab["rotation_deg"].median < 1e-8
    assert "not localised" in format_absolute_table(tab)


def test_errors():
    g = make_graph(5, 3, seed=30)
    with pytest.raises(ValueError, match="pose_gt"):
        absolute_table(dataclasses.replace(g, pose_gt=None), None, "eig_se3")
    with pytest.raises(ValueError, match="alignment="):
        absolute_table(g, None, "eig_se3", alignment="affine")
    with pytest.raises(ValueError, match="only accepted together"):
        absolute_table(g, None, get_backend("eig_se3"), scale="unit")

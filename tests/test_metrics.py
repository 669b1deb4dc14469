"""Relative-pose metrics in the paper's per-graph format."""

from __future__ import annotations

import math

import pytest
import torch

from posernet import geometry as G
from posernet.metrics import per_graph_mean, relative_pose_errors, threshold_row


def test_relative_pose_errors_known_values():
    R = G.axis_angle_to_rotation_matrix(torch.tensor([[0.0, 0, math.radians(10)]]))
    est = torch.cat((G.rotation_matrix_to_quaternion(R), torch.tensor([[0.0, 1, 0]])), -1)
    gt = torch.tensor([[1.0, 0, 0, 0, 5.0, 0, 0]])
    rot, tdir = relative_pose_errors(est, gt)
    assert rot.item() == pytest.approx(10.0, abs=1e-4)
    assert tdir.item() == pytest.approx(90.0, abs=1e-4)
    with pytest.raises(ValueError, match="must both be"):
        relative_pose_errors(est, gt[:, :4])


def test_per_graph_mean_is_per_graph_then_nan_for_empty():
    v = torch.tensor([1.0, 3.0, 10.0, 20.0, 30.0])
    b = torch.tensor([0, 0, 2, 2, 2])
    out = per_graph_mean(v, b, 3)
    assert out[0] == 2.0 and out[2] == 20.0 and math.isnan(out[1])


def test_threshold_row_counts_graphs_below_each_threshold():
    row = threshold_row(torch.tensor([1.0, 4.0, 8.0, 40.0, float("nan")]))
    assert row.count == 4
    assert row.percent_below == (25.0, 50.0, 75.0, 75.0, 100.0)
    assert row.median == pytest.approx(6.0)
    d = row.as_dict("rot ")
    assert d["rot <3"] == 25.0 and d["rot median"] == pytest.approx(6.0)
    empty = threshold_row(torch.tensor([float("nan")]))
    assert empty.count == 0 and math.isnan(empty.median)

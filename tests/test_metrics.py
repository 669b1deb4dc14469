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


def test_trajectory_errors_evo_style():
    from posernet.geometry import invert_se3
    from posernet.metrics import trajectory_errors
    from posernet.testing import random_absolute_poses

    g = torch.Generator().manual_seed(3)
    gt = invert_se3(random_absolute_poses(6, g).double())  # camera to world
    # the estimate: the same trajectory in another frame, at another scale
    S = torch.eye(4, dtype=torch.float64)
    S[:3, :3] = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))[0]
    if torch.det(S[:3, :3]) < 0:
        S[:3, 0] *= -1
    S[:3, 3] = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    est = S @ gt.clone()
    est[:, :3, 3] *= 0.25
    err = trajectory_errors(est, gt)
    assert err["ape_translation"]["max"] < 1e-9 and err["rpe_rotation_deg"]["max"] < 1e-5
    assert err["rpe_translation"]["max"] < 1e-9
    assert err["scale"]["sim3"] == pytest.approx(4.0)
    # one camera 0.3 units off: its APE dominates, RPE touches its two neighbours' steps
    moved = est.clone()
    moved[3, :3, 3] += 0.3 / 4.0 * torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    err = trajectory_errors(moved, gt)
    assert 0.1 < err["ape_translation"]["max"] < 0.31  # the alignment absorbs part of it
    assert err["rpe_translation"]["median"] < err["rpe_translation"]["max"]
    with pytest.raises(ValueError, match="at least 3"):
        trajectory_errors(est[:2], gt[:2])

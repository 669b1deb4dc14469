"""gtsam reference backend (optional extra): skipped cleanly when gtsam is not installed."""

from __future__ import annotations

import numpy as np
import pytest
import torch

gtsam = pytest.importorskip("gtsam")

from helpers import errors, make_graph, rel_to_first  # noqa: E402

from posernet.graph import GraphBatch  # noqa: E402
from posernet.sync import available_backends, get_backend  # noqa: E402


def test_listed_and_scale_free_only():
    assert "gtsam" in available_backends()
    be = get_backend("gtsam")
    assert be.scale == "free" and not be.metric
    with pytest.raises(ValueError, match="not supported by sync backend 'gtsam'"):
        get_backend("gtsam", scale="unit")


def test_exact_recovery_from_noise_free_relative_poses():
    graphs = [make_graph(n, e, seed=n) for n, e in [(4, 3), (8, 8), (15, 40)]]
    b = GraphBatch.from_graphs(graphs)
    rot, pos = errors(get_backend("gtsam").solve(b, b.edge_pose_gt), b, "similarity")
    # gtsam's iterative solvers stop at their tolerances (not machine precision).
    assert float(rot.max()) < 1e-5 and float(pos.max()) < 1e-6


def test_agrees_with_rotation_translation_on_noisy_input():
    g = make_graph(12, 40, seed=31, rot_noise_deg=2.0, trans_noise=0.02)
    a = errors(get_backend("gtsam").solve(g), g, "similarity")
    b = errors(get_backend("rotation_translation").solve(g), g, "similarity")
    assert float(a[0].max()) < 3.0 and float(b[0].max()) < 3.0
    assert abs(float(a[0][0]) - float(b[0][0])) < 1.0


def test_measurement_conventions():
    """BinaryMeasurementRot3(i, j, R_ij^T) with camera-to-world results; Unit3 directions of
    c_j - c_i. A transposed rotation convention must not reproduce the truth."""
    g = make_graph(6, 6, seed=32)
    be = get_backend("gtsam")
    ok = be.solve(g, g.edge_pose_gt)
    np.testing.assert_allclose(rel_to_first(ok)[:, :3, :3],
                               rel_to_first(g.pose_gt)[:, :3, :3], atol=1e-7)
    from posernet.geometry import invert_pose_vec

    bad = be.solve(g, invert_pose_vec(g.edge_pose_gt))
    assert np.abs(rel_to_first(bad)[:, :3, :3] - rel_to_first(g.pose_gt)[:, :3, :3]).max() > 1e-2
    assert torch.isfinite(bad).all()

"""EIG-SE3: exactness, agreement with the literal numpy/scipy reference, IRLS robustness,
batching, the edge-direction convention, disconnected graphs, solvers, dtypes, devices."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from helpers import F64, errors, make_graph, rel_to_first
from hypothesis import given, settings
from hypothesis import strategies as st

from posernet.geometry import (
    axis_angle_to_rotation_matrix,
    invert_pose_vec,
    make_se3,
    matrix_to_pose_vec,
    pose_vec_to_matrix,
    relative_pose,
)
from posernet.graph import GraphBatch, ViewGraph
from posernet.sync import get_backend
from posernet.sync.reference import eig_se3_reference

# --------------------------------------------------------------------------- exactness


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n,extra", [(2, 0), (3, 1), (8, 8), (20, 60)])
def test_exact_recovery_noise_free(n, extra, dtype):
    g = make_graph(n, extra, seed=n, dtype=dtype)
    poses = get_backend("eig_se3", scale="given").solve(g, g.edge_pose_gt)
    assert poses.dtype == dtype and poses.shape == (n, 4, 4)
    rot, pos = errors(poses, g)
    tol_deg, tol_m = (1e-9, 1e-12) if dtype == F64 else (5e-2, 1e-5)
    assert float(rot.max()) < tol_deg and float(pos.max()) < tol_m
    # Gauge-free comparison with the truth as well.
    np.testing.assert_allclose(rel_to_first(poses), rel_to_first(g.pose_gt),
                               atol=1e-11 if dtype == F64 else 1e-4)


def test_exact_recovery_krylov_large_graph():
    g = make_graph(150, 900, seed=3)
    res = get_backend("eig_se3", scale="given", solver="krylov").solve_with_info(
        g, g.edge_pose_gt)
    assert res.info["eig_converged"]
    np.testing.assert_allclose(rel_to_first(res.poses), rel_to_first(g.pose_gt), atol=1e-10)


def test_oracle_scale_recovers_metric_poses_from_unit_directions():
    g = make_graph(8, 8, seed=4)
    unit = g.edge_pose_gt.clone()
    unit[:, 4:] = torch.nn.functional.normalize(unit[:, 4:], dim=-1)
    be = get_backend("eig_se3", scale="oracle")
    assert "ORACLE" in be.describe()["scale_label"]
    rot, pos = errors(be.solve(g, unit), g)
    assert float(rot.max()) < 1e-9 and float(pos.max()) < 1e-12
    # 'unit' keeps the wrong (unit) baselines: metric positions are then not exact.
    _, pos_unit = errors(get_backend("eig_se3", scale="unit").solve(g, unit), g)
    assert float(pos_unit.max()) > 1e-3


def test_edge_direction_convention():
    """Stored direction i -> j carries M_j M_i^{-1}. Flipping an edge together with its pose
    changes nothing; a transposed (inverted) pose on an edge must break exact recovery."""
    g = make_graph(8, 8, seed=5)
    be = get_backend("eig_se3", scale="given", robust=False)
    ref = rel_to_first(be.solve(g, g.edge_pose_gt))
    np.testing.assert_allclose(ref, rel_to_first(g.pose_gt), atol=1e-11)
    flipped = dataclasses.replace(g, edge_index=g.edge_index.flip(0))
    np.testing.assert_allclose(rel_to_first(be.solve(flipped, invert_pose_vec(g.edge_pose_gt))),
                               ref, atol=1e-11)
    # The wrong convention (every edge's pose inverted) must fail the exactness check ...
    rot, _ = errors(be.solve(g, invert_pose_vec(g.edge_pose_gt)), g)
    assert float(rot.mean()) > 1.0
    # ... and so must a single transposed edge.
    one = g.edge_pose_gt.clone()
    one[0] = invert_pose_vec(one[0])
    rot1, pos1 = errors(be.solve(g, one), g)
    assert float(rot1.max()) > 1e-3 or float(pos1.max()) > 1e-3


# --------------------------------------------------------------------------- reference


@pytest.mark.parametrize("n,extra,seed", [(8, 8, 0), (5, 3, 1), (12, 20, 2), (8, 4, 3)])
def test_matches_literal_reference_with_noise(n, extra, seed):
    g = make_graph(n, extra, seed, rot_noise_deg=4.0, trans_noise=0.05)
    res = get_backend("eig_se3", scale="given").solve_with_info(g)
    ref = eig_se3_reference(n, g.edge_index.numpy(), pose_vec_to_matrix(g.edge_pose).numpy())
    assert int(res.iterations[0]) == ref.iterations
    np.testing.assert_allclose(rel_to_first(res.poses), rel_to_first(ref.poses), atol=1e-9)
    np.testing.assert_allclose(res.edge_weight.numpy(), ref.weights, atol=1e-9)


@pytest.mark.parametrize("shift_invert", [False, True])
def test_matches_sparse_reference_and_krylov(monkeypatch, shift_invert):
    """Dense and Krylov solves give the reference's poses; the Krylov one also where large
    CPU components run Lanczos on the shifted inverse (here: above 10 cameras, at once)."""
    import posernet.sync.spectral as sp
    import posernet.sync.translation as tr

    if shift_invert:
        monkeypatch.setattr(tr, "SPARSE_MIN_NODES", 10)
        monkeypatch.setattr(sp, "PLAIN_KRYLOV_CYCLES", 0)
    g = make_graph(70, 500, seed=7, rot_noise_deg=3.0, trans_noise=0.03)
    ref = eig_se3_reference(70, g.edge_index.numpy(), pose_vec_to_matrix(g.edge_pose).numpy(),
                            use_sparse=True)
    for solver in ("dense", "krylov"):
        res = get_backend("eig_se3", scale="given", solver=solver).solve_with_info(g)
        assert int(res.iterations[0]) == ref.iterations
        np.testing.assert_allclose(rel_to_first(res.poses), rel_to_first(ref.poses), atol=1e-8)


@pytest.mark.parametrize("graph", ["chain", "connected"])
def test_large_components_invert_only_where_plain_lanczos_stalls(monkeypatch, graph):
    """Large CPU components start with Lanczos on ``N``: a well-connected graph settles in a
    few cycles and never pays for a sparse LU (which fills in on such a graph); a chain of
    cameras (tiny spectral gap) does not, and switches to the shifted inverse. Both give the
    dense solver's poses."""
    import posernet.sync.spectral as sp
    import posernet.sync.translation as tr

    monkeypatch.setattr(tr, "SPARSE_MIN_NODES", 10)
    n = 120
    if graph == "chain":  # each camera sees the next two
        ei = torch.tensor([[i, i + d] for d in (1, 2) for i in range(n - d)]).T
        g = make_graph(n, 0, seed=9, rot_noise_deg=2.0, trans_noise=0.02, edge_index=ei)
    else:
        g = make_graph(n, 900, seed=9, rot_noise_deg=2.0, trans_noise=0.02)
    lus = []
    real = sp.shift_invert_apply

    def spy(S, rows):
        lus.append(S.shape[0])
        return real(S, rows)

    monkeypatch.setattr(sp, "shift_invert_apply", spy)
    res = get_backend("eig_se3", scale="given", solver="krylov").solve_with_info(g)
    assert res.info["eig_converged"]
    assert (len(lus) > 0) == (graph == "chain")
    if graph == "chain":  # once it stalls, every later IRLS round factors at once
        assert len(lus) == int(res.iterations[0])
    dense = get_backend("eig_se3", scale="given", solver="dense").solve_with_info(g)
    assert torch.equal(res.iterations, dense.iterations)
    np.testing.assert_allclose(rel_to_first(res.poses), rel_to_first(dense.poses), atol=1e-8)


def test_well_connected_components_never_factor(monkeypatch):
    """Where plain Lanczos is slow on a well-connected graph (here: one cycle allowed), it goes
    on by itself rather than factor: the LU of such a graph fills in. A chain factors."""
    import posernet.sync.spectral as sp
    import posernet.sync.translation as tr

    monkeypatch.setattr(tr, "SPARSE_MIN_NODES", 10)
    monkeypatch.setattr(sp, "PLAIN_KRYLOV_CYCLES", 1)
    lus = []
    real = sp.shift_invert_apply
    monkeypatch.setattr(sp, "shift_invert_apply", lambda S, rows: lus.append(1) or real(S, rows))
    n = 80
    dense = make_graph(n, 1500, seed=10, rot_noise_deg=2.0, trans_noise=0.02)
    assert 2 * dense.num_edges / n > sp.SHIFT_INVERT_MAX_DEGREE
    res = get_backend("eig_se3", scale="given", solver="krylov").solve_with_info(dense)
    assert res.info["eig_converged"] and not lus
    ref = get_backend("eig_se3", scale="given", solver="dense").solve_with_info(dense)
    np.testing.assert_allclose(rel_to_first(res.poses), rel_to_first(ref.poses), atol=1e-8)
    ei = torch.tensor([[i, i + 1] for i in range(n - 1)]).T
    chain = make_graph(n, 0, seed=10, rot_noise_deg=2.0, trans_noise=0.02, edge_index=ei)
    get_backend("eig_se3", scale="given", solver="krylov").solve_with_info(chain)
    assert lus


def test_non_robust_single_solve_matches_reference():
    g = make_graph(10, 12, seed=8, rot_noise_deg=5.0, trans_noise=0.1)
    res = get_backend("eig_se3", scale="given", robust=False).solve_with_info(g)
    ref = eig_se3_reference(10, g.edge_index.numpy(), pose_vec_to_matrix(g.edge_pose).numpy(),
                            robust=False)
    assert int(res.iterations[0]) == 1 and ref.iterations == 1
    np.testing.assert_allclose(rel_to_first(res.poses), rel_to_first(ref.poses), atol=1e-10)


# --------------------------------------------------------------------------- noise, outliers


def test_graceful_degradation_with_noise():
    med = []
    for sigma in (0.0, 0.5, 2.0, 8.0):
        graphs = [make_graph(8, 9, seed=100 + k, rot_noise_deg=sigma, trans_noise=sigma / 100)
                  for k in range(12)]
        b = GraphBatch.from_graphs(graphs)
        rot, pos = errors(get_backend("eig_se3", scale="given").solve(b), b)
        med.append((float(rot.median()), float(pos.median())))
    assert med[0][0] < 1e-8
    assert med[1][0] < 1.0 and med[2][0] < 4.0 and med[3][0] < 15.0
    assert med[1][0] < med[2][0] < med[3][0]
    assert med[1][1] < med[2][1] < med[3][1]


def test_irls_is_robust_to_outlier_edges():
    graphs = [make_graph(25, 120, seed=200 + k, rot_noise_deg=1.0, trans_noise=0.01,
                         outlier_frac=0.2) for k in range(4)]
    b = GraphBatch.from_graphs(graphs)
    rob = errors(get_backend("eig_se3", scale="given").solve(b), b, "similarity")
    plain = errors(get_backend("eig_se3", scale="given", robust=False).solve(b), b, "similarity")
    assert float(rob[0].mean()) < 0.5 * float(plain[0].mean())
    assert float(rob[0].max()) < 3.0
    assert float(rob[1].mean()) < float(plain[1].mean())


# --------------------------------------------------------------------------- batching


def test_batching_equals_one_by_one():
    graphs = [make_graph(n, e, seed=300 + n, rot_noise_deg=3.0, trans_noise=0.05)
              for n, e in [(3, 1), (8, 8), (12, 25), (5, 2), (8, 3)]]
    b = GraphBatch.from_graphs(graphs)
    be = get_backend("eig_se3", scale="given")
    res = be.solve_with_info(b)
    for k, gr in enumerate(graphs):
        one = be.solve_with_info(gr)
        sl = slice(int(b.ptr[k]), int(b.ptr[k + 1]))
        np.testing.assert_allclose(rel_to_first(res.poses[sl]), rel_to_first(one.poses),
                                   atol=1e-10)
        assert int(res.iterations[k]) == int(one.iterations[0])


def test_mixed_dense_and_krylov_components_in_one_batch():
    graphs = [make_graph(6, 5, 400, rot_noise_deg=2.0), make_graph(80, 400, 401, 2.0)]
    b = GraphBatch.from_graphs(graphs)
    auto = get_backend("eig_se3", scale="given", dense_max_nodes=40).solve(b)
    dense = get_backend("eig_se3", scale="given", solver="dense").solve(b)
    for k in range(2):
        sl = slice(int(b.ptr[k]), int(b.ptr[k + 1]))
        np.testing.assert_allclose(rel_to_first(auto[sl]), rel_to_first(dense[sl]), atol=1e-9)


@settings(max_examples=8, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=6, max_size=6), st.floats(0.2, 5.0))
def test_gauge_invariance(params, scale):
    """A global rigid motion of the ground truth leaves the relative poses, hence the
    estimate's aligned errors, unchanged."""
    g = make_graph(8, 8, seed=11, rot_noise_deg=3.0, trans_noise=0.05)
    T = make_se3(axis_angle_to_rotation_matrix(torch.tensor(params[:3], dtype=F64)),
                 torch.tensor(params[3:], dtype=F64) * scale)
    moved = dataclasses.replace(g, pose_gt=g.pose_gt @ torch.linalg.inv(T))
    moved = dataclasses.replace(moved, edge_pose=g.edge_pose)
    rel_gt = matrix_to_pose_vec(relative_pose(moved.pose_gt[g.edge_index[0]],
                                              moved.pose_gt[g.edge_index[1]]))
    np.testing.assert_allclose(pose_vec_to_matrix(rel_gt).numpy(),
                               pose_vec_to_matrix(g.edge_pose_gt).numpy(), atol=1e-9)
    be = get_backend("eig_se3", scale="given")
    a = errors(be.solve(g), g, "similarity")
    b = errors(be.solve(moved), moved, "similarity")
    torch.testing.assert_close(a, b, atol=1e-7, rtol=0)


# --------------------------------------------------------------------------- topology


def _subgraph(g: ViewGraph, keep_edges: torch.Tensor) -> ViewGraph:
    z = torch.zeros(0, dtype=torch.long)
    return dataclasses.replace(g, edge_index=g.edge_index[:, keep_edges],
                               edge_pose=g.edge_pose[keep_edges],
                               edge_pose_gt=g.edge_pose_gt[keep_edges],
                               pair_edge=z, pair_src=z, pair_dst=z)


def test_disconnected_graph_is_solved_per_component_and_isolated_nodes_flagged():
    g = make_graph(9, 20, seed=12)
    src, dst = g.edge_index
    side = lambda v: (v < 4).long() + 2 * ((v >= 4) & (v < 8)).long()  # noqa: E731
    keep = (side(src) == side(dst)) & (src != 8) & (dst != 8)
    sub = _subgraph(g, keep)
    res = get_backend("eig_se3", scale="given").solve_with_info(sub, sub.edge_pose_gt)
    assert torch.isfinite(res.poses).all()
    assert not bool(res.solved[8]) and bool(res.solved[:8].all())
    torch.testing.assert_close(res.poses[8], torch.eye(4, dtype=F64))
    assert res.component[:4].unique().numel() == 1 and res.component[4:8].unique().numel() == 1
    assert int(res.component[0]) != int(res.component[4]) != int(res.component[8])
    for part in (slice(0, 4), slice(4, 8)):
        np.testing.assert_allclose(rel_to_first(res.poses[part]),
                                   rel_to_first(sub.pose_gt[part]), atol=1e-11)
    with pytest.raises(ValueError, match="not connected"):
        get_backend("eig_se3", disconnected="error").solve(sub)


# --------------------------------------------------------------------------- input errors


@pytest.mark.parametrize("backend", ["eig_se3", "rotation_translation"])
def test_bad_inputs_raise_clear_errors(backend):
    be = get_backend(backend)
    g = make_graph(5, 3, seed=13)
    with pytest.raises(ValueError, match="edge_pose has shape"):
        be.solve(g, g.edge_pose[:-1])
    nan = g.edge_pose.clone()
    nan[2, 5] = float("nan")
    with pytest.raises(ValueError, match="NaN/inf value .edge 2"):
        be.solve(g, nan)
    with pytest.raises(ValueError, match="zero quaternion"):
        be.solve(g, torch.cat((torch.zeros_like(nan[:, :4]), g.edge_pose[:, 4:]), 1))
    no_edges = _subgraph(g, torch.zeros(g.num_edges, dtype=torch.bool))
    with pytest.raises(ValueError, match="no edges"):
        be.solve(no_edges, no_edges.edge_pose)
    one = make_graph(2, 0, seed=14)
    one = dataclasses.replace(_subgraph(one, torch.zeros(1, dtype=torch.bool)),
                              node_attr=one.node_attr[:1], K=one.K[:1],
                              image_size=one.image_size[:1], pose_gt=one.pose_gt[:1])
    with pytest.raises(ValueError, match="fewer than 2 nodes"):
        be.solve(one, one.edge_pose)
    with pytest.raises(ValueError, match="GraphBatch or ViewGraph"):
        be.solve("not a graph", g.edge_pose)  # type: ignore[arg-type]


def test_scale_policy_errors():
    g = make_graph(5, 3, seed=15)
    with pytest.raises(ValueError, match="rotation_translation"):
        get_backend("eig_se3", scale="free")
    with pytest.raises(ValueError, match="edge_pose_gt is missing"):
        get_backend("eig_se3", scale="oracle").solve(dataclasses.replace(g, edge_pose_gt=None))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    graphs = [make_graph(8, 8, seed=500 + k, rot_noise_deg=3.0, trans_noise=0.05)
              for k in range(5)] + [make_graph(90, 500, 510, 2.0)]
    b = GraphBatch.from_graphs(graphs)
    be = get_backend("eig_se3", scale="given")
    cpu = be.solve(b)
    gpu = be.solve(b.to("cuda"))
    assert gpu.device.type == "cuda"
    for k in range(b.num_graphs):
        sl = slice(int(b.ptr[k]), int(b.ptr[k + 1]))
        np.testing.assert_allclose(rel_to_first(gpu[sl].cpu()), rel_to_first(cpu[sl]),
                                   atol=1e-8)

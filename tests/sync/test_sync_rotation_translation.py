"""rotation_translation backend: exactness (scale-free and metric), noise, outliers, batching."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import errors, make_graph, rel_to_first

from posernet.graph import GraphBatch
from posernet.sync import get_backend
from posernet.sync.backend import graph_structure
from posernet.sync.components import connected_components
from posernet.sync.padding import build_padded, edge_rotations
from posernet.sync.rotation_translation import refine_rotations, translations_from_directions


@pytest.mark.parametrize("n,extra", [(4, 4), (8, 10), (30, 120)])
def test_exact_recovery_scale_free(n, extra):
    g = make_graph(n, extra, seed=n)
    unit = g.edge_pose_gt.clone()
    unit[:, 4:] = torch.nn.functional.normalize(unit[:, 4:], dim=-1)
    res = get_backend("rotation_translation").solve_with_info(g, unit)
    assert not res.metric and res.scale == "free"
    rot, pos = errors(res.poses, g, "similarity")
    assert float(rot.max()) < 1e-8 and float(pos.max()) < 1e-9
    # The scale-free gauge: centroid at the origin, RMS camera distance 1.
    c = -(res.poses[:, :3, :3].mT @ res.poses[:, :3, 3:]).squeeze(-1)
    assert float(c.mean(0).abs().max()) < 1e-12
    assert abs(float((c * c).sum(1).mean()) - 1.0) < 1e-12


@pytest.mark.parametrize("scale", ["given", "oracle"])
def test_exact_recovery_metric(scale):
    g = make_graph(8, 8, seed=21)
    ep = g.edge_pose_gt.clone()
    if scale == "oracle":
        ep[:, 4:] = torch.nn.functional.normalize(ep[:, 4:], dim=-1)
    poses = get_backend("rotation_translation", scale=scale).solve(g, ep)
    rot, pos = errors(poses, g, "rigid")
    assert float(rot.max()) < 1e-9 and float(pos.max()) < 1e-12


def test_graceful_degradation_with_noise():
    med = []
    for sigma in (0.5, 2.0, 6.0):
        graphs = [make_graph(10, 20, seed=600 + k, rot_noise_deg=sigma, trans_noise=sigma / 100)
                  for k in range(10)]
        b = GraphBatch.from_graphs(graphs)
        rot, pos = errors(get_backend("rotation_translation").solve(b), b, "similarity")
        med.append((float(rot.median()), float(pos.median())))
    assert med[0][0] < 1.0 and med[1][0] < 3.0 and med[2][0] < 10.0
    assert med[0][0] < med[1][0] < med[2][0]
    assert med[0][1] < med[1][1] < med[2][1]


def test_robust_rotations_beat_non_robust_with_outliers():
    graphs = [make_graph(25, 120, seed=700 + k, rot_noise_deg=1.0, trans_noise=0.01,
                         outlier_frac=0.2) for k in range(3)]
    b = GraphBatch.from_graphs(graphs)
    rob = errors(get_backend("rotation_translation").solve(b), b, "similarity")
    plain = errors(get_backend("rotation_translation", robust=False).solve(b), b, "similarity")
    assert float(rob[0].mean()) < 0.5 * float(plain[0].mean())
    assert float(rob[1].mean()) < float(plain[1].mean())


def test_geodesic_refinement_lowers_the_geodesic_cost():
    """The refinement minimises sum_e |log(R_j^T R_e R_i)|^2 (robust=False): it must lower
    that cost from the spectral (chordal) solution and stop at a stationary point."""
    from posernet.geometry import rotation_matrix_to_axis_angle
    from posernet.sync.spectral import rotation_irls

    g = make_graph(12, 30, seed=800, rot_noise_deg=15.0)
    st = graph_structure(g)
    comps = connected_components(st["edge_index"], st["num_nodes"], st["node_batch"], 1)
    prob = build_padded(st["edge_index"], edge_rotations(g.edge_pose), g.edge_pose[:, 4:], comps)

    def cost(R):
        gi = torch.zeros_like(prob.src)
        E = R[gi, prob.dst].mT @ prob.R @ R[gi, prob.src]
        return float((rotation_matrix_to_axis_angle(E) ** 2).sum())

    R0 = rotation_irls(prob, False, 1, 1e-5, 2.0, krylov=False).R
    R1 = refine_rotations(prob, R0, 50, False, 2.0)
    assert cost(R1) < cost(R0)
    R2 = refine_rotations(prob, R1, 1, False, 2.0)
    assert abs(cost(R2) - cost(R1)) < 1e-12


def test_translation_stage_uses_the_edge_convention():
    """c_j - c_i = -R_j^T t_ij: with true rotations and directions the centres are exact; with
    the direction reversed (a transposed edge convention) they are not."""
    g = make_graph(8, 12, seed=22)
    st = graph_structure(g)
    comps = connected_components(st["edge_index"], st["num_nodes"], st["node_batch"], 1)
    for sign, ok in ((1.0, True), (-1.0, False)):
        prob = build_padded(st["edge_index"], edge_rotations(g.edge_pose_gt),
                            sign * g.edge_pose_gt[:, 4:], comps)
        R = g.pose_gt[:, :3, :3][None]
        c = translations_from_directions(prob, R, 1, False, 2.0)[0]
        cg = -(g.pose_gt[:, :3, :3].mT @ g.pose_gt[:, :3, 3:]).squeeze(-1)
        cg = cg - cg.mean(0)
        cg = cg / (cg * cg).sum(1).mean().sqrt()
        assert bool(torch.allclose(c, cg, atol=1e-9)) == ok
    # Refinement from the truth stays at the truth.
    R2 = refine_rotations(prob, R.clone(), 5, True, 2.0)
    torch.testing.assert_close(R2, R, atol=1e-12, rtol=0)


def test_batching_equals_one_by_one():
    graphs = [make_graph(n, e, seed=900 + n, rot_noise_deg=2.0, trans_noise=0.02)
              for n, e in [(4, 3), (8, 10), (11, 20)]]
    b = GraphBatch.from_graphs(graphs)
    be = get_backend("rotation_translation")
    poses = be.solve(b)
    for k, gr in enumerate(graphs):
        sl = slice(int(b.ptr[k]), int(b.ptr[k + 1]))
        np.testing.assert_allclose(rel_to_first(poses[sl]), rel_to_first(be.solve(gr)),
                                   atol=1e-9)


def test_vanishing_robust_weights_do_not_make_the_solve_singular(monkeypatch):
    # A Cauchy weight can underflow to 0 (e.g. on a bridge edge with a large early residual),
    # disconnecting the weighted graph; the weight floor keeps every Laplacian invertible.
    import posernet.sync.rotation_translation as rt

    monkeypatch.setattr(rt, "mad_cauchy_weights", lambda r, mask, theta: torch.zeros_like(r))
    g = make_graph(8, 4, seed=3)
    poses = get_backend("rotation_translation", robust=True).solve(g, g.edge_pose)
    assert bool(torch.isfinite(poses).all())


@pytest.mark.parametrize("robust", [False, True])
def test_sparse_position_solve_equals_the_dense_one(monkeypatch, robust):
    """Large components solve the position system sparsely (scipy's LU): the same centres as
    the dense batched solve, with two components padded to one size, per-edge start weights
    and an edge-free component."""
    import posernet.sync.translation as tr

    b = GraphBatch.from_graphs([make_graph(30, 60, seed=31, rot_noise_deg=2.0, trans_noise=0.05),
                                make_graph(18, 20, seed=32, rot_noise_deg=2.0,
                                           trans_noise=0.05)])
    st = graph_structure(b)
    comps = connected_components(st["edge_index"], st["num_nodes"], st["node_batch"], 2)
    prob = build_padded(st["edge_index"], edge_rotations(b.edge_pose),
                        torch.nn.functional.normalize(b.edge_pose[:, 4:], dim=-1), comps)
    assert prob.G == 2 and not bool(prob.node_mask.all())  # padded
    R = torch.zeros(prob.G, prob.n, 3, 3, dtype=torch.float64)
    R[prob.node_mask] = b.pose_gt[prob.node[prob.node_mask], :3, :3]
    R[~prob.node_mask] = torch.eye(3, dtype=torch.float64)
    w0 = torch.rand(prob.G, prob.m, generator=torch.Generator().manual_seed(0),
                    dtype=torch.float64) + 0.5
    out = {}
    for limit in (10**9, 8):  # dense everywhere / sparse above 8 cameras
        monkeypatch.setattr(tr, "SPARSE_MIN_NODES", limit)
        out[limit] = translations_from_directions(prob, R, 10, robust, 2.0, w0=w0)
        none = translations_from_directions(prob, R, 1, robust, 2.0, w0=torch.zeros_like(w0))
        assert float(none.abs().max()) == 0.0  # no edge: every centre at 0
    assert float(out[8].abs().max()) > 0.1
    torch.testing.assert_close(out[8], out[10**9], atol=1e-9, rtol=0)


def test_sparse_laplacian_solve_equals_the_dense_one(monkeypatch):
    """Large CPU components solve the Laplacian least squares of BATA / the rotation
    refinement sparsely (bordered gauge row): the dense solve's centres, with two padded
    components, zero weights that cut one in two (the ridge places the pieces) and an
    edge-free component."""
    import posernet.sync.translation as tr

    b = GraphBatch.from_graphs([make_graph(30, 60, seed=33), make_graph(18, 20, seed=34)])
    st = graph_structure(b)
    comps = connected_components(st["edge_index"], st["num_nodes"], st["node_batch"], 2)
    prob = build_padded(st["edge_index"], edge_rotations(b.edge_pose), b.edge_pose[:, 4:], comps)
    gen = torch.Generator().manual_seed(3)
    w = (torch.rand(prob.G, prob.m, generator=gen, dtype=torch.float64) + 0.5) * prob.edge_mask
    cut = prob.edge_mask[0] & (prob.src[0] < 15) & (prob.dst[0] >= 15)
    w[0, cut] = 0.0
    target = torch.randn(prob.G, prob.m, 3, generator=gen, dtype=torch.float64)
    out = {}
    for limit in (10**9, 8):  # dense everywhere / sparse above 8 cameras
        monkeypatch.setattr(tr, "SPARSE_MIN_NODES", limit)
        out[limit] = tr.laplacian_solve(prob, w, target)
        assert float(tr.laplacian_solve(prob, torch.zeros_like(w), target).abs().max()) == 0.0
    assert float(out[8].abs().max()) > 0.1
    torch.testing.assert_close(out[8], out[10**9], atol=1e-7, rtol=1e-7)

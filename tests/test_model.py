"""PoserNet: equivariances (permutation, batching, edge direction), gradients, edge cases.

All checks use untrained (random-weight) models so they test the architecture, not training.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from posernet.geometry import invert_pose_vec, quaternion_angle
from posernet.graph import GraphBatch, ViewGraph
from posernet.nn import PoserNet, invert_pose_raw
from posernet.testing import random_view_graph


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    """Tiny tensors: one thread avoids OpenMP oversubscription on a busy 2-core machine."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


CONFIGS = [
    {},
    {"residual": True},
    {"unit_output": True, "nested_mean": False},
    {"edge_hidden": 6, "shared_weights": True, "depth": 3},
]


def make_graph(seed: int, dtype: torch.dtype = torch.float64, **kw) -> ViewGraph:
    return random_view_graph(generator=torch.Generator().manual_seed(seed), dtype=dtype, **kw)


def make_model(seed: int = 0, dtype: torch.dtype = torch.float64, **kw) -> PoserNet:
    torch.manual_seed(seed)
    return PoserNet(**kw).to(dtype)


# --------------------------------------------------------------------------- graph edits


def relabel_nodes(g: ViewGraph, order: torch.Tensor) -> ViewGraph:
    """New node k is old node ``order[k]``."""
    new_of_old = torch.argsort(order)
    return dataclasses.replace(
        g, node_attr=g.node_attr[order], K=g.K[order], image_size=g.image_size[order],
        pose_gt=g.pose_gt[order], edge_index=new_of_old[g.edge_index],
        det_node=new_of_old[g.det_node])


def reorder_edges(g: ViewGraph, order: torch.Tensor) -> ViewGraph:
    """New edge k is old edge ``order[k]``."""
    new_of_old = torch.argsort(order)
    return dataclasses.replace(
        g, edge_index=g.edge_index[:, order], edge_pose=g.edge_pose[order],
        edge_pose_gt=g.edge_pose_gt[order], pair_edge=new_of_old[g.pair_edge])


def reorder_pairs_and_dets(g: ViewGraph, pair_order: torch.Tensor,
                           det_order: torch.Tensor) -> ViewGraph:
    det_new_of_old = torch.argsort(det_order)
    return dataclasses.replace(
        g, det_box=g.det_box[det_order], det_node=g.det_node[det_order],
        pair_edge=g.pair_edge[pair_order], pair_src=det_new_of_old[g.pair_src[pair_order]],
        pair_dst=det_new_of_old[g.pair_dst[pair_order]])


def flip_edges(g: ViewGraph, flip: torch.Tensor) -> ViewGraph:
    """Store the edges marked in ``flip [E]`` the other way round (inverse pose, swapped pairs)."""
    fp = flip[g.pair_edge]
    return dataclasses.replace(
        g,
        edge_index=torch.where(flip, g.edge_index.flip(0), g.edge_index),
        edge_pose=torch.where(flip[:, None], invert_pose_vec(g.edge_pose), g.edge_pose),
        edge_pose_gt=torch.where(flip[:, None], invert_pose_vec(g.edge_pose_gt),
                                 g.edge_pose_gt),
        pair_src=torch.where(fp, g.pair_dst, g.pair_src),
        pair_dst=torch.where(fp, g.pair_src, g.pair_dst),
    )


def assert_same_poses(a: torch.Tensor, b: torch.Tensor, tol: float = 1e-9) -> None:
    """Equal rotations (sign-invariant), quaternion norms and translations."""
    assert a.shape == b.shape
    assert quaternion_angle(a[:, :4], b[:, :4]).max() < tol
    torch.testing.assert_close(a[:, :4].norm(dim=-1), b[:, :4].norm(dim=-1), atol=tol, rtol=0)
    torch.testing.assert_close(a[:, 4:], b[:, 4:], atol=tol, rtol=0)


# --------------------------------------------------------------------------- equivariances


@pytest.mark.parametrize("cfg", CONFIGS)
@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_permutation_equivariance(cfg: dict, seed: int) -> None:
    g = make_graph(seed)
    model = make_model(seed, **cfg)
    out = model(g)
    p = torch.Generator().manual_seed(seed + 1)
    # Relabelling nodes, detections or pairs leaves every edge's output unchanged.
    g2 = relabel_nodes(g, torch.randperm(g.num_nodes, generator=p))
    g2 = reorder_pairs_and_dets(g2, torch.randperm(g.num_pairs, generator=p),
                                torch.randperm(g.num_dets, generator=p))
    assert_same_poses(model(g2.validate()), out)
    # Reordering edges reorders the outputs the same way.
    order = torch.randperm(g.num_edges, generator=p)
    assert_same_poses(model(reorder_edges(g, order).validate()), out[order])


@pytest.mark.parametrize("cfg", CONFIGS)
@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_flipping_an_edge_gives_the_inverse_output(cfg: dict, seed: int) -> None:
    g = make_graph(seed)
    model = make_model(seed, **cfg)
    out = model(g)
    flip = torch.rand(g.num_edges, generator=torch.Generator().manual_seed(seed)) < 0.5
    flip[0] = True
    out_flipped = model(flip_edges(g, flip).validate())
    expected = torch.where(flip[:, None], invert_pose_raw(out), out)
    assert_same_poses(out_flipped, expected)
    # The other edges' outputs do not depend on how their neighbours are stored.
    assert_same_poses(out_flipped[~flip], out[~flip])


def test_flip_test_can_fail() -> None:
    """Sanity check of the test itself: the inverse of a generic pose is not the pose."""
    out = make_model(**CONFIGS[0])(make_graph(0))
    assert quaternion_angle(invert_pose_raw(out)[:, :4], out[:, :4]).min() > 1e-3


@pytest.mark.parametrize("cfg", CONFIGS)
def test_batch_equals_graphs_one_by_one(cfg: dict) -> None:
    graphs = [make_graph(s, num_nodes=n) for s, n in ((1, 8), (2, 3), (3, 6))]
    model = make_model(1, **cfg)
    batched = model(GraphBatch.from_graphs(graphs))
    single = torch.cat([model(g) for g in graphs])
    torch.testing.assert_close(batched, single, atol=1e-12, rtol=0)


# --------------------------------------------------------------------------- edge cases


def test_isolated_nodes_single_pairs_and_components() -> None:
    """A graph with an isolated node, two components and single-pair edges."""
    a = make_graph(4, num_nodes=4, extra_edges=0, pairs_per_edge=(1, 1))
    b = make_graph(5, num_nodes=3, extra_edges=1, pairs_per_edge=(1, 3))
    lone = make_graph(6, num_nodes=2, extra_edges=0)
    lone = dataclasses.replace(  # one node, no edges, no pairs
        lone, node_attr=lone.node_attr[:1], K=lone.K[:1], image_size=lone.image_size[:1],
        pose_gt=lone.pose_gt[:1], edge_index=lone.edge_index[:, :0], edge_pose=lone.edge_pose[:0],
        edge_pose_gt=lone.edge_pose_gt[:0], det_box=lone.det_box[:3],
        det_node=torch.zeros(3, dtype=torch.long), pair_edge=lone.pair_edge[:0],
        pair_src=lone.pair_src[:0], pair_dst=lone.pair_dst[:0])
    merged = GraphBatch.from_graphs([a, lone, b])
    # As ONE graph with two components and an isolated node (not as a batch of three).
    one = ViewGraph(**{f.name: getattr(merged, f.name) for f in dataclasses.fields(ViewGraph)})
    one.validate()
    model = make_model(2)
    out = model(one)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out, torch.cat([model(a), model(b)]), atol=1e-12, rtol=0)
    assert model(lone).shape == (0, 7)


def test_edge_without_pairs_keeps_its_pose() -> None:
    g = make_graph(7)
    keep = g.pair_edge != 0  # drop every pair of edge 0
    g2 = dataclasses.replace(g, pair_edge=g.pair_edge[keep], pair_src=g.pair_src[keep],
                             pair_dst=g.pair_dst[keep])
    out = make_model(3)(g2)
    assert_same_poses(out[:1], g.edge_pose[:1])


def test_unit_output_and_dtype() -> None:
    g = make_graph(8, dtype=torch.float32)
    model = PoserNet(unit_output=True)
    assert next(model.parameters()).dtype == torch.float32
    out = model(g)
    assert out.dtype == torch.float32 and out.shape == (g.num_edges, 7)
    torch.testing.assert_close(out[:, :4].norm(dim=-1), torch.ones(g.num_edges))
    torch.testing.assert_close(out[:, 4:].norm(dim=-1), torch.ones(g.num_edges))
    assert (out[:, 0] >= 0).all()  # sign-canonical quaternion
    outs = model(g, return_all=True)
    assert len(outs) == 2 and torch.equal(outs[-1], out)


def test_plain_tensors_equal_graph_input() -> None:
    g = make_graph(9)
    model = make_model(4)
    out = model(g.node_attr, g.edge_index, g.edge_pose, g.pair_edge, g.det_box[g.pair_src],
                g.det_box[g.pair_dst])
    torch.testing.assert_close(out, model(g))


def test_sizes_and_weight_sharing() -> None:
    separate = PoserNet(depth=3)
    shared = PoserNet(depth=3, shared_weights=True)
    assert len(separate.convs) == 3 and len(shared.convs) == 1
    n_sep = sum(p.numel() for p in separate.parameters())
    n_sh = sum(p.numel() for p in shared.parameters())
    assert n_sh < n_sep
    assert sum(p.numel() for p in PoserNet(mlp_hidden=64).parameters()) > \
        sum(p.numel() for p in PoserNet().parameters())
    with pytest.raises(ValueError, match="depth"):
        PoserNet(depth=0)


def test_residual_with_zero_correction_is_identity() -> None:
    g = make_graph(10)
    model = make_model(5, residual=True)
    for conv in model.convs:  # zero the last layer of Psi_E: correction = identity
        last = conv.psi_edge.net[-1]
        torch.nn.init.zeros_(last.weight)
        torch.nn.init.zeros_(last.bias)
    assert_same_poses(model(g), g.edge_pose, tol=1e-9)


def test_gradcheck_tiny_graph() -> None:
    g = make_graph(11, num_nodes=3, extra_edges=1, pairs_per_edge=(1, 2), dets_per_node=2)
    model = make_model(6, node_hidden=3, mlp_hidden=4, edge_hidden=2)
    pose = g.edge_pose.clone().requires_grad_(True)
    box_s = g.det_box[g.pair_src].clone().requires_grad_(True)
    box_d = g.det_box[g.pair_dst].clone().requires_grad_(True)
    x = g.node_attr.clone().requires_grad_(True)

    def f(x, pose, box_s, box_d):
        return model(x, g.edge_index, pose, g.pair_edge, box_s, box_d)

    assert torch.autograd.gradcheck(f, (x, pose, box_s, box_d), eps=1e-6, atol=1e-5)
    # Every parameter that can influence the output gets a finite gradient; the node MLP of
    # the last round cannot (its node states are never read again).
    f(x, pose, box_s, box_d).sum().backward()
    unused = {id(p) for p in model.convs[-1].psi_node.parameters()}
    for name, p in model.named_parameters():
        if id(p) in unused:
            assert p.grad is None, name
        else:
            assert p.grad is not None and torch.isfinite(p.grad).all(), name


def test_input_validation_messages() -> None:
    g = make_graph(12)
    model = make_model(7)
    args = [g.node_attr, g.edge_index, g.edge_pose, g.pair_edge, g.det_box[g.pair_src],
            g.det_box[g.pair_dst]]

    def call(i: int, value) -> None:
        a = list(args)
        a[i] = value
        model(*a)

    with pytest.raises(ValueError, match=r"edge_pose must have shape \[E, 7\]"):
        call(2, g.edge_pose[:, :6])
    with pytest.raises(ValueError, match="edge_index must be torch.long"):
        call(1, g.edge_index.int())
    with pytest.raises(ValueError, match=r"pair_edge values must lie in \[0, "):
        call(3, g.pair_edge + g.num_edges)
    with pytest.raises(ValueError, match="4 features per node, the layer expects 4|expects 4"):
        call(0, torch.zeros(g.num_nodes, 5, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"pair_box_src must have shape \[M, 4\]"):
        call(4, g.det_box[:3])
    with pytest.raises(ValueError, match="dtype"):
        call(2, g.edge_pose.float())
    with pytest.raises(ValueError, match="inputs are torch.float32 but the parameters are"):
        model(g.apply(lambda t: t.float() if t.is_floating_point() else t))

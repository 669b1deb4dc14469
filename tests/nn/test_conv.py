"""PoserConv: one round of message passing, its pose mean and its plain-tensor interface."""

from __future__ import annotations

import copy
import dataclasses
import subprocess
import sys

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from posernet.geometry import (
    compose_pose_vec,
    invert_pose_raw,
    invert_pose_vec,
    quaternion_angle,
    symmetric_pose_mean,
)
from posernet.graph import GraphBatch
from posernet.nn import PoserConv, graph_inputs
from posernet.testing import random_view_graph


def random_poses(n: int, seed: int, scale: float = 1.0) -> torch.Tensor:
    """Raw pose vectors with non-unit quaternions (like untrained network outputs)."""
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n, 7, generator=g, dtype=torch.float64) * scale


def same_pose(a: torch.Tensor, b: torch.Tensor, tol: float = 1e-10) -> None:
    assert quaternion_angle(a[..., :4], b[..., :4]).max() < tol
    torch.testing.assert_close(a[..., :4].norm(dim=-1), b[..., :4].norm(dim=-1), atol=tol, rtol=0)
    torch.testing.assert_close(a[..., 4:], b[..., 4:], atol=tol, rtol=0)


# --------------------------------------------------------------------------- pose helpers


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_symmetric_pose_mean_properties(seed: int) -> None:
    a, b, ref = random_poses(3, seed).unbind(0)
    m = symmetric_pose_mean(a, b, ref)
    same_pose(symmetric_pose_mean(b, a, ref), m)  # symmetric
    # inverse-equivariant, exactly: mu(a, b)^-1 = mu(a^-1, b^-1)
    inv = symmetric_pose_mean(invert_pose_raw(a), invert_pose_raw(b), invert_pose_raw(ref))
    same_pose(inv, invert_pose_raw(m))
    torch.testing.assert_close(inv[:4], invert_pose_raw(m)[:4])  # same sign too
    # idempotent on unit poses (and sign-blind: -q is the same rotation)
    u = torch.cat((a[:4] / a[:4].norm(), a[4:]))
    same_pose(symmetric_pose_mean(u, u, ref), u)
    same_pose(symmetric_pose_mean(u, torch.cat((-u[:4], u[4:])), ref), u)


def test_symmetric_pose_mean_is_between_its_inputs() -> None:
    base = torch.tensor([1.0, 0, 0, 0, 0.0, 0, 1], dtype=torch.float64)
    turn = torch.tensor([0.9238795325, 0.3826834324, 0, 0, 0, 0, 0], dtype=torch.float64)  # 45 deg
    b = compose_pose_vec(turn, base)
    m = symmetric_pose_mean(base, b, base)
    ang = torch.rad2deg(quaternion_angle(m[:4], base[:4]))
    assert abs(float(ang) - 22.5) < 1e-6


def test_invert_pose_raw_is_an_involution_and_matches_geometry() -> None:
    p = random_poses(5, 1)
    torch.testing.assert_close(invert_pose_raw(invert_pose_raw(p)), p)
    unit = torch.cat((p[:, :4] / p[:, :4].norm(dim=-1, keepdim=True), p[:, 4:]), dim=-1)
    same_pose(invert_pose_raw(unit), invert_pose_vec(unit))


# --------------------------------------------------------------------------- the layer


def graph(seed: int = 0, **kw):
    return random_view_graph(generator=torch.Generator().manual_seed(seed),
                             dtype=torch.float64, **kw)


def test_tensor_and_graph_interfaces_agree() -> None:
    g = graph(1)
    torch.manual_seed(0)
    conv = PoserConv(4, 16, edge_dim=3).double()
    a = conv(g)
    inp = graph_inputs(g)
    b = conv(inp["x"], inp["edge_index"], inp["edge_pose"], inp["pair_edge"],
             inp["pair_box_src"], inp["pair_box_dst"])
    for u, v in zip(a, b, strict=True):
        torch.testing.assert_close(u, v)
    assert a.x.shape == (g.num_nodes, 16)
    assert a.edge_pose.shape == (g.num_edges, 7)
    assert a.edge_state.shape == (g.num_edges, 2, 3)
    # A GraphBatch is accepted as well.
    c = conv(GraphBatch.from_graphs([g]))
    torch.testing.assert_close(c.edge_pose, a.edge_pose)


def flip_all_edges(g):
    """Every edge stored the other way round: inverse pose, swapped pair detections."""
    return dataclasses.replace(g, edge_index=g.edge_index.flip(0),
                               edge_pose=invert_pose_vec(g.edge_pose),
                               pair_src=g.pair_dst, pair_dst=g.pair_src)


def test_node_state_ignores_the_stored_direction() -> None:
    g = graph(2)
    torch.manual_seed(1)
    conv = PoserConv(4, 8, edge_dim=2).double()
    out = conv(g)
    out2 = conv(flip_all_edges(g).validate())
    torch.testing.assert_close(out2.x, out.x)
    torch.testing.assert_close(out2.edge_state, out.edge_state.flip(1))
    same_pose(out2.edge_pose, invert_pose_raw(out.edge_pose))


def test_nested_and_flat_means() -> None:
    """Nested = mean over neighbours of per-neighbour means; flat = mean over all pairs."""
    # Node 0 hears node 1 through 3 pairs and node 2 through 1 pair.
    x = torch.zeros(3, 4, dtype=torch.float64)
    edge_index = torch.tensor([[0, 0], [1, 2]])
    pose = torch.tensor([[1.0, 0, 0, 0, 1, 0, 0]] * 2, dtype=torch.float64)
    pair_edge = torch.tensor([0, 0, 0, 1])
    boxes = torch.rand(4, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    torch.manual_seed(2)
    nested = PoserConv(4, 5, nested_mean=True).double()
    flat = PoserConv(4, 5, nested_mean=False).double()
    flat.load_state_dict(nested.state_dict())
    hn = nested(x, edge_index, pose, pair_edge, boxes, boxes).x
    hf = flat(x, edge_index, pose, pair_edge, boxes, boxes).x
    # Reference for node 0 from the node MLP applied to each pair's forward view.
    z = torch.cat((x[[0, 0, 0, 0]], x[[1, 1, 1, 2]], pose[pair_edge], boxes, boxes), dim=-1)
    m = nested.psi_node(z)
    torch.testing.assert_close(hn[0], 0.5 * (m[:3].mean(0) + m[3]))
    torch.testing.assert_close(hf[0], m.mean(0))
    assert not torch.allclose(hn[0], hf[0])


def test_isolated_node_gets_zero_state_and_layer_repr() -> None:
    x = torch.randn(3, 4, dtype=torch.float64)
    edge_index = torch.tensor([[0], [1]])
    pose = torch.tensor([[1.0, 0, 0, 0, 0, 0, 1]], dtype=torch.float64)
    box = torch.rand(2, 4, dtype=torch.float64)
    conv = PoserConv(4, 6).double()
    out = conv(x, edge_index, pose, torch.tensor([0, 0]), box, box)
    assert (out.x[2] == 0).all() and out.x[:2].abs().sum() > 0
    assert "PoserConv(node 4 -> 6" in repr(conv)


@pytest.mark.parametrize("residual", [False, True])
def test_last_round_layer_builds_only_what_its_edge_poses_need(residual: bool) -> None:
    """update_nodes=False / update_edge_state=False: no Psi_N, a pose-only Psi_E, the same
    edge poses as a full layer with the same pose weights."""
    g = graph(4)
    torch.manual_seed(3)
    full = PoserConv(4, 8, edge_dim=3, residual=residual).double()
    last = PoserConv(4, 8, edge_dim=3, residual=residual, update_nodes=False,
                     update_edge_state=False).double()
    assert last.psi_node is None and last.psi_edge.out_dim == 7
    assert not any(k.startswith("psi_node.") for k in last.state_dict())
    assert "update_nodes=False" in repr(last) and "update_edge_state=False" in repr(last)
    # the full layer's weights that reach the edge poses: Psi_E, its last layer's pose rows
    weights = {k: v for k, v in full.state_dict().items() if not k.startswith("psi_node.")}
    index = len(full.psi_edge.net) - 1
    for name in ("weight", "bias"):
        weights[f"psi_edge.net.{index}.{name}"] = weights[f"psi_edge.net.{index}.{name}"][:7]
    last.load_state_dict(weights)
    state = torch.randn(g.num_edges, 2, 3, dtype=torch.float64)
    a = full(g, edge_state=state)
    b = last(g, edge_state=state)
    assert b.x is None and b.edge_state is None
    torch.testing.assert_close(b.edge_pose, a.edge_pose, atol=1e-12, rtol=1e-10)  # round-off
    # every parameter of the trimmed layer reaches its output
    b.edge_pose.sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in last.parameters())
    # a full layer can skip the node update for one call (a network sharing one layer)
    inp = graph_inputs(g)
    c = full.propagate(inp["x"], inp["edge_index"], inp["edge_pose"], inp["pair_edge"],
                       inp["pair_box_src"], inp["pair_box_dst"], state, update_nodes=False,
                       update_edge_state=False)
    assert c.x is None and c.edge_state is None
    # round-off only: the fused fast path multiplies Psi_E's first layer alone here and
    # together with Psi_N's in the full call (a different matrix product blocking)
    torch.testing.assert_close(c.edge_pose, a.edge_pose, atol=1e-12, rtol=1e-10)
    with pytest.raises(ValueError, match="update_nodes=False"):
        last.propagate(inp["x"], inp["edge_index"], inp["edge_pose"], inp["pair_edge"],
                       inp["pair_box_src"], inp["pair_box_dst"], state, update_nodes=True)
    # the checked entry point takes the same per-call switches
    d = full(g, edge_state=state, update_nodes=False, update_edge_state=False)
    assert d.x is None and d.edge_state is None
    torch.testing.assert_close(d.edge_pose, a.edge_pose, atol=1e-12, rtol=1e-10)


def test_validation_errors() -> None:
    g = graph(3)
    conv = PoserConv(4, 8).double()
    inp = graph_inputs(g)
    with pytest.raises(ValueError, match="self loop"):
        conv(**{**inp, "edge_index": torch.zeros(2, g.num_edges, dtype=torch.long)})
    with pytest.raises(ValueError, match=r"edge_index values must lie in \[0, 8\)"):
        conv(**{**inp, "edge_index": inp["edge_index"] + 8})
    with pytest.raises(ValueError, match="pair_edge must be 1-D"):
        conv(**{**inp, "pair_edge": inp["pair_edge"][None]})
    with pytest.raises(ValueError, match="edge_state must have shape"):
        PoserConv(4, 8, edge_dim=2).double()(**inp, edge_state=torch.zeros(1, 2, 2))


def test_nn_package_imports_neither_lightning_nor_hydra() -> None:
    """Nor torch_geometric: only ``posernet.nn.pyg`` (imported explicitly) needs it."""
    code = ("import sys, posernet.nn; "
            "bad = [m for m in sys.modules if m.split('.')[0] in ('lightning', 'hydra', "
            "'pytorch_lightning', 'omegaconf', 'torch_geometric')]; print(bad); "
            "sys.exit(1 if bad else 0)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr


# --------------------------------------------------------------------------- PyG-style API


def test_pyg_argument_names() -> None:
    torch.manual_seed(0)
    new = PoserConv(in_channels=4, out_channels=8, edge_dim=2, hidden_channels=16, num_layers=2)
    torch.manual_seed(0)
    positional = PoserConv(4, 8, 2, 16, 2)
    assert {k: v.shape for k, v in positional.state_dict().items()} == \
        {k: v.shape for k, v in new.state_dict().items()}
    for k, v in positional.state_dict().items():
        torch.testing.assert_close(v, new.state_dict()[k], atol=0, rtol=0)
    assert (new.in_channels, new.out_channels, new.hidden_channels, new.num_layers) == \
        (4, 8, 16, 2)
    assert new.message_dim == PoserConv.message_size(4, 2) == 2 * 4 + 7 + 2 + 8
    assert repr(new).startswith("PoserConv(node 4 -> 8, edge_dim=2, hidden=16, layers=2")
    with pytest.raises(TypeError, match="needs in_channels"):
        PoserConv()
    with pytest.raises(ValueError, match="sizes must be positive"):
        PoserConv(in_channels=0)


def test_injected_psi_networks() -> None:
    g = graph(5)
    torch.manual_seed(4)
    ref = PoserConv(4, 8, edge_dim=3).double()
    # the built-in networks passed in: the same layer
    same = PoserConv(4, 8, edge_dim=3, psi_edge=copy.deepcopy(ref.psi_edge),
                     psi_node=copy.deepcopy(ref.psi_node))
    for u, v in zip(same(g), ref(g), strict=True):
        torch.testing.assert_close(u, v, atol=0, rtol=0)
    # networks of your own: any module of the right sizes
    d = PoserConv.message_size(4, edge_dim=3)
    psi_edge = torch.nn.Sequential(torch.nn.Linear(d, 20), torch.nn.Tanh(),
                                   torch.nn.Linear(20, 7 + 3))
    psi_node = torch.nn.Sequential(torch.nn.Linear(d, 5), torch.nn.GELU())
    conv = PoserConv(4, 5, edge_dim=3, psi_edge=psi_edge, psi_node=psi_node).double()
    assert conv.psi_edge is psi_edge and conv.psi_node is psi_node
    assert "psi_edge=Sequential" in repr(conv) and "psi_node=Sequential" in repr(conv)
    out = conv(g)
    assert out.x.shape == (g.num_nodes, 5) and out.edge_state.shape == (g.num_edges, 2, 3)
    (out.x.sum() + out.edge_pose.sum() + out.edge_state.sum()).backward()
    assert all(p.grad is not None for p in conv.parameters())
    before = [p.detach().clone() for p in conv.parameters()]
    conv.reset_parameters()  # reaches the Linear layers inside the Sequential
    assert all(not torch.equal(a, b) for a, b in zip(before, conv.parameters(), strict=True))
    # a network of the wrong width fails with the sizes in the message
    bad = PoserConv(4, 5, psi_edge=torch.nn.Linear(PoserConv.message_size(4), 6)).double()
    with pytest.raises(ValueError, match=r"psi_edge maps \[\d+, 23\] messages to .*, 6\), "
                                         r"expected \[\d+, 7\]"):
        bad(g)
    bad_node = PoserConv(4, 5, psi_node=torch.nn.Linear(PoserConv.message_size(4), 4)).double()
    with pytest.raises(ValueError, match=r"psi_node maps .* expected \[\d+, 5\]"):
        bad_node(g)
    with pytest.raises(ValueError, match="psi_node was given but update_nodes=False"):
        PoserConv(4, 5, update_nodes=False, psi_node=torch.nn.Linear(23, 5))
    with pytest.raises(TypeError, match="psi_edge must be a torch.nn.Module"):
        PoserConv(4, 5, psi_edge=lambda z: z)
    # a pose-only Psi_E of your own for a last-round layer (no hidden-state output)
    last = PoserConv(4, 5, edge_dim=3, update_nodes=False, update_edge_state=False,
                     psi_edge=torch.nn.Linear(PoserConv.message_size(4, 3), 7)).double()
    assert last.edge_out_dim == 7 and last(g).edge_state is None


def test_propagate_is_the_public_round_without_checks() -> None:
    g = graph(6)
    torch.manual_seed(5)
    conv = PoserConv(4, 8, edge_dim=2).double()
    assert not hasattr(conv, "_propagate")
    inp = graph_inputs(g)
    a = conv(**inp)
    b = conv.propagate(**inp)  # edge_state defaults to zeros, as in forward
    for u, v in zip(a, b, strict=True):
        torch.testing.assert_close(u, v, atol=0, rtol=0)

"""The fast paths compute what the literal ones compute, up to float round-off.

``PoserConv(fused=True)`` (the default) splits and fuses the MLPs' first layers and runs CPU
inference in edge blocks; ``fused=False`` is the literal round (one concatenated message per
matched pair through each network), i.e. the implementation before the optimisation. Every
configuration is compared in float64 (agreement to ~1e-12: the same maths) and float32 (to
round-off), outputs and gradients, on the three execution modes of the fast path.
"""

from __future__ import annotations

import copy

import pytest
import torch

import posernet.nn.conv as conv_module
from posernet.graph import GraphBatch
from posernet.nn import MLP, PoserConv, PoserNet, graph_inputs
from posernet.testing import random_view_graph

F64, F32 = torch.float64, torch.float32
TOL = {F64: {"atol": 1e-11, "rtol": 1e-9}, F32: {"atol": 2e-5, "rtol": 1e-4}}


def batch(dtype: torch.dtype, n: int = 6, seed: int = 0, **kw) -> GraphBatch:
    g = torch.Generator().manual_seed(seed)
    graphs = [random_view_graph(generator=g, dtype=dtype, name=f"e{i}", **kw) for i in range(n)]
    return GraphBatch.from_graphs(graphs)


def set_fused(module: torch.nn.Module, fused: bool) -> torch.nn.Module:
    for m in module.modules():
        if isinstance(m, PoserConv):
            m.fused = fused
    return module


def pair(dtype: torch.dtype, seed: int = 0, **kw) -> tuple[PoserNet, PoserNet]:
    """The same weights twice: fast path and literal path."""
    torch.manual_seed(seed)
    fast = PoserNet(**kw).to(dtype)
    slow = set_fused(copy.deepcopy(fast), False)
    return fast, slow


CONFIGS = [
    {},
    {"depth": 3, "edge_hidden": 4},
    {"shared_weights": True},
    {"shared_weights": True, "depth": 1, "edge_hidden": 2},
    {"residual": True, "nested_mean": False, "unit_output": True},
    {"mlp_layers": 1},
    {"mlp_layers": 2, "negative_slope": 0.2, "mlp_hidden": 16},
]


@pytest.fixture(params=["all", "blocks"])
def mode(request, monkeypatch) -> str:
    """``blocks``: CPU inference in edge blocks of a few pairs (the paper-size path)."""
    if request.param == "blocks":
        monkeypatch.setattr(conv_module, "_BLOCK_PAIRS", 7)
    return request.param


@pytest.mark.parametrize("cfg", CONFIGS)
@pytest.mark.parametrize("dtype", [F64, F32])
def test_network_outputs_match_the_literal_path(cfg: dict, dtype: torch.dtype,
                                                mode: str) -> None:
    b = batch(dtype)
    fast, slow = pair(dtype, **cfg)
    with torch.no_grad():
        ref = slow(b, return_all=True)
        got = fast(b, return_all=True)
    for u, v in zip(got, ref, strict=True):
        torch.testing.assert_close(u, v, **TOL[dtype])


@pytest.mark.parametrize("cfg", CONFIGS)
@pytest.mark.parametrize("dtype", [F64, F32])
def test_gradients_match_the_literal_path(cfg: dict, dtype: torch.dtype) -> None:
    b = batch(dtype, seed=1)
    fast, slow = pair(dtype, seed=2, **cfg)
    weights = torch.linspace(-1, 1, b.num_edges * 7, dtype=dtype).view(-1, 7)
    for net in (fast, slow):
        (net(b) * weights).sum().backward()
    for (name, p), q in zip(fast.named_parameters(), slow.parameters(), strict=True):
        assert p.grad is not None, name
        scale = float(q.grad.abs().max()) + 1e-30
        torch.testing.assert_close(p.grad / scale, q.grad / scale, **TOL[dtype], msg=name)


def test_unsorted_pairs_edges_without_pairs_and_isolated_nodes(mode: str) -> None:
    """Blocks sort the pairs by edge (stably): any pair order, empty edges, lone nodes."""
    b = batch(F64, n=4, seed=3)
    perm = torch.randperm(b.num_pairs, generator=torch.Generator().manual_seed(0))
    keep = perm[: b.num_pairs * 2 // 3]  # drops every pair of some edges
    b.pair_edge, b.pair_src, b.pair_dst = b.pair_edge[keep], b.pair_src[keep], b.pair_dst[keep]
    b.node_attr = torch.cat((b.node_attr, torch.rand(2, 4, dtype=F64)))  # two isolated nodes
    for cfg in ({}, {"edge_hidden": 3, "nested_mean": False}):
        fast, slow = pair(F64, **cfg)
        with torch.no_grad():
            torch.testing.assert_close(fast(b), slow(b), **TOL[F64])


def test_layer_outputs_node_states_and_edge_states_match(mode: str) -> None:
    b = batch(F64, seed=4)
    inp = graph_inputs(b)
    torch.manual_seed(5)
    fast = PoserConv(4, 8, edge_dim=3, residual=True).double()
    slow = copy.deepcopy(fast)
    slow.fused = False
    state = torch.randn(b.num_edges, 2, 3, dtype=F64)
    with torch.no_grad():
        for kw in ({}, {"update_nodes": False, "update_edge_state": False}):
            for u, v in zip(fast(**inp, edge_state=state, **kw), slow(**inp, edge_state=state,
                                                                     **kw), strict=True):
                if v is None:
                    assert u is None
                else:
                    torch.testing.assert_close(u, v, **TOL[F64])


def test_only_the_builtin_mlp_takes_the_fast_path() -> None:
    """A generic Psi network (or a hooked MLP) runs the literal path, and gives the same result
    as that path; an injected MLP instance is the built-in network and is fused."""
    conv = PoserConv(4, 8)
    assert conv._fusable_nets(True) is not None
    seq = PoserConv(4, 8, psi_edge=torch.nn.Sequential(torch.nn.Linear(23, 7)))
    assert seq._fusable_nets(True) is None
    injected = PoserConv(4, 8, psi_edge=MLP(23, 7, num_layers=2, act_last=False),
                         psi_node=MLP(23, 8, hidden=5, num_layers=4))
    assert injected._fusable_nets(True) is not None
    hooked = copy.deepcopy(injected)
    calls = []
    hooked.psi_node.register_forward_hook(lambda *a: calls.append(1))
    assert hooked._fusable_nets(True) is None and hooked._fusable_nets(False) is not None
    b = batch(F32, n=2)
    with torch.no_grad():
        out = hooked(b)
        assert calls  # the hook ran: the literal path was taken
        ref = copy.deepcopy(injected)
        ref.fused = False
        torch.testing.assert_close(injected(b).edge_pose, ref(b).edge_pose, **TOL[F32])
        torch.testing.assert_close(out.x, ref(b).x, **TOL[F32])


def test_blocked_inference_is_deterministic_and_matches_the_unblocked_path(monkeypatch) -> None:
    b = batch(F32, n=8, seed=6)
    fast, _ = pair(F32)
    with torch.no_grad():
        whole = fast(b)
        monkeypatch.setattr(conv_module, "_BLOCK_PAIRS", 5)
        first, second = fast(b), fast(b)
    assert torch.equal(first, second)
    torch.testing.assert_close(first, whole, **TOL[F32])


def test_state_dict_is_unchanged_by_the_fast_path() -> None:
    """The fused weights are views built at run time: the stored parameters keep their names
    and shapes, so checkpoints load both ways."""
    fast, slow = pair(F32, edge_hidden=2)
    assert {k: v.shape for k, v in fast.state_dict().items()} == \
        {k: v.shape for k, v in slow.state_dict().items()}
    fresh = PoserNet(edge_hidden=2)
    fresh.load_state_dict(slow.state_dict())

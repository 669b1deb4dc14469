"""``torch.compile`` on PoserNet (CPU): no graph breaks from our code, same outputs as eager."""

from __future__ import annotations

import pytest
import torch

from posernet.graph import GraphBatch
from posernet.nn import PoserConv, PoserNet
from posernet.testing import random_view_graph


def batch(n: int = 3, seed: int = 0) -> GraphBatch:
    g = torch.Generator().manual_seed(seed)
    return GraphBatch.from_graphs([random_view_graph(generator=g, name=f"c{i}")
                                   for i in range(n)])


def model(fused: bool = True, **kwargs) -> PoserNet:
    torch.manual_seed(0)
    m = PoserNet(**kwargs)
    for conv in m.modules():
        if isinstance(conv, PoserConv):
            conv.fused = fused
    return m


@pytest.mark.parametrize(("cfg", "fused"), [
    ({}, True),
    ({}, False),  # the literal path (custom Psi networks take it) traces without breaks too
    ({"edge_hidden": 3, "depth": 3, "residual": True}, True),
    ({"shared_weights": True, "nested_mean": False}, True),
])
def test_dynamo_traces_the_model_in_one_graph(cfg: dict, fused: bool) -> None:
    """The input checks (index ranges, self loops) run inside the graph as an asynchronous
    assertion instead of a host sync, so nothing breaks the graph."""
    torch._dynamo.reset()
    explain = torch._dynamo.explain(model(fused, **cfg))(batch())
    assert explain.graph_break_count == 0, [r.reason for r in explain.break_reasons]
    assert explain.graph_count == 1


@pytest.mark.slow
def test_compiled_model_matches_eager_on_cpu() -> None:
    """Inductor on the CPU (about 30 s here): outputs equal to eager up to float round-off,
    gradients as well, and a bad index still fails inside the compiled graph."""
    torch._dynamo.reset()
    m = model()
    b = batch()
    compiled = torch.compile(m)
    with torch.no_grad():
        torch.testing.assert_close(compiled(b), m(b), atol=1e-5, rtol=0)
    y = compiled(b)
    y.square().sum().backward()
    grads = {n: p.grad.clone() for n, p in m.named_parameters()}
    m.zero_grad()
    m(b).square().sum().backward()
    for n, p in m.named_parameters():
        torch.testing.assert_close(grads[n], p.grad, atol=1e-4, rtol=1e-4, msg=n)
    bad = batch()
    bad.pair_edge = bad.pair_edge + bad.num_edges
    with pytest.raises(RuntimeError, match="out of range"), torch.no_grad():
        compiled(bad)

"""The forward of the paper-architecture checkpoint gives the numbers the code printed before
the block reductions became sparse products (``OLD_*``), blocked (CPU inference) and not."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import posernet.nn.conv as conv_module
from posernet.graph import GraphBatch
from posernet.nn import PoserNet
from posernet.testing import random_view_graph

# Printed by the code before (12 random paper-size graphs, seed 11, float64, return_all):
OLD_SUM = [14.370630708543, 157.312351838283]  # per round: sum of all outputs
OLD_ABS = [733.645831953945, 660.292020803596]  # per round: sum of |outputs|
OLD_FIRST = [0.891582833674, -0.119707473799, -0.286358401409, 0.329771189399,
             -0.932779575468, -0.280013687205, 0.226968276565]  # last round, first edge
OLD_LAST = [0.986776096113, 0.023340642967, -0.011989187185, 0.159951273568,
            -0.293323940733, -0.121365253573, 0.948278198114]  # last round, last edge


@pytest.mark.parametrize("block", [256, 10**9])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_shipped_network_gives_the_old_numbers(block: int, dtype: torch.dtype,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(conv_module, "_BLOCK_PAIRS", block)  # 256: the blocked CPU path
    g = torch.Generator().manual_seed(11)
    graphs = [random_view_graph(num_nodes=8, extra_edges=12, pairs_per_edge=(5, 15),
                                dets_per_node=30, generator=g, dtype=torch.float64,
                                name=f"p{i}") for i in range(12)]
    b = GraphBatch.from_graphs(graphs)
    b = b.apply(lambda t: t.to(dtype) if t.is_floating_point() else t)
    model = PoserNet.from_checkpoint("shipped:posernet_synthetic_kp_v1.ckpt").to(dtype)
    with torch.no_grad():
        out = model(b, return_all=True)
    tol = 1e-10 if dtype == torch.float64 else 2e-4
    np.testing.assert_allclose([float(o.double().sum()) for o in out], OLD_SUM, rtol=tol,
                               atol=tol * 100)
    np.testing.assert_allclose([float(o.double().abs().sum()) for o in out], OLD_ABS,
                               rtol=tol)
    np.testing.assert_allclose(out[-1][0].double().numpy(), OLD_FIRST, atol=tol)
    np.testing.assert_allclose(out[-1][-1].double().numpy(), OLD_LAST, atol=tol)

"""PyTorch Geometric interop: ``PoserData`` batched by PyG's own ``Batch`` equals ``GraphBatch``.

Skipped when torch_geometric is not installed (it is an optional test dependency).
"""

from __future__ import annotations

import dataclasses

import pytest

pytest.importorskip("torch_geometric")

import torch
from torch_geometric.data import Batch, Data
from torch_geometric.loader import DataLoader
from torch_geometric.nn import GCNConv
from torch_geometric.utils import to_undirected

from posernet.graph import GraphBatch, ViewGraph
from posernet.nn import PoserConv, PoserNet, graph_inputs
from posernet.nn.pyg import GraphMeta, PoserData
from posernet.testing import random_view_graph

PAIR_FIELDS = ("pair_edge", "pair_src", "pair_dst")


def three_graphs(dtype: torch.dtype = torch.float64) -> list[ViewGraph]:
    """Three small graphs of different sizes, with estimates and metadata."""
    graphs = []
    for i, n in enumerate((5, 7, 4)):
        g = random_view_graph(num_nodes=n, extra_edges=i + 2, dets_per_node=6 + i,
                              generator=torch.Generator().manual_seed(10 + i), dtype=dtype,
                              name=f"g{i}")
        g.estimates["kp"] = g.edge_pose.clone()
        g.meta.update(scene="chess", index=i)
        graphs.append(g.validate())
    return graphs


def assert_same_graph(a: ViewGraph, b: ViewGraph) -> None:
    assert type(a) is type(b)
    for f in dataclasses.fields(a):
        u, v = getattr(a, f.name), getattr(b, f.name)
        if isinstance(u, torch.Tensor):
            assert isinstance(v, torch.Tensor) and u.dtype == v.dtype, f.name
            torch.testing.assert_close(u, v, atol=0, rtol=0, msg=f.name)
        elif isinstance(u, dict) and u and isinstance(next(iter(u.values())), torch.Tensor):
            assert u.keys() == v.keys(), f.name
            for k in u:
                torch.testing.assert_close(u[k], v[k], atol=0, rtol=0, msg=f"{f.name}[{k}]")
        else:
            assert u == v, f.name


# --------------------------------------------------------------------------- batching


def test_pyg_batch_offsets_every_index_field_like_graph_batch() -> None:
    graphs = three_graphs()
    batch = Batch.from_data_list([PoserData.from_view_graph(g) for g in graphs])
    ours = GraphBatch.from_graphs(graphs)
    assert isinstance(batch, PoserData) and batch.num_graphs == 3
    for k in ("edge_index", "det_node", *PAIR_FIELDS, "edge_pose", "det_box", "K"):
        torch.testing.assert_close(batch[k], getattr(ours, k), atol=0, rtol=0, msg=k)
    torch.testing.assert_close(batch.node_attr, ours.node_attr, atol=0, rtol=0)
    assert batch.node_attr is batch.x  # PyG's name for node features, ViewGraph's alias
    torch.testing.assert_close(batch.batch, ours.node_batch, atol=0, rtol=0)
    torch.testing.assert_close(batch.ptr, ours.ptr, atol=0, rtol=0)
    torch.testing.assert_close(batch.estimates["kp"], ours.estimates["kp"], atol=0, rtol=0)
    assert batch.meta == [GraphMeta(g.meta) for g in graphs]
    # the plain-tensor inputs of the network are identical
    a, b = graph_inputs(batch), graph_inputs(ours)
    for k in a:
        torch.testing.assert_close(a[k], b[k], atol=0, rtol=0, msg=k)


@pytest.mark.parametrize("cfg", [{}, {"residual": True, "edge_hidden": 3},
                                 {"shared_weights": True, "depth": 3, "nested_mean": False}])
def test_posernet_on_a_pyg_batch_equals_graph_batch(cfg: dict) -> None:
    graphs = three_graphs()
    torch.manual_seed(0)
    model = PoserNet(**cfg).double()
    pyg = model(Batch.from_data_list([PoserData.from_view_graph(g) for g in graphs]),
                return_all=True)
    ours = model(GraphBatch.from_graphs(graphs), return_all=True)
    for u, v in zip(pyg, ours, strict=True):
        torch.testing.assert_close(u, v)  # float round-off at most (here: identical)
    # and one graph at a time
    for g, sl in zip(graphs, torch.split(ours[-1], [g.num_edges for g in graphs]), strict=True):
        torch.testing.assert_close(model(PoserData.from_view_graph(g)), sl)


def test_poserconv_on_a_pyg_batch_and_pyg_data_loader() -> None:
    graphs = three_graphs(torch.float32)
    torch.manual_seed(1)
    conv = PoserConv(in_channels=4, out_channels=8, edge_dim=2)
    want = conv(GraphBatch.from_graphs(graphs))
    loader = DataLoader([PoserData.from_view_graph(g) for g in graphs], batch_size=3)
    (batch,) = list(loader)
    got = conv(batch)
    for u, v in zip(got, want, strict=True):
        torch.testing.assert_close(u, v)


def test_plain_pyg_data_does_not_offset_pair_edge() -> None:
    """Why PoserData exists: PyG offsets only fields named '*index*', so a plain Data batches
    ``pair_edge`` (and the pair detections) unchanged, and the pairs of the second graph point
    at the first graph's edges. The network refuses such a batch instead of refining wrongly."""
    graphs = three_graphs()
    plain = [Data(node_attr=g.node_attr, edge_index=g.edge_index, edge_pose=g.edge_pose,
                  det_box=g.det_box, det_node=g.det_node, pair_edge=g.pair_edge,
                  pair_src=g.pair_src, pair_dst=g.pair_dst) for g in graphs]
    naive = Batch.from_data_list(plain)
    ours = GraphBatch.from_graphs(graphs)
    torch.testing.assert_close(naive.edge_index, ours.edge_index, atol=0, rtol=0)  # offset
    for k in (*PAIR_FIELDS, "det_node"):  # not offset: plain concatenation
        torch.testing.assert_close(naive[k], torch.cat([getattr(g, k) for g in graphs]),
                                   atol=0, rtol=0, msg=k)
        assert not torch.equal(naive[k], getattr(ours, k)), k
    model = PoserNet().double()
    with pytest.raises(ValueError, match=r"batched 'pair_edge' without adding the number of "
                                         r"edges.*PoserData\.from_view_graph"):
        model(naive)
    with pytest.raises(ValueError, match="PoserData.from_view_graph"):
        PoserConv(4).double()(naive)
    # one plain graph on its own needs no offsets
    torch.testing.assert_close(model(plain[0]), model(graphs[0]))


# --------------------------------------------------------------------------- conversions


def test_view_graph_round_trip() -> None:
    graphs = three_graphs()
    for g in graphs:
        d = PoserData.from_view_graph(g)
        assert d.num_nodes == g.num_nodes and d.num_edges == g.num_edges
        assert d.num_dets == g.num_dets and d.num_pairs == g.num_pairs and d.name == g.name
        assert_same_graph(d.to_view_graph(), g)
        assert d.validate_graph() is d
    # optional fields stay absent, metadata of any plain type survives (PyG would split a dict)
    bare = dataclasses.replace(graphs[0], edge_pose_gt=None, pose_gt=None, estimates={},
                               meta={"name": "bare", "sequences": ["seq-01", "seq-02"]})
    d = PoserData.from_view_graph(bare)
    assert "edge_pose_gt" not in d and "pose_gt" not in d
    assert_same_graph(d.to_view_graph(), bare)
    # a PyG batch converts to the GraphBatch of its graphs, and splits back into them
    batch = Batch.from_data_list([PoserData.from_view_graph(g) for g in graphs])
    assert_same_graph(batch.to_view_graph(), GraphBatch.from_graphs(graphs))
    for d, g in zip(batch.to_data_list(), graphs, strict=True):
        assert type(d) is PoserData
        assert_same_graph(d.to_view_graph(), g)
    with pytest.raises(TypeError, match="one by one"):
        PoserData.from_view_graph(GraphBatch.from_graphs(graphs))
    with pytest.raises(ValueError, match="has no field"):
        PoserData(x=graphs[0].node_attr).to_view_graph()


# --------------------------------------------------------------------------- in a PyG model


class TinyPygModel(torch.nn.Module):
    """A PyG layer on the camera attributes, then one PoserConv round."""

    def __init__(self) -> None:
        super().__init__()
        self.gcn = GCNConv(4, 16)
        self.poser = PoserConv(in_channels=16, out_channels=8, hidden_channels=16)

    def forward(self, data: PoserData):
        h = self.gcn(data.x, to_undirected(data.edge_index, num_nodes=data.num_nodes)).relu()
        return self.poser(**{**graph_inputs(data), "x": h})


def test_tiny_pyg_model_forward_backward() -> None:
    graphs = three_graphs(torch.float32)
    batch = Batch.from_data_list([PoserData.from_view_graph(g) for g in graphs])
    batch.x = torch.rand(batch.x.shape, generator=torch.Generator().manual_seed(0))
    torch.manual_seed(2)
    model = TinyPygModel()
    out = model(batch)
    assert out.x.shape == (batch.num_nodes, 8) and out.edge_pose.shape == (batch.num_edges, 7)
    (out.x.square().mean() + (out.edge_pose - batch.edge_pose).square().mean()).backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name

"""ViewGraph / GraphBatch: contract validation, batching offsets, storage."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from posernet import GraphBatch, GraphValidationError, ViewGraph, load_graphs, save_graphs
from posernet.graph import denormalize_boxes, node_attributes, normalize_boxes
from posernet.io import atomic_path
from posernet.testing import random_view_graph


def graphs(n: int = 3, seed: int = 0) -> list[ViewGraph]:
    g = torch.Generator().manual_seed(seed)
    return [random_view_graph(num_nodes=4 + i, extra_edges=i, generator=g, name=f"g{i}")
            for i in range(n)]


def assert_same(a: ViewGraph, b: ViewGraph) -> None:
    for k, v in a.to_dict().items():
        if isinstance(v, torch.Tensor):
            assert torch.equal(v, getattr(b, k)), k
    assert a.estimates.keys() == b.estimates.keys()
    for k in a.estimates:
        assert torch.equal(a.estimates[k], b.estimates[k])
    assert a.meta == b.meta


def test_random_graph_is_valid():
    for g in graphs():
        g.validate()
        # pairs connect detections of the edge's two images
        assert torch.equal(g.det_node[g.pair_src], g.edge_index[0, g.pair_edge])


def test_batch_offsets_every_index_field():
    gs = graphs()
    b = GraphBatch.from_graphs(gs)
    b.validate()
    assert b.num_graphs == 3
    assert b.ptr.tolist() == [0, 4, 9, 15]
    n_off, e_off, d_off = 0, 0, 0
    for i, g in enumerate(gs):
        es = slice(int(b.edge_ptr[i]), int(b.edge_ptr[i + 1]))
        ds = slice(int(b.det_ptr[i]), int(b.det_ptr[i + 1]))
        ps = slice(int(b.pair_ptr[i]), int(b.pair_ptr[i + 1]))
        assert torch.equal(b.edge_index[:, es], g.edge_index + n_off)
        assert torch.equal(b.det_node[ds], g.det_node + n_off)
        assert torch.equal(b.pair_edge[ps], g.pair_edge + e_off)
        assert torch.equal(b.pair_src[ps], g.pair_src + d_off)
        assert torch.equal(b.pair_dst[ps], g.pair_dst + d_off)
        assert bool((b.node_batch[n_off:n_off + g.num_nodes] == i).all())
        assert bool((b.edge_batch[es] == i).all())
        n_off += g.num_nodes
        e_off += g.num_edges
        d_off += g.num_dets


def test_batch_split_round_trip_is_exact():
    gs = graphs(4)
    gs[1].estimates = {"kp": gs[1].edge_pose, "bb": gs[1].edge_pose * 2}
    for g in gs:
        g.estimates = {"kp": g.edge_pose.clone()}
    back = GraphBatch.from_graphs(gs).to_graphs()
    assert len(back) == 4
    for a, b in zip(gs, back, strict=True):
        assert_same(a, b)


def test_batch_of_batches_and_single_graph():
    gs = graphs(2)
    b = GraphBatch.from_graphs(gs[:1])
    assert b.num_graphs == 1
    assert_same(b.to_graphs()[0], gs[0])


def test_optional_fields_dropped_unless_all_graphs_have_them():
    gs = graphs(2)
    gs[0] = dataclasses.replace(gs[0], pose_gt=None)
    b = GraphBatch.from_graphs(gs)
    assert b.pose_gt is None
    assert b.edge_pose_gt is not None


def test_to_device_copies():
    g = graphs(1)[0]
    h = g.to("cpu")
    assert h is not g and torch.equal(h.edge_pose, g.edge_pose)
    b = GraphBatch.from_graphs(graphs(2)).to("cpu")
    assert isinstance(b, GraphBatch) and b.num_graphs == 2


def test_with_estimate():
    g = graphs(1)[0]
    g.estimates = {"bb": torch.zeros_like(g.edge_pose)}
    assert torch.equal(g.with_estimate("bb").edge_pose, g.estimates["bb"])
    with pytest.raises(KeyError, match="no initial estimate 'kp'"):
        g.with_estimate("kp")


# --------------------------------------------------------------------------- validation


def broken(**changes) -> ViewGraph:
    g = graphs(1)[0]
    return dataclasses.replace(g, **changes)


@pytest.mark.parametrize(
    "make,match",
    [
        (lambda g: dict(edge_pose=g.edge_pose[:, :6]), "'edge_pose' has shape"),
        (lambda g: dict(edge_index=g.edge_index.float()), "must be torch.long"),
        (lambda g: dict(edge_index=g.edge_index + 100), "'edge_index' out of range"),
        (lambda g: dict(pair_src=g.pair_dst), r"\('pair_src'\) is not in the source image"),
        (lambda g: dict(pair_edge=torch.full_like(g.pair_edge, 10_000)), "'pair_edge' out of"),
        (lambda g: dict(det_box=g.det_box.index_fill(0, torch.tensor([2]), float("nan"))),
         "'det_box' has a NaN/inf value \\(row 2\\)"),
        (lambda g: dict(edge_pose=g.edge_pose.index_fill(1, torch.tensor([0, 1, 2, 3]), 0.0)),
         "zero quaternion"),
        (lambda g: dict(edge_index=torch.cat((g.edge_index, g.edge_index[:, :1].flip(0)), 1),
                        edge_pose=torch.cat((g.edge_pose, g.edge_pose[:1])),
                        edge_pose_gt=torch.cat((g.edge_pose_gt, g.edge_pose_gt[:1]))),
         "stored more than once"),
        (lambda g: dict(edge_index=torch.tensor([[0], [0]]), edge_pose=g.edge_pose[:1],
                        edge_pose_gt=None, pair_edge=g.pair_edge[:0], pair_src=g.pair_src[:0],
                        pair_dst=g.pair_dst[:0]), "self loop"),
        (lambda g: dict(estimates={"bb": g.edge_pose[:2]}), "estimate 'bb' has shape"),
    ],
)
def test_validation_names_the_field(make, match):
    g = graphs(1)[0]
    bad = dataclasses.replace(g, **make(g))
    with pytest.raises(GraphValidationError, match=match) as info:
        bad.validate()
    assert "graph 'g0'" in str(info.value)


def test_missing_required_field():
    with pytest.raises(GraphValidationError, match="'det_box' is missing"):
        broken(det_box=None).validate()


# --------------------------------------------------------------------------- normalisation


def test_box_normalisation_round_trip():
    size = torch.tensor([[640.0, 480.0]])
    xyxy = torch.tensor([[0.0, 0.0, 640.0, 480.0], [100.0, 50.0, 164.0, 98.0]])
    n = normalize_boxes(xyxy, size)
    assert torch.allclose(n[0], torch.tensor([0.0, 0.0, 1.0, 1.0]))
    assert torch.allclose(n[1], torch.tensor([132 / 320 - 1, 74 / 240 - 1, 0.1, 0.1]))
    assert torch.allclose(denormalize_boxes(n, size), xyxy, atol=1e-4)


def test_node_attributes_reference_camera_is_zero():
    K = torch.tensor([[[585.0, 0, 320], [0, 585.0, 240], [0, 0, 1]]])
    attr = node_attributes(K, torch.tensor([[640.0, 480.0]]))
    assert torch.allclose(attr, torch.zeros(1, 4))


# --------------------------------------------------------------------------- storage


def test_save_load_round_trip(tmp_path):
    gs = graphs(3)
    for g in gs:
        g.estimates = {"kp": g.edge_pose, "bb": g.edge_pose.flip(0)}
        g.meta.update(scene="chess", split="test")
    path = save_graphs(tmp_path / "g.pt", gs, extra={"seed": 1})
    assert [p.name for p in tmp_path.iterdir()] == ["g.pt"]  # no temp file left behind
    back = load_graphs(path)
    for a, b in zip(gs, back, strict=True):
        assert_same(a, b)


def test_load_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        load_graphs(tmp_path / "missing.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a torch file")
    with pytest.raises(GraphValidationError, match="junk.pt"):
        load_graphs(junk)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, other)
    with pytest.raises(GraphValidationError, match="other.pt: not a posernet graph file"):
        load_graphs(other)


def test_load_rejects_invalid_graph_in_file(tmp_path):
    gs = graphs(2)
    path = save_graphs(tmp_path / "g.pt", gs)
    payload = torch.load(path, weights_only=True)
    payload["tensors"]["edge_pose"][3] = float("nan")
    torch.save(payload, path)
    # Row 3 of the concatenated edges is edge 0 of the second graph (the first has 3 edges).
    expected = r"g.pt: graph 1 \('g1'\): field 'edge_pose' has a NaN/inf value \(row 0\)"
    with pytest.raises(GraphValidationError, match=expected):
        load_graphs(path)


def test_load_does_not_execute_pickled_code(tmp_path):
    class Evil:
        def __reduce__(self):
            return (exec, ("raise SystemExit('pwned')",))

    path = tmp_path / "evil.pt"
    torch.save({"format": "posernet-graphs", "evil": Evil()}, path)
    with pytest.raises(GraphValidationError, match="evil.pt"):
        load_graphs(path)


def test_interrupted_write_leaves_old_file(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("interrupted")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_refuses_empty_graph_list(tmp_path):
    with pytest.raises(GraphValidationError, match="empty"):
        save_graphs(tmp_path / "e.pt", [])
    with pytest.raises(GraphValidationError, match="empty list"):
        GraphBatch.from_graphs([])


def test_save_refuses_what_load_would_reject(tmp_path):
    gs = graphs(2)
    ep = gs[1].edge_pose.clone()
    ep[0, 5] = float("nan")
    gs[1] = dataclasses.replace(gs[1], edge_pose=ep)
    expected = r"n.pt: graph 1 \('g1'\): field 'edge_pose' has a NaN/inf value \(row 0\)"
    with pytest.raises(GraphValidationError, match=expected):
        save_graphs(tmp_path / "n.pt", gs)
    bad_index = dataclasses.replace(graphs(1)[0], det_node=graphs(1)[0].det_node + 100)
    with pytest.raises(GraphValidationError, match=r"graph 0 \('g0'\): index field 'det_node'"):
        save_graphs(tmp_path / "n.pt", [bad_index])
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- one edge-index check


def test_one_edge_index_check_for_graphs_layers_and_backends():
    """graph.validate, PoserConv and the sync backends report a bad edge_index alike."""
    from posernet.graph import check_edge_index
    from posernet.nn import PoserConv, graph_inputs
    from posernet.sync import get_backend

    g = graphs(1)[0]
    loop = g.edge_index.clone()
    loop[1, 1] = loop[0, 1]
    out = g.edge_index.clone()
    out[1, 0] = g.num_nodes
    conv = PoserConv(4, 8).to(g.node_attr.dtype)
    backend = get_backend("eig_se3")
    cases = ((loop, r"edge_index has a self loop: edge 1 on node \d+ \(source == target\)"),
             (out, rf"index field 'edge_index' out of range: edge_index values must lie in "
                   rf"\[0, {g.num_nodes}\) \({g.num_nodes} nodes\), got \[0, {g.num_nodes}\]"),
             (g.edge_index.float(), "edge_index must be torch.long, got torch.float32"))
    for ei, match in cases:
        with pytest.raises(ValueError, match=match):
            check_edge_index(ei, g.num_nodes)
        with pytest.raises(GraphValidationError, match="graph 'g0': " + match):
            dataclasses.replace(g, edge_index=ei).validate()
        with pytest.raises(ValueError, match="PoserConv: " + match):
            conv(**{**graph_inputs(g), "edge_index": ei})
        if ei.dtype == torch.long:  # the backends cast to long first
            with pytest.raises(ValueError, match=match):
                backend.solve(dataclasses.replace(g, edge_index=ei))
    with pytest.raises(ValueError, match=r"edge_index must have shape \[2, E\], got \(3, 2\)"):
        check_edge_index(torch.zeros(3, 2, dtype=torch.long), 4)
    with pytest.raises(ValueError, match=r"batch.edge_index must have shape \[2, E\]"):
        backend.solve(dataclasses.replace(g, edge_index=g.edge_index[0]), g.edge_pose)
    check_edge_index(torch.zeros(2, 0, dtype=torch.long), 0)  # no edges: nothing to check
    with pytest.raises(ValueError, match=r"index field 'pair_edge' out of range"):
        check_edge_index(g.edge_index, g.num_nodes,
                         others=(("pair_edge", g.pair_edge + g.num_edges, g.num_edges, "edges"),))

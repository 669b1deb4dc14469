"""Reader/writer of the authors' graph JSON, against a file written by hand in their schema."""

from __future__ import annotations

import copy
import json
import math

import pytest
import torch

from posernet import GraphValidationError
from posernet import geometry as G
from posernet.data import load_posernet_json, save_posernet_json
from posernet.graph import denormalize_boxes
from posernet.testing import random_view_graph

K = [[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]]


def c2w(yaw_deg: float, centre: list[float]) -> list[list[float]]:
    R = G.axis_angle_to_rotation_matrix(torch.tensor([0.0, math.radians(yaw_deg), 0.0],
                                                     dtype=torch.float64))
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = R
    T[:3, 3] = torch.tensor(centre, dtype=torch.float64)
    return T.tolist()


def rel(c2w_i, c2w_f) -> list[list[float]]:
    """inv(c2w_f) @ c2w_i: maps camera-i points into camera f (the schema's definition)."""
    f, i = torch.tensor(c2w_f, dtype=torch.float64), torch.tensor(c2w_i, dtype=torch.float64)
    return (torch.linalg.inv(f) @ i).tolist()


def perturbed(T: list[list[float]], deg: float) -> list[list[float]]:
    R = G.axis_angle_to_rotation_matrix(torch.tensor([math.radians(deg), 0.0, 0.0],
                                                     dtype=torch.float64))
    M = torch.tensor(T, dtype=torch.float64)
    M[:3, :3] = R @ M[:3, :3]
    return M.tolist()


def schema_graph() -> dict:
    """Three cameras, covisible pairs (a, b) and (b, c), written as the authors' README says."""
    poses = {"a": c2w(0, [0, 0, 0]), "b": c2w(20, [0.5, 0, 0]), "c": c2w(-15, [0, 0.2, 0.4])}
    boxes = {
        ("a", "b"): [([10, 10, 50, 60], [30, 12, 70, 62]),
                     ([100, 100, 140, 180], [120, 98, 160, 178])],
        ("b", "c"): [([30, 12, 70, 62], [5, 20, 45, 70])],
    }
    cams = {}
    for cid in poses:
        cams[cid] = {
            "camera_to_world": poses[cid], "K": K,
            "K_i": torch.linalg.inv(torch.tensor(K)).tolist(),
            "image_path": f"/data01/7Scenes/fire/seq-0{ord(cid) - 96}/frame-000001.color.png",
            "matches": {},
        }
    for (i, f), lst in boxes.items():
        cams[i]["matches"][f] = [{"bb_i": bi, "bb_f": bf} for bi, bf in lst]
        cams[f]["matches"][i] = [{"bb_i": bf, "bb_f": bi} for bi, bf in lst]
    rel_poses = {
        "a": {"b": {"ground_truth": rel(poses["a"], poses["b"]),
                    "feature_5pt": perturbed(rel(poses["a"], poses["b"]), 5.0),
                    "bb_centre_5pt": perturbed(rel(poses["a"], poses["b"]), 30.0)}},
        "b": {"c": {"ground_truth": rel(poses["b"], poses["c"]),
                    "feature_5pt": perturbed(rel(poses["b"], poses["c"]), 5.0),
                    "bb_centre_5pt": perturbed(rel(poses["b"], poses["c"]), 30.0)}},
    }
    return {
        "cameras": cams,
        "detections": {
            "detection_bb": [], "box_matches_sparse": [], "detection_cam": [],
            "detection_seq": [],
            "covisibility": [[0, 1, 0], [1, 0, 1], [0, 1, 0]],
        },
        "relative_poses": rel_poses,
        "origin": {"file": "fire.json", "id": 7},
    }


def write(tmp_path, train=None, test=None, name="graphs.json"):
    path = tmp_path / name
    path.write_text(json.dumps({"train": train or [], "test": test or [schema_graph()]}))
    return path


def test_reads_the_schema(tmp_path):
    (g,) = load_posernet_json(write(tmp_path), split="test", estimate="feature_5pt",
                              dtype=torch.float64)
    g.validate()
    assert g.num_nodes == 3 and g.num_edges == 2
    assert g.edge_index.tolist() == [[0, 1], [1, 2]]
    assert g.meta["scene"] == "fire" and g.meta["camera_ids"] == ["a", "b", "c"]
    # Absolute poses are world-to-camera: the inverse of the stored camera_to_world.
    raw = schema_graph()
    c2w_b = torch.tensor(raw["cameras"]["b"]["camera_to_world"], dtype=torch.float64)
    assert torch.allclose(g.pose_gt[1], torch.linalg.inv(c2w_b))
    # Ground truth relative pose = relative_pose(pose_i, pose_j) = inv(c2w_j) @ c2w_i.
    expected = G.relative_pose_vec(g.pose_gt[g.edge_index[0]], g.pose_gt[g.edge_index[1]])
    assert torch.allclose(g.edge_pose_gt, expected, atol=1e-12)
    # KP estimate is 5 degrees off, BB 30 degrees; edge_pose holds the requested one (unit t).
    assert torch.allclose(G.rotation_error_deg(g.edge_pose[:, :4], g.edge_pose_gt[:, :4]),
                          torch.full((2,), 5.0, dtype=torch.float64), atol=1e-9)
    assert torch.allclose(G.rotation_error_deg(g.estimates["bb"][:, :4], g.edge_pose_gt[:, :4]),
                          torch.full((2,), 30.0, dtype=torch.float64), atol=1e-9)
    assert torch.allclose(g.edge_pose[:, 4:].norm(dim=-1), torch.ones(2, dtype=torch.float64))
    # Matches: 2 on edge (a, b), 1 on (b, c); b's box [30,12,70,62] is one detection shared by both.
    assert g.pair_edge.tolist() == [0, 0, 1]
    assert g.num_dets == 5
    assert int(g.pair_dst[0]) == int(g.pair_src[2])
    px = denormalize_boxes(g.det_box, g.image_size[g.det_node])
    assert torch.allclose(px[g.pair_src[0]], torch.tensor([10.0, 10, 50, 60], dtype=px.dtype))
    assert torch.allclose(px[g.pair_dst[0]], torch.tensor([30.0, 12, 70, 62], dtype=px.dtype))
    assert g.image_size[0].tolist() == [640.0, 480.0]


def test_transposed_relative_pose_is_detected_by_the_convention(tmp_path):
    raw = schema_graph()
    # Store the relative pose the wrong way round (maps camera b into camera a).
    poses = {k: v["camera_to_world"] for k, v in raw["cameras"].items()}
    raw["relative_poses"]["a"]["b"]["feature_5pt"] = rel(poses["b"], poses["a"])
    (g,) = load_posernet_json(write(tmp_path, test=[raw]), dtype=torch.float64)
    err = G.rotation_error_deg(g.edge_pose[:, :4], g.edge_pose_gt[:, :4])
    assert float(err[0]) > 30.0  # 2 x 20 degrees of yaw: a transposed pose is not accepted as gt
    assert float(err[1]) < 5.0 + 1e-6


def test_estimate_names_and_short_names(tmp_path):
    path = write(tmp_path)
    a = load_posernet_json(path, estimate="bb_centre_5pt")[0]
    b = load_posernet_json(path, estimate="bb")[0]
    assert torch.equal(a.edge_pose, b.edge_pose)
    gt = load_posernet_json(path, estimate="ground_truth")[0]
    assert float(G.rotation_error_deg(gt.edge_pose[:, :4], gt.edge_pose_gt[:, :4]).max()) < 1e-3
    with pytest.raises(ValueError, match="unknown estimate 'sift'"):
        load_posernet_json(path, estimate="sift")


def test_reverse_stored_pose_is_inverted(tmp_path):
    raw = schema_graph()
    entry = raw["relative_poses"]["a"].pop("b")
    raw["relative_poses"]["b"]["a"] = {k: torch.linalg.inv(torch.tensor(v)).tolist()
                                       for k, v in entry.items()}
    ref = load_posernet_json(write(tmp_path, name="ref.json"), dtype=torch.float64)[0]
    got = load_posernet_json(write(tmp_path, test=[raw]), dtype=torch.float64)[0]
    assert torch.allclose(got.edge_pose, ref.edge_pose, atol=1e-7)


@pytest.mark.parametrize(
    "breaker,reason",
    [
        (lambda r: r["detections"].__setitem__("covisibility", [[0, 1], [1, 0]]),
         "covisibility size differs"),
        (lambda r: r["relative_poses"]["b"]["c"].pop("feature_5pt"), "missing its 'feature_5pt'"),
        (lambda r: r["relative_poses"].pop("b"), r"pair \(b, c\) is covisible but has no"),
        (lambda r: r["cameras"]["a"].__setitem__("camera_to_world",
                                                 [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0],
                                                  [0, 0, 0, 1]]),
         "not a rigid transform"),
        (lambda r: r["relative_poses"]["a"]["b"].__setitem__("feature_5pt", [[1, 0], [0, 1]]),
         "has shape"),
        (lambda r: r["cameras"]["b"]["matches"].pop("c") and r["cameras"]["c"]["matches"].pop("b"),
         "has no matches"),
    ],
)
def test_malformed_graph_strict_and_lenient(tmp_path, breaker, reason):
    bad = copy.deepcopy(schema_graph())
    breaker(bad)
    path = write(tmp_path, test=[schema_graph(), bad, schema_graph()])
    with pytest.raises(GraphValidationError, match=f"test graph 1: .*{reason}"):
        load_posernet_json(path, strict=True)
    with pytest.warns(UserWarning, match="skipped 1 of 3 malformed graphs"):
        graphs = load_posernet_json(path, strict=False)
    assert len(graphs) == 2


def test_file_level_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.json"):
        load_posernet_json(tmp_path / "nope.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(GraphValidationError, match="bad.json: not valid JSON"):
        load_posernet_json(bad)
    with pytest.raises(GraphValidationError, match="no split 'val'"):
        load_posernet_json(write(tmp_path), split="val")


def test_round_trip_preserves_poses_and_matches(tmp_path):
    gen = torch.Generator().manual_seed(4)
    graphs = []
    for i in range(3):
        g = random_view_graph(num_nodes=6, extra_edges=3, generator=gen, dtype=torch.float64,
                              name=f"s{i}")
        g.estimates = {"kp": g.edge_pose, "bb": G.invert_pose_vec(g.edge_pose)}
        g.meta["scene"] = "office"
        graphs.append(g)
    path = save_posernet_json(tmp_path / "out.json", {"train": graphs[:2], "test": graphs[2:]})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]
    back = (load_posernet_json(path, "train", "kp", dtype=torch.float64)
            + load_posernet_json(path, "test", "kp", dtype=torch.float64))
    for a, b in zip(graphs, back, strict=True):
        b.validate()
        assert b.meta["scene"] == "office"
        assert torch.allclose(a.pose_gt, b.pose_gt, atol=1e-12)
        # The reader stores every pair as (i, j) with i < j: re-orient a's edges to compare.
        flip = a.edge_index[0] > a.edge_index[1]
        ei = torch.where(flip, a.edge_index.flip(0), a.edge_index)
        order = (ei[0] * 100 + ei[1]).argsort()
        assert torch.equal(ei[:, order], b.edge_index)
        for key in ("kp", "bb"):
            est = torch.where(flip[:, None], G.invert_pose_vec(a.estimates[key]),
                              a.estimates[key])[order]
            assert torch.allclose(est, b.estimates[key], atol=1e-9)
        gt = torch.where(flip[:, None], G.invert_pose_vec(a.edge_pose_gt), a.edge_pose_gt)[order]
        assert torch.allclose(gt, b.edge_pose_gt, atol=1e-9)
        # Same matched box pairs per image pair (as sets of pixel boxes).
        assert _match_set(a) == _match_set(b)


def _match_set(g) -> set:
    px = denormalize_boxes(g.det_box, g.image_size[g.det_node]).round(decimals=3)
    out = set()
    for e, s, d in zip(g.pair_edge.tolist(), g.pair_src.tolist(), g.pair_dst.tolist(),
                       strict=True):
        i, j = g.edge_index[:, e].tolist()
        bs, bd = tuple(px[s].tolist()), tuple(px[d].tolist())
        out.add((i, j, bs, bd) if i < j else (j, i, bd, bs))
    return out


def test_writer_without_absolute_poses_keeps_relative_ground_truth(tmp_path):
    import dataclasses

    g = dataclasses.replace(random_view_graph(dtype=torch.float64), pose_gt=None)
    path = save_posernet_json(tmp_path / "x.json", {"test": [g]})
    (back,) = load_posernet_json(path, dtype=torch.float64)
    assert back.pose_gt is None and back.edge_pose_gt is not None and "gt" in back.estimates


def strip_ground_truth(raw: dict, cameras: bool = True, pairs: bool = True) -> dict:
    raw = copy.deepcopy(raw)
    if cameras:
        for cam in raw["cameras"].values():
            del cam["camera_to_world"]
    if pairs:
        for row in raw["relative_poses"].values():
            for entry in row.values():
                del entry["ground_truth"]
    return raw


def test_reads_a_file_without_ground_truth(tmp_path):
    (g,) = load_posernet_json(write(tmp_path, test=[strip_ground_truth(schema_graph())]))
    g.validate()
    assert g.pose_gt is None and g.edge_pose_gt is None
    assert sorted(g.estimates) == ["bb", "kp"]
    # Explicit nulls read as "no ground truth" too; relative ground truth alone is kept.
    raw = strip_ground_truth(schema_graph(), pairs=False)
    for cam in raw["cameras"].values():
        cam["camera_to_world"] = None
    (h,) = load_posernet_json(write(tmp_path, test=[raw], name="rel.json"), dtype=torch.float64)
    assert h.pose_gt is None and h.edge_pose_gt is not None
    ref = load_posernet_json(write(tmp_path, name="ref.json"), dtype=torch.float64)[0]
    assert torch.allclose(h.edge_pose_gt, ref.edge_pose_gt)
    with pytest.raises(GraphValidationError, match="'ground_truth' estimate"):
        load_posernet_json(write(tmp_path, test=[strip_ground_truth(schema_graph())]),
                           estimate="ground_truth")


def test_partial_ground_truth_is_refused_not_filled_in(tmp_path):
    raw = schema_graph()
    del raw["cameras"]["b"]["camera_to_world"]
    with pytest.raises(GraphValidationError, match="camera 'b' has no 'camera_to_world' while"):
        load_posernet_json(write(tmp_path, test=[raw]))
    raw = strip_ground_truth(schema_graph(), pairs=False)
    del raw["relative_poses"]["b"]["c"]["ground_truth"]
    with pytest.raises(GraphValidationError, match=r"pair \(b, c\) has no 'ground_truth'"):
        load_posernet_json(write(tmp_path, test=[raw]))


def test_distortion_feature_is_read_not_zeroed(tmp_path):
    from posernet.graph import REF_K1

    raw = schema_graph()
    raw["cameras"]["a"]["k1"] = 0.2
    raw["cameras"]["b"]["distortion"] = [-0.05, 0.01, 0.0, 0.0, 0.0]
    (g,) = load_posernet_json(write(tmp_path, test=[raw]), dtype=torch.float64)
    k1 = (g.node_attr[:, 3] * REF_K1).tolist()
    assert k1 == pytest.approx([0.2, -0.05, 0.0])  # c has none: 0 (no distortion) assumed
    (h,) = load_posernet_json(write(tmp_path, test=[raw]), dtype=torch.float64, default_k1=0.1)
    assert (h.node_attr[:, 3] * REF_K1).tolist() == pytest.approx([0.2, -0.05, 0.1])
    raw["cameras"]["c"]["k1"] = "strong"
    with pytest.raises(GraphValidationError, match="camera 'c' 'k1' must be a number"):
        load_posernet_json(write(tmp_path, test=[raw]))


def test_round_trip_keeps_the_distortion_feature(tmp_path):
    import dataclasses

    from posernet.graph import node_attributes

    g = random_view_graph(num_nodes=5, dtype=torch.float64)
    k1 = torch.linspace(-0.1, 0.2, 5, dtype=torch.float64)
    g = dataclasses.replace(g, node_attr=node_attributes(g.K, g.image_size, k1))
    (back,) = load_posernet_json(save_posernet_json(tmp_path / "k.json", {"test": [g]}),
                                 dtype=torch.float64)
    assert torch.allclose(back.node_attr, g.node_attr, atol=1e-12)

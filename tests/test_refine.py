"""The refine pipeline (model + motion averaging + metrics) and the posernet-refine CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import lightning as L
import pytest
import torch

from posernet import GraphBatch, PoserNet, save_graphs
from posernet.data import save_posernet_json
from posernet.evaluation import evaluate_result, result_tables
from posernet.geometry import relative_pose_vec, rotation_error_deg
from posernet.lit import PoserNetModule
from posernet.refinement import refine_graphs, result_to_json
from posernet.sync import get_backend
from posernet.testing import random_view_graph


def graphs(n: int, seed: int = 0) -> list:
    gen = torch.Generator().manual_seed(seed)
    out = []
    for i in range(n):
        g = random_view_graph(num_nodes=5 + i % 3, extra_edges=3, generator=gen, name=f"p{i}")
        g.estimates = {"kp": g.edge_pose, "bb": g.edge_pose}
        g.meta["scene"] = "heads"
        out.append(g)
    return out


def test_refine_is_batch_size_independent_and_complete():
    torch.manual_seed(0)
    model = PoserNet()
    gs = graphs(5)
    backend = get_backend("eig_se3")
    a = refine_graphs(model, gs, backend=backend, batch_size=2, progress=False)
    b = refine_graphs(model, gs, backend=backend, batch_size=5, progress=False)
    for k, g in enumerate(gs):
        assert a.edge_pose["refined"][k].shape == (g.num_edges, 7)
        assert torch.allclose(a.edge_pose["refined"][k], b.edge_pose["refined"][k], atol=1e-5)
        assert torch.equal(a.edge_pose["initial"][k], g.edge_pose)
        assert a.absolute["refined"][k].shape == (g.num_nodes, 4, 4)
        assert torch.allclose(a.absolute["initial"][k], b.absolute["initial"][k], atol=1e-5)
    assert a.backend["backend"] == "eig_se3"


def test_evaluation_matches_direct_computation():
    gs = graphs(4)
    res = refine_graphs(None, gs, backend=get_backend("eig_se3"), progress=False)
    ev = evaluate_result(res)
    assert set(ev["relative"]) == {"initial"}
    direct = torch.stack([rotation_error_deg(g.edge_pose[:, :4], g.edge_pose_gt[:, :4]).mean()
                          for g in gs])
    assert torch.allclose(ev["per_graph"]["rel_rot_initial"].double(), direct.double(), atol=1e-4)
    assert ev["relative"]["initial"]["rot"].count == 4
    # Motion averaging of noisy poses gives finite, non-trivial absolute errors.
    assert ev["absolute"]["initial"]["rot"].median > 0
    tables = result_tables(ev, label="KP", backend=res.backend)
    assert "Initial" in tables["relative"].to_markdown()
    assert "unit-norm" in tables["absolute"].to_markdown()


def test_motion_averaging_of_ground_truth_recovers_cameras():
    gs = [g.with_estimate("kp") for g in graphs(3)]
    for g in gs:  # feed exact relative poses (metric translations, given scale)
        g.edge_pose = relative_pose_vec(g.pose_gt[g.edge_index[0]], g.pose_gt[g.edge_index[1]])
    res = refine_graphs(None, gs, backend=get_backend("eig_se3", scale="given"), progress=False)
    ev = evaluate_result(res)
    assert ev["alignment"] == "rigid"
    assert float(ev["per_graph"]["abs_rot_initial"].max()) < 1e-3
    assert float(ev["per_graph"]["abs_pos_initial"].max()) < 1e-4


def test_result_json_has_poses_for_every_edge_and_camera():
    gs = graphs(2)
    res = refine_graphs(PoserNet(), gs, backend=get_backend("eig_se3"), progress=False)
    rec = result_to_json(res, {"input": "x"})
    json.dumps(rec, allow_nan=False)
    assert rec["format"] == "posernet-refined" and rec["input"] == "x"
    g0 = rec["graphs"][0]
    assert len(g0["edges"]) == gs[0].num_edges
    e = g0["edges"][0]
    assert set(e) == {"source", "target", "initial", "refined"}
    assert len(e["refined"]["q_wxyz"]) == 4 and len(e["refined"]["matrix"]) == 4
    cam = g0["cameras"]["0"]["refined"]
    T = torch.tensor(cam["world_to_camera"])
    assert torch.allclose(T @ torch.tensor(cam["camera_to_world"]), torch.eye(4), atol=1e-5)


# --------------------------------------------------------------------------- input selection


def fake_dataset(root: Path) -> Path:
    """A posernet-make-data layout: small train/val/test and large test graphs + manifest."""
    from posernet.io import atomic_write_json

    layout = {("small", "train"): 3, ("small", "val"): 1, ("small", "test"): 2,
              ("large", "test"): 1}
    splits: dict = {}
    for seed, ((size, split), n) in enumerate(layout.items()):
        gs = graphs(n, seed=seed)
        for k, g in enumerate(gs):
            g.meta.update(split=split, size=size, name=f"{size}-{split}-{k}")
        save_graphs(root / size / split / "heads.pt", gs)
        splits.setdefault(size, {})[split] = ["heads"]
    atomic_write_json(root / "manifest.json", {"splits": splits})
    return root


def test_dataset_root_uses_one_split_and_says_which(tmp_path):
    from posernet.data.inputs import load_input_graphs
    from posernet.data.store import DatasetError

    root = fake_dataset(tmp_path / "ds")
    said: list[str] = []
    gs = load_input_graphs(root, log=said.append)
    assert [g.meta["split"] for g in gs] == ["test", "test"]
    assert {g.meta["size"] for g in gs} == {"small"}
    assert len(said) == 1 and "split=test size=small: 2 small test graphs" in said[0]
    every = load_input_graphs(root, size="all")
    assert sorted(g.name for g in every) == ["large-test-0", "small-test-0", "small-test-1"]
    assert len(load_input_graphs(root, split="train")) == 3
    with pytest.raises(DatasetError, match="size must be one of"):
        load_input_graphs(root, size="medium")
    with pytest.raises(DatasetError, match="no large val graphs"):
        load_input_graphs(root, split="val", size="large")
    # One split's folder needs no manifest.
    assert len(load_input_graphs(root / "small" / "train")) == 3


def test_folder_mixing_splits_without_manifest_is_refused(tmp_path):
    from posernet.data.inputs import load_input_graphs
    from posernet.graph import GraphValidationError

    root = fake_dataset(tmp_path / "ds")
    (root / "manifest.json").unlink()
    with pytest.raises(GraphValidationError, match=rf"{root}: its .pt files mix splits "
                       r"\(test: 2 file\(s\).*train: 1 file\(s\)"):
        load_input_graphs(root)
    # Graphs without a split in their metadata: the folder names tell.
    plain = tmp_path / "plain"
    save_graphs(plain / "train" / "a.pt", graphs(1))
    save_graphs(plain / "test" / "b.pt", graphs(1))
    with pytest.raises(GraphValidationError, match="mix splits"):
        load_input_graphs(plain)
    assert len(load_input_graphs(plain / "test")) == 1


# --------------------------------------------------------------------------- CLI


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("ckpt")
    L.seed_everything(0)
    loader = torch.utils.data.DataLoader(graphs(8), batch_size=4,
                                         collate_fn=GraphBatch.from_graphs)
    trainer = L.Trainer(max_steps=2, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False,
                        default_root_dir=tmp)
    trainer.fit(PoserNetModule(), loader)
    path = tmp / "model.ckpt"
    trainer.save_checkpoint(path)
    return path


def run_refine(tmp: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "posernet.cli.refine", f"hydra.run.dir={tmp}", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300)


@pytest.mark.slow
def test_refine_cli_on_pt_and_json(tmp_path, checkpoint):
    gs = graphs(3)
    pt = save_graphs(tmp_path / "g.pt", gs)
    js = save_posernet_json(tmp_path / "g.json", {"test": gs})
    for name, src in (("pt", pt), ("json", js)):
        out = tmp_path / name
        r = run_refine(out, f"input={src}", f"ckpt_path={checkpoint}", "sync=rotation_translation")
        assert r.returncode == 0, r.stderr
        rec = json.loads((out / "refined.json").read_text())
        assert len(rec["graphs"]) == 3
        assert rec["backend"]["backend"] == "rotation_translation"
        assert (out / "table.md").exists() and (out / "abs_table.csv").exists()
        assert "PoserNet" in r.stdout


@pytest.mark.slow
def test_refine_cli_bad_inputs_give_one_line_errors(tmp_path, checkpoint):
    r = run_refine(tmp_path / "a", f"input={tmp_path / 'missing.json'}",
                   f"ckpt_path={checkpoint}")
    assert r.returncode == 1
    assert "posernet-refine: error: graph JSON not found" in r.stderr
    assert "Traceback" not in r.stderr
    bogus = tmp_path / "bogus.ckpt"
    torch.save({"state_dict": {}}, bogus)
    pt = save_graphs(tmp_path / "g.pt", graphs(1))
    r = run_refine(tmp_path / "b", f"input={pt}", f"ckpt_path={bogus}")
    assert r.returncode == 1 and "not a PoserNet checkpoint" in r.stderr
    assert not (tmp_path / "b" / "refined.json").exists()


@pytest.mark.slow
def test_refine_cli_on_a_dataset_root_uses_the_test_split(tmp_path, checkpoint):
    root = fake_dataset(tmp_path / "ds")
    r = run_refine(tmp_path / "out", f"input={root}", f"ckpt_path={checkpoint}", "sync=none")
    assert r.returncode == 0, r.stderr
    assert "dataset root; using split=test size=small: 2 small test graphs" in r.stdout
    rec = json.loads((tmp_path / "out" / "refined.json").read_text())
    assert [g["name"] for g in rec["graphs"]] == ["small-test-0", "small-test-1"]
    (root / "manifest.json").unlink()
    r = run_refine(tmp_path / "mixed", f"input={root}", f"ckpt_path={checkpoint}")
    assert r.returncode == 1 and "mix splits" in r.stderr and str(root) in r.stderr
    assert "Traceback" not in r.stderr

"""Dataset generation: determinism, atomic layout, overwrite / resume, bad configs, summary."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from posernet.data.synthetic import (
    ConfigError,
    DatasetExistsError,
    GenerationError,
    available_presets,
    format_summary,
    generate_dataset,
    load_preset,
    options_from_dict,
    simulate_graphs,
)
from posernet.graph import load_graphs


def mini() -> dict:
    """The tiny preset cut down further: 2 scenes, a few 4-image graphs, one large graph."""
    d = load_preset("tiny").to_dict()
    d["name"] = "mini"
    d["small"].update(graph_size=4, train=2, val=1, test=1)
    d["large"].update(graph_size=6, train=1, val=0, test=1, scenes=["chess"])
    return d


def files_of(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*.pt"))}


def same_payload(a, b) -> bool:
    """Exact equality of two loaded graph files (tensors bit for bit, dtypes, metadata)."""
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b)
    if isinstance(a, dict):
        return (
            isinstance(b, dict)
            and a.keys() == b.keys()
            and all(same_payload(a[k], b[k]) for k in a)
        )
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(same_payload(x, y) for x, y in zip(a, b, strict=True))
    return a == b or (a != a and b != b)  # NaN statistics compare equal


def contents_of(root: Path) -> dict[str, dict]:
    return {
        str(p.relative_to(root)): torch.load(p, weights_only=True)
        for p in sorted(root.rglob("*.pt"))
    }


def assert_same_dataset(a: Path, b: Path) -> None:
    ca, cb = contents_of(a), contents_of(b)
    assert ca.keys() == cb.keys()
    for k in ca:
        assert same_payload(ca[k], cb[k]), k
    assert (a / "manifest.json").read_bytes() == (b / "manifest.json").read_bytes()


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("gen") / "ds"
    generate_dataset(mini(), root, seed=5, workers=1, progress=False, echo=None)
    return root


def test_layout_and_manifest(made: Path):
    m = json.loads((made / "manifest.json").read_text())
    assert m["seed"] == 5 and m["preset"] == "mini"
    assert m["splits"]["small"] == {
        "train": ["chess", "fire"],
        "val": ["chess", "fire"],
        "test": ["chess", "fire"],
    }
    assert m["splits"]["large"] == {"train": ["chess"], "test": ["chess"]}
    for rel, info in m["files"].items():
        graphs = load_graphs(made / rel)
        assert len(graphs) == info["graphs"]
        size, split, scene = rel[:-3].split("/")
        names = set()
        for g in graphs:
            assert (g.meta["size"], g.meta["split"], g.meta["scene"]) == (size, split, scene)
            names.add(g.meta["name"])
        assert len(names) == len(graphs)
    assert m["composition"]["small"]["train"]["graphs"] == 4
    st = m["statistics"]["small"]["test"]
    assert set(st) == {"kp", "bb"} and st["kp"]["rot"]["count"] == 2
    assert not list(made.rglob("*.tmp"))


@pytest.fixture(scope="module")
def made_with_two_workers(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("gen2") / "ds"
    generate_dataset(mini(), root, seed=5, workers=2, progress=False, echo=None)
    return root


def test_same_seed_gives_identical_graphs_for_any_worker_count(made, made_with_two_workers):
    assert_same_dataset(made, made_with_two_workers)


def test_same_seed_gives_bit_identical_files(made, made_with_two_workers):
    assert files_of(made_with_two_workers) == files_of(made)


def test_another_seed_gives_other_graphs(tmp_path: Path):
    a = simulate_graphs(mini(), scene="chess", split="train", count=1, seed=1)[0]
    b = simulate_graphs(mini(), scene="chess", split="train", count=1, seed=2)[0]
    assert not (a.pose_gt.shape == b.pose_gt.shape and bool((a.pose_gt == b.pose_gt).all()))


def test_existing_directory_is_refused_then_overwritten(made: Path, tmp_path: Path):
    root = tmp_path / "ds"
    generate_dataset(mini(), root, seed=5, workers=1, progress=False, echo=None)
    with pytest.raises(DatasetExistsError, match="overwrite=true"):
        generate_dataset(mini(), root, seed=5, workers=1, progress=False, echo=None)
    (root / "notes.txt").write_text("mine")
    generate_dataset(mini(), root, seed=6, workers=1, progress=False, echo=None, overwrite=True)
    assert json.loads((root / "manifest.json").read_text())["seed"] == 6
    assert (root / "notes.txt").read_text() == "mine"  # only our own files are replaced


def test_resume_finishes_an_interrupted_run(made: Path, tmp_path: Path):
    root = tmp_path / "ds"
    generate_dataset(mini(), root, seed=5, workers=1, progress=False, echo=None)
    # simulate an interruption: no manifest, one file missing, a stale temp file
    (root / "manifest.json").unlink()
    (root / "small/val/fire.pt").unlink()
    (root / "small/val/.fire.pt.abc.tmp").write_bytes(b"half")
    keep = (root / "small/train/chess.pt").stat().st_mtime_ns
    from posernet.data.store import DatasetError, open_split

    with pytest.raises(DatasetError, match="manifest"):
        open_split(root)
    with pytest.raises(GenerationError, match="different configuration"):
        generate_dataset(mini(), root, seed=7, workers=1, progress=False, echo=None, resume=True)
    generate_dataset(mini(), root, seed=5, workers=1, progress=False, echo=None, resume=True)
    assert (root / "small/train/chess.pt").stat().st_mtime_ns == keep  # not redone
    assert_same_dataset(root, made)
    assert not list(root.rglob("*.tmp"))


def test_resume_refuses_a_foreign_directory(tmp_path: Path):
    (tmp_path / "x.txt").write_text("not a dataset")
    with pytest.raises(GenerationError, match="cannot resume"):
        generate_dataset(mini(), tmp_path, workers=1, progress=False, echo=None, resume=True)


@pytest.mark.parametrize(
    ("patch", "field"),
    [
        ({"small": {"train": -1}}, "dataset.small.train"),
        ({"small": {"graph_size": 1}}, "dataset.small.graph_size"),
        ({"large": {"graph_size": 0}}, "dataset.large.graph_size"),
        ({"keypoints": {"pixel_noise": -1.0}}, "dataset.keypoints.pixel_noise"),
        ({"keypoints": {"outlier_rate": 1.5}}, "dataset.keypoints.outlier_rate"),
        ({"detector": {"max_area": 0.0}}, "dataset.detector.max_area"),
        ({"detector": {"box_jiter": 0.1}}, "dataset.detector.box_jiter"),
        ({"matching": {"min_boxes": 0}}, "dataset.matching.min_boxes"),
        ({"matching": {"kp_boxes": -1}}, "dataset.matching.kp_boxes"),
        ({"pose": {"method": "magic"}}, "dataset.pose.method"),
        ({"scenes": ["chess", "kitchen"]}, "dataset.scenes"),
        ({"small": {"train": "many"}}, "dataset.small.train"),
        ({"camera": {"focal": float("nan")}}, "dataset.camera.focal"),
    ],
)
def test_bad_configs_name_the_field(patch: dict, field: str):
    d = mini()
    for k, v in patch.items():
        if isinstance(v, dict):
            d[k].update(v)
        else:
            d[k] = v
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        options_from_dict(d)


def test_bad_generation_arguments(tmp_path: Path):
    with pytest.raises(ConfigError, match="unknown dataset preset 'nope'"):
        generate_dataset("nope", tmp_path / "a", progress=False, echo=None)
    with pytest.raises(ConfigError, match="workers"):
        generate_dataset(mini(), tmp_path / "b", workers=0, progress=False, echo=None)
    with pytest.raises(ConfigError, match="seed"):
        generate_dataset(mini(), tmp_path / "c", seed=-1, progress=False, echo=None)
    d = mini()
    for size in ("small", "large"):
        d[size].update(train=0, val=0, test=0)
    with pytest.raises(ConfigError, match="nothing to generate"):
        generate_dataset(d, tmp_path / "d", progress=False, echo=None)
    assert not (tmp_path / "a").exists() and not (tmp_path / "d").exists()


def test_presets_load_and_paper_is_paper_sized():
    assert {"paper", "easy", "demo", "tiny"} <= set(available_presets())
    p = load_preset("paper")
    assert (p.small.graph_size, p.small.train, p.small.test) == (8, 2000, 1000)
    assert len(p.scenes) == 7 and p.small.val > 0
    assert (p.large.graph_size, p.large.train, p.large.test) == (125, 1, 1)
    assert p.scenes_for("large") == ["chess", "fire", "heads", "office", "pumpkin"]
    assert p.detector.max_boxes == 50 and p.detector.max_area == 0.25
    assert (p.matching.min_keypoints, p.matching.min_span, p.matching.min_boxes) == (15, 0.3, 5)


def test_summary_prints_the_paper_table(made: Path):
    m = json.loads((made / "manifest.json").read_text())
    text = format_summary(dict(m, root=str(made)))
    assert "small test graphs" in text
    lines = text.splitlines()
    assert any(ln.startswith("KP  paper") and "36.26" in ln for ln in lines)
    assert any(ln.startswith("BB  paper") and "96.48" in ln for ln in lines)
    assert any(ln.startswith("KP  ours") for ln in lines)
    assert any(ln.startswith("small train") for ln in lines)


def test_json_export_round_trips(tmp_path: Path):
    pytest.importorskip("posernet.data.posernet_json")
    from posernet.data.posernet_json import load_posernet_json

    d = mini()
    d["large"].update(train=0, test=0)
    d["scenes"] = ["chess"]
    d["large"]["scenes"] = []
    root = tmp_path / "ds"
    m = generate_dataset(d, root, workers=1, progress=False, echo=None, export_json_files=True)
    assert m["json"] == {"small": "json/small.json"}
    ours = load_graphs(root / "small/test/chess.pt")
    back = load_posernet_json(root / "json/small.json", "test", "kp")
    assert len(back) == len(ours)
    for a, b in zip(ours, back, strict=True):
        assert a.num_nodes == b.num_nodes and a.num_edges == b.num_edges


def test_parts_cover_every_graph_once_and_spread_over_many_workers():
    from posernet.data.synthetic.chunks import plan_chunks
    from posernet.data.synthetic.generate import plan_parts

    chunks = plan_chunks(load_preset("paper"))
    for workers in (1, 2, 16):
        parts = plan_parts(chunks, workers)
        for c in chunks:
            idx = sorted(i for pc, r in parts if pc == c for i in r)
            assert idx == list(range(c.count)), (workers, c.relpath)
    assert len(plan_parts(chunks, 1)) == len(chunks)  # one process: whole chunks
    assert len(plan_parts(chunks, 16)) >= 4 * 16 // 2  # many workers: many parts


def test_parts_of_a_chunk_join_into_the_whole_chunk():
    from posernet.data.synthetic.chunks import Chunk, merge_stats, simulate_chunk, split_chunk

    opts = options_from_dict(mini())
    chunk = Chunk("small", "train", "chess", 3, 4)
    whole, st_whole = simulate_chunk(opts, chunk, seed=5)
    parts = [simulate_chunk(opts, chunk, seed=5, graphs_range=r) for r in split_chunk(chunk, 2)]
    assert [len(g) for g, _ in parts] == [1, 2]
    joined = [g for gs, _ in parts for g in gs]
    assert [g.name for g in joined] == [g.name for g in whole]
    for a, b in zip(joined, whole, strict=True):
        assert torch.equal(a.edge_pose, b.edge_pose) and torch.equal(a.det_box, b.det_box)
    assert same_payload(merge_stats([st for _, st in parts]), st_whole)
    with pytest.raises(ValueError, match="outside"):
        simulate_chunk(opts, chunk, seed=5, graphs_range=range(2, 5))

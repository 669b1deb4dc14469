"""Dataset directory reader: manifest, splits, scene selection, clear errors."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from posernet.data.store import DatasetError, available_scenes, open_split, read_manifest
from posernet.data.synthetic import generate_dataset, load_preset


def mini() -> dict:
    d = load_preset("tiny").to_dict()
    d["small"].update(graph_size=4, train=2, val=1, test=1)
    d["large"].update(graph_size=5, train=1, val=0, test=0, scenes=["fire"])
    return d


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    r = tmp_path_factory.mktemp("store") / "ds"
    generate_dataset(mini(), r, seed=1, workers=1, progress=False, echo=None)
    return r


def test_open_split_reads_all_scenes(root: Path):
    graphs = open_split(root, "small", "train")
    assert len(graphs) == 4
    assert [g.meta["scene"] for g in graphs] == ["chess", "chess", "fire", "fire"]
    assert all(g.meta["split"] == "train" and g.meta["size"] == "small" for g in graphs)
    assert set(graphs[0].estimates) == {"kp", "bb"}


def test_open_split_selects_scenes(root: Path):
    assert [g.meta["scene"] for g in open_split(root, "small", "test", scenes="fire")] == ["fire"]
    assert len(open_split(root, "small", "val", scenes=["chess", "fire"])) == 2
    # a scene of the dataset without graphs in this split/size: nothing, not an error
    assert open_split(root, "large", "train", scenes=["chess"]) == []
    assert len(open_split(root, "large", "train")) == 1
    assert open_split(root, "large", "test") == []  # no large test graphs generated


def test_unknown_scene_size_split(root: Path):
    with pytest.raises(DatasetError, match="unknown scene"):
        open_split(root, scenes=["kitchen"])
    with pytest.raises(ValueError, match="size"):
        open_split(root, size="huge")
    with pytest.raises(ValueError, match="split"):
        open_split(root, split="dev")


def test_manifest(root: Path):
    m = read_manifest(root)
    assert m["seed"] == 1
    assert available_scenes(root, "small", "val") == ["chess", "fire"]
    assert available_scenes(root, "large", "test") == []


def test_errors_name_the_path(root: Path, tmp_path: Path):
    with pytest.raises(DatasetError, match=str(tmp_path / "none")):
        read_manifest(tmp_path / "none")
    bad = tmp_path / "bad"
    shutil.copytree(root, bad)
    (bad / "manifest.json").write_text("{not json")
    with pytest.raises(DatasetError, match="malformed manifest"):
        read_manifest(bad)
    (bad / "manifest.json").write_text(json.dumps({"hello": 1}))
    with pytest.raises(DatasetError, match="malformed manifest"):
        read_manifest(bad)
    (bad / "manifest.json").unlink()
    with pytest.raises(DatasetError, match="resume=true"):
        open_split(bad)
    miss = tmp_path / "miss"
    shutil.copytree(root, miss)
    (miss / "small/train/fire.pt").unlink()
    with pytest.raises(DatasetError, match="fire.pt"):
        open_split(miss, "small", "train")
    assert len(open_split(miss, "small", "train", scenes=["chess"])) == 2

"""7-Scenes reader: a rendered scene read back, intrinsics, and every broken layout."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from posernet.data.render import render_intrinsics, render_sevenscenes
from posernet.data.sevenscenes import (
    DEFAULT_INTRINSICS,
    SevenScenesError,
    SevenScenesFrame,
    SevenScenesScene,
    open_sevenscenes,
    read_color,
    read_depth,
)

W, H, F = 160, 120, 146.25


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A dataset root holding one rendered scene: seq-01, seq-02 train, seq-03 test."""
    root = tmp_path_factory.mktemp("7scenes")
    render_sevenscenes(
        root, "fire", seed=0, train_sequences=2, test_sequences=1, frames_per_sequence=2,
        width=W, height=H, focal=F, progress=False,
    )  # fmt: skip
    return root


@pytest.fixture
def copy(dataset: Path, tmp_path: Path) -> Path:
    """A private copy of the rendered scene folder to break."""
    return Path(shutil.copytree(dataset / "fire", tmp_path / "fire"))


def _esc(p: Path) -> str:
    return re.escape(str(p))


# --------------------------------------------------------------------------- reading


def test_reads_rendered_scene(dataset: Path) -> None:
    (scene,) = open_sevenscenes(dataset)
    assert scene.name == "fire" and scene.path == dataset / "fire"
    assert scene.sequences("train") == ["seq-01", "seq-02"]
    assert scene.sequences("test") == ["seq-03"]
    train = scene.frames("train")
    assert [(f.sequence, f.index) for f in train] == [
        ("seq-01", 0), ("seq-01", 1), ("seq-02", 0), ("seq-02", 1),
    ]  # fmt: skip
    f = scene.frames("test")[1]
    assert isinstance(f, SevenScenesFrame)
    assert (f.scene, f.split, f.sequence, f.index) == ("fire", "test", "seq-03", 1)
    assert f.key == "seq-03/frame-000001.color.png"
    assert f.color == dataset / "fire" / "seq-03" / "frame-000001.color.png"
    assert f.depth.name == "frame-000001.depth.png" and f.pose.name == "frame-000001.pose.txt"
    for fr in train + scene.frames("test"):
        T = scene.camera_to_world(fr)
        assert T.dtype == np.float64 and T.shape == (4, 4)
        np.testing.assert_allclose(T, np.loadtxt(fr.pose), atol=1e-9)
        np.testing.assert_allclose(scene.world_to_camera(fr) @ T, np.eye(4), atol=1e-12)
    rgb = read_color(f.color)
    assert rgb.shape == (H, W, 3) and rgb.dtype == np.uint8
    np.testing.assert_array_equal(rgb, cv2.imread(str(f.color))[..., ::-1])
    d = read_depth(f.depth)
    raw = cv2.imread(str(f.depth), cv2.IMREAD_UNCHANGED)
    assert d.dtype == np.float32 and d.shape == (H, W)
    np.testing.assert_allclose(d[raw != 65535], raw[raw != 65535] / 1000.0, rtol=1e-6)


def test_keys_match_objects_json(dataset: Path) -> None:
    (scene,) = open_sevenscenes(dataset)
    doc = json.loads((scene.path / "objects.json").read_text())
    keys = [f.key for s in ("train", "test") for f in scene.frames(s)]
    assert sorted(keys) == sorted(doc["images"])


def test_scene_folder_as_root_and_any_name(copy: Path) -> None:
    renamed = copy.rename(copy.parent / "my office")
    (scene,) = open_sevenscenes(renamed)
    assert scene.name == "my office"
    assert open_sevenscenes(renamed.parent)[0].name == "my office"
    assert open_sevenscenes(renamed.parent, scenes="my office")[0].path == renamed
    assert SevenScenesScene(renamed).frames("test")[0].scene == "my office"


def test_scene_selection(dataset: Path, copy: Path) -> None:
    shutil.copytree(copy, copy.parent / "heads")
    names = [s.name for s in open_sevenscenes(copy.parent)]
    assert names == ["fire", "heads"]
    assert [s.name for s in open_sevenscenes(copy.parent, scenes=["heads", "fire"])] == [
        "heads", "fire",
    ]  # fmt: skip
    unknown = r"\['pumpkin'\] not found under " + _esc(copy.parent)
    with pytest.raises(SevenScenesError, match=unknown):
        open_sevenscenes(copy.parent, scenes=["fire", "pumpkin"])


def test_intrinsics(dataset: Path) -> None:
    (scene,) = open_sevenscenes(dataset)
    fx, fy, cx, cy = DEFAULT_INTRINSICS
    np.testing.assert_array_equal(scene.K(), [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    assert DEFAULT_INTRINSICS == (585.0, 585.0, 320.0, 240.0)
    (scene,) = open_sevenscenes(dataset, intrinsics=render_intrinsics(dataset / "fire"))
    np.testing.assert_array_equal(scene.K(), [[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]])
    K = np.array([[500.0, 0, 300], [0, 510, 200], [0, 0, 1]])
    np.testing.assert_array_equal(SevenScenesScene(dataset / "fire", K).K(), K)
    scene.K()[0, 0] = 1.0  # a copy: the scene's K does not change
    assert scene.K()[0, 0] == F


@pytest.mark.parametrize(
    ("intrinsics", "message"),
    [
        ((585.0, 585.0, 320.0), r"4 numbers fx,fy,cx,cy or a 3x3 matrix, got shape \(3,\)"),
        (np.eye(4), r"got shape \(4, 4\)"),
        ((0.0, 585.0, 320.0, 240.0), "must be positive"),
        ((585.0, -1.0, 320.0, 240.0), "must be positive"),
        ((585.0, np.nan, 320.0, 240.0), "must be numbers"),
        ([[585.0, 0, 320], [0, 585, 240], [0, 0, 2]], "last row 0 0 1"),
        ("f=585", "must be numbers"),
    ],
)
def test_bad_intrinsics(dataset: Path, intrinsics: object, message: str) -> None:
    with pytest.raises(SevenScenesError, match=message):
        open_sevenscenes(dataset, intrinsics=intrinsics)
    with pytest.raises(SevenScenesError, match=message):
        SevenScenesScene(dataset / "fire", intrinsics)


def test_bad_split_name(dataset: Path) -> None:
    (scene,) = open_sevenscenes(dataset)
    with pytest.raises(SevenScenesError, match="split must be one of"):
        scene.frames("val")


def test_rotation_reorthonormalised(copy: Path) -> None:
    pose = copy / "seq-01" / "frame-000000.pose.txt"
    T = np.loadtxt(pose)
    T[:3, :3] *= 1.0004  # slightly non-orthonormal, like real 7-Scenes poses
    np.savetxt(pose, T)
    R = SevenScenesScene(copy).camera_to_world(SevenScenesScene(copy).frames("train")[0])[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R, T[:3, :3] / 1.0004, atol=1e-6)


def test_read_depth_invalid_values(tmp_path: Path) -> None:
    raw = np.array([[0, 1000, 65535], [1500, 2, 65534]], np.uint16)
    cv2.imwrite(str(tmp_path / "d.png"), raw)
    d = read_depth(tmp_path / "d.png")
    assert np.isnan(d[0, 0]) and np.isnan(d[0, 2])
    np.testing.assert_allclose(d[[0, 1, 1, 1], [1, 0, 1, 2]], [1.0, 1.5, 0.002, 65.534], rtol=1e-6)


# --------------------------------------------------------------------------- broken input


def test_root_missing(tmp_path: Path) -> None:
    with pytest.raises(SevenScenesError, match="7-Scenes root .*" + _esc(tmp_path / "nope")):
        open_sevenscenes(tmp_path / "nope")
    with pytest.raises(SevenScenesError, match=_esc(tmp_path / "nope") + " does not exist"):
        SevenScenesScene(tmp_path / "nope")


def test_root_without_scenes(tmp_path: Path) -> None:
    (tmp_path / "chess" / "seq-01").mkdir(parents=True)
    with pytest.raises(SevenScenesError, match=_esc(tmp_path) + " is not in 7-Scenes layout"):
        open_sevenscenes(tmp_path)
    with pytest.raises(SevenScenesError, match="TrainSplit.txt and TestSplit.txt missing"):
        SevenScenesScene(tmp_path / "chess")
    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(SevenScenesError, match=_esc(tmp_path / "file.txt") + " is not a folder"):
        open_sevenscenes(tmp_path / "file.txt")


def test_split_file_missing(copy: Path) -> None:
    (copy / "TestSplit.txt").unlink()
    with pytest.raises(SevenScenesError, match=_esc(copy) + ".*TestSplit.txt missing"):
        open_sevenscenes(copy.parent)


@pytest.mark.parametrize("line", ["seq-01", "sequence", "sequence1 extra", "Sequence 1", "1"])
def test_bad_split_line(copy: Path, line: str) -> None:
    (copy / "TrainSplit.txt").write_text(f"sequence1\n{line}\n")
    with pytest.raises(
        SevenScenesError, match=_esc(copy / "TrainSplit.txt") + " line 2: expected 'sequenceN'"
    ):
        SevenScenesScene(copy)


def test_split_tolerates_blank_lines_and_crlf(copy: Path) -> None:
    (copy / "TrainSplit.txt").write_bytes(b"sequence2\r\n\r\nsequence1 \r\n")
    assert SevenScenesScene(copy).sequences("train") == ["seq-01", "seq-02"]


def test_split_names_missing_folder(copy: Path) -> None:
    (copy / "TestSplit.txt").write_text("sequence3\nsequence7\n")
    with pytest.raises(SevenScenesError, match="sequence7 but folder " + _esc(copy / "seq-07")):
        SevenScenesScene(copy)
    (copy / "seq-07.zip").write_bytes(b"")
    with pytest.raises(SevenScenesError, match="unzip it first"):
        SevenScenesScene(copy)


def test_sequence_in_both_splits_or_twice(copy: Path) -> None:
    (copy / "TestSplit.txt").write_text("sequence1\n")
    with pytest.raises(SevenScenesError, match=_esc(copy / "TestSplit.txt") + " lists sequence1"):
        SevenScenesScene(copy)
    (copy / "TestSplit.txt").write_text("sequence3\nsequence3\n")
    with pytest.raises(SevenScenesError, match="lists sequence3 twice"):
        SevenScenesScene(copy)


def test_no_sequences_at_all(copy: Path) -> None:
    (copy / "TrainSplit.txt").write_text("")
    (copy / "TestSplit.txt").write_text("\n")
    with pytest.raises(SevenScenesError, match="split files of " + _esc(copy) + " list no"):
        SevenScenesScene(copy)


def test_empty_sequence(copy: Path) -> None:
    for f in (copy / "seq-02").iterdir():
        f.unlink()
    with pytest.raises(SevenScenesError, match=_esc(copy / "seq-02") + " holds no frame"):
        SevenScenesScene(copy)


def test_frame_pose_missing(copy: Path) -> None:
    missing = copy / "seq-03" / "frame-000001.pose.txt"
    missing.unlink()
    with pytest.raises(SevenScenesError, match=_esc(missing) + " is missing"):
        SevenScenesScene(copy)


def test_depth_images_are_optional(copy: Path) -> None:
    """RGB-only data in the 7-Scenes layout: graphs never read depth."""
    for p in copy.rglob("*.depth.png"):
        p.unlink()
    scene = SevenScenesScene(copy)
    frames = scene.frames("test")
    assert frames and all(f.depth is None for f in frames)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n", "not a 4x4 matrix"),
        ("1 0 0\n0 1 0\n0 0 1\n0 0 0\n", "not a 4x4 matrix"),
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1 5\n", "not a 4x4 matrix"),
        ("1 0 0 x\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "not a 4x4 matrix of numbers"),
        ("", "not a 4x4 matrix"),
        ("1 0 0 nan\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "non-finite"),
        ("2 0 0 0\n0 2 0 0\n0 0 2 0\n0 0 0 1\n", "not a rigid transform"),
        ("1 0 0 0\n0 1 0 0\n0 0 -1 0\n0 0 0 1\n", "not a rigid transform"),
        ("1 0.1 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "not a rigid transform"),
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 1 1\n", "last row must be 0 0 0 1"),
    ],
)
def test_bad_pose(copy: Path, text: str, message: str) -> None:
    pose = copy / "seq-02" / "frame-000001.pose.txt"
    pose.write_text(text)
    scene = SevenScenesScene(copy)  # poses are read lazily
    frame = next(f for f in scene.frames("train") if f.pose == pose)
    with pytest.raises(SevenScenesError, match=_esc(pose)):
        scene.camera_to_world(frame)
    with pytest.raises(SevenScenesError, match=message):
        scene.world_to_camera(frame)


def test_bad_depth_image(copy: Path) -> None:
    colour = copy / "seq-01" / "frame-000000.color.png"
    with pytest.raises(SevenScenesError, match=_esc(colour) + " must be single-channel uint16"):
        read_depth(colour)
    junk = copy / "junk.png"
    junk.write_bytes(b"not a png")
    with pytest.raises(SevenScenesError, match="cannot read depth image " + _esc(junk)):
        read_depth(junk)
    with pytest.raises(SevenScenesError, match=_esc(copy / "none.png") + " does not exist"):
        read_depth(copy / "none.png")
    with pytest.raises(SevenScenesError, match="cannot read colour image " + _esc(junk)):
        read_color(junk)

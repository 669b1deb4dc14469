"""posernet-make-data source=sevenscenes: graphs of a rendered scene in the 7-Scenes layout.

One tiny scene per module (320x240, 12 frames in one train and one test sequence); EdgeBoxes +
SIFT, 4-image graphs, so a full run takes seconds.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from posernet.data.render import render_sevenscenes

INTRINSICS = "292.5,292.5,160,120"
# small graphs: 2 train / 1 val / 1 test of 4 images; one large test graph of 6 images
ARGS = [
    f"intrinsics={INTRINSICS}",
    "frame_step=1",
    "proposals=edge_boxes",
    "matcher=sift",
    "sevenscenes.val_fraction=0.35",
    "sevenscenes.window=3",
    "sevenscenes.small.graph_size=4",
    "sevenscenes.small.train=2",
    "sevenscenes.small.val=1",
    "sevenscenes.small.test=1",
    "sevenscenes.large.graph_size=6",
    "sevenscenes.large.train=0",
    "sevenscenes.large.test=1",
    "sevenscenes.large.scenes=null",
    "workers=1",
]


@pytest.fixture(scope="module")
def scenes_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("7scenes")
    render_sevenscenes(root, "chess", seed=0, train_sequences=1, test_sequences=1,
                       frames_per_sequence=12, width=320, height=240, focal=292.5,
                       progress=False)
    return root


def cli(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "posernet.cli.make_data", "source=sevenscenes", *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )


def finish(p: subprocess.Popen) -> tuple[int, str, str]:
    out, err = p.communicate(timeout=600)
    return p.returncode, out, err


def compose(*overrides: str):
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from posernet.cli import CONFIG_DIR

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return hydra_compose("make_data", overrides=list(overrides))


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    assert err.startswith("posernet-make-data: error:"), err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    return err


# --------------------------------------------------------------------------- end to end


@pytest.mark.slow
def test_verified_edges_make_graphs_shaped_like_the_reconstructions(scenes_root: Path,
                                                                   tmp_path: Path) -> None:
    """``sevenscenes.edge_rule=verified``: every verified pair is an edge (as in
    posernet-reconstruct), also those with fewer matched boxes than the paper's rule asks."""
    import torch

    from posernet.data.store import open_split

    counts = {}
    for rule in ("boxes", "verified"):
        out = tmp_path / rule
        # a rule no pair of this scene meets: only verified edges can make graphs
        code, _, stderr = finish(cli(f"root={scenes_root}", f"out_dir={out}", "progress=false",
                                     f"sevenscenes.edge_rule={rule}",
                                     "box_matching.min_boxes=40", *ARGS))
        if rule == "boxes":
            assert code == 1 and "could not grow a connected" in stderr
            continue
        assert code == 0, stderr
        graphs = open_split(out, "small", "train") + open_split(out, "small", "test")
        counts[rule] = torch.cat([torch.bincount(g.pair_edge, minlength=g.num_edges)
                                  for g in graphs])
        assert json.loads((out / "manifest.json").read_text())["config"][
            "edge_rule"] == rule
    assert 0 < counts["verified"].max() < 40


@pytest.mark.slow
def test_cli_builds_loads_resumes_and_refuses_another_config(scenes_root: Path, tmp_path: Path):
    from posernet.data.posernet_json import load_posernet_json
    from posernet.data.store import open_split

    out = tmp_path / "ds"
    # unquoted intrinsics=a,b,c,d: the command passes it as one string, not a Hydra sweep
    code, stdout, stderr = finish(cli(f"root={scenes_root}", f"out_dir={out}", "export_json=true",
                                      *ARGS))
    assert code == 0, stderr
    assert "7-Scenes graph dataset" in stdout and "KP  ours" in stdout
    assert "per image:" in stdout and "per pair:" in stdout
    assert "images" in stderr and "pairs" in stderr and "graph" in stderr  # progress bars

    m = json.loads((out / "manifest.json").read_text())
    assert m["format"] == "posernet-sevenscenes-dataset" and m["source"] == "sevenscenes"
    assert m["splits"]["small"] == {"train": ["chess"], "val": ["chess"], "test": ["chess"]}
    assert m["splits"]["large"] == {"test": ["chess"]}
    assert m["frontend"]["images"] > 0 and m["frontend"]["seconds"]["features"] > 0
    train = open_split(out, "small", "train")
    assert [g.name for g in train] == ["chess-small-train-00000", "chess-small-train-00001"]
    for split, n in (("val", 1), ("test", 1)):
        assert len(open_split(out, "small", split)) == n
    (large,) = open_split(out, "large", "test")
    assert large.num_nodes == 6
    for g in [*train, large]:
        assert g.pose_gt is not None and g.edge_pose_gt is not None and g.num_edges > 0
        assert g.meta["source"] == "sevenscenes" and g.meta["scene"] == "chess"
        assert len(g.meta["camera_ids"]) == g.num_nodes
        assert all(k.startswith("seq-0") for k in g.meta["camera_ids"])
    # the test sequence is seq-02 (train sequences come first), validation the tail of seq-01
    (val,) = open_split(out, "small", "val")
    assert all(int(k[-16:-10]) >= 8 for k in val.meta["camera_ids"]), val.meta["camera_ids"]
    assert all(k.startswith("seq-02") for k in large.meta["camera_ids"])
    assert len(load_posernet_json(out / m["json"]["small"], "train", "kp")) == 2

    # interrupted run: no manifest, one file missing; resume keeps the complete files
    files = sorted(out.rglob("*.pt"))
    mtimes = {p: p.stat().st_mtime_ns for p in files}
    lost = out / "small/test/chess.pt"
    before = lost.read_bytes()
    lost.unlink()
    (out / "manifest.json").unlink()
    code, _, stderr = finish(cli(f"root={scenes_root}", f"out_dir={out}", "resume=true",
                                 "progress=false", *ARGS))
    assert code == 0, stderr
    assert (out / "manifest.json").is_file()
    for p in files:
        if p != lost:
            assert p.stat().st_mtime_ns == mtimes[p], p
    # made alone in a fresh process, the chunk equals the one made after the others
    assert lost.read_bytes() == before

    # another configuration: refused, nothing touched
    code, _, stderr = finish(cli(f"root={scenes_root}", f"out_dir={out}", "resume=true",
                                 "progress=false", *ARGS, "sevenscenes.locality=0.5"))
    assert code == 1 and "different configuration" in stderr and "locality" in stderr
    assert len(stderr.strip().splitlines()) == 1
    assert (out / "manifest.json").is_file()
    assert all(p.stat().st_mtime_ns == mtimes[p] for p in files if p != lost)


def test_missing_root_in_a_subprocess_is_one_line(tmp_path: Path):
    code, _, stderr = finish(cli(f"root={tmp_path / 'nope'}", f"out_dir={tmp_path / 'ds'}",
                                 "intrinsics=585,585,320,240", "progress=false"))
    assert code == 1, stderr
    assert stderr.startswith("posernet-make-data: error:") and "does not exist" in stderr
    assert len(stderr.strip().splitlines()) == 1
    assert not (tmp_path / "ds").exists()


# --------------------------------------------------------------------------- user errors


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["root={missing}"], "does not exist"),
        (["root={plain}"], "not in 7-Scenes layout"),
        (["root={root}", "intrinsics='1,2,3'"], "4 numbers"),
        (["root={root}", "intrinsics=[-5,5,160,120]"], "focal"),
        (["root={root}", "scenes=[kitchen]"], "kitchen"),
        ([], "needs root=DIR"),
        (["root={root}", "sevenscenes.frame_step=0"], "sevenscenes.frame_step"),
        (["root={root}", "sevenscenes.val_fraction=2"], "sevenscenes.val_fraction"),
        (["root={root}", "proposals=file"], "proposals.path"),
        # 12 frames per sequence, every 5th: 2 train images, fewer than a graph needs
        (["root={root}", "frame_step=5"], "scene 'chess' split 'train' has 2 images"),
    ],
)
def test_user_errors_are_one_line_and_write_nothing(scenes_root, tmp_path, capsys, args,
                                                    message):
    from posernet.cli.make_data import execute

    (tmp_path / "plain" / "photos").mkdir(parents=True)
    paths = {"missing": tmp_path / "nope", "plain": tmp_path / "plain", "root": scenes_root}
    out = tmp_path / "ds"
    cfg = compose("source=sevenscenes", f"out_dir={out}", "progress=false",
                  *[a.format(**paths) for a in args])
    assert execute(cfg) == 1
    assert message in one_line_error(capsys)
    assert not out.exists()


def test_sevenscenes_keys_are_refused_for_synthetic_data(tmp_path, capsys):
    from posernet.cli.make_data import execute

    cfg = compose("dataset=tiny", f"out_dir={tmp_path}", f"root={tmp_path}")
    assert execute(cfg) == 1
    assert "source=sevenscenes" in one_line_error(capsys)


def test_unconnected_scene_names_scene_split_and_the_fix(scenes_root, tmp_path):
    from posernet.cli.build import frontend_stages
    from posernet.data.sevenscenes_graphs import generate_sevenscenes
    from posernet.data.synthetic import SamplingError

    opts = {"root": str(scenes_root), "intrinsics": INTRINSICS, "frame_step": 1,
            "max_tries_per_node": 3, "restarts": 1,
            "small": {"graph_size": 4, "train": 1, "val": 0, "test": 0},
            "large": {"train": 0, "test": 0}}
    impossible = {"box_matching": {"_target_": "posernet.frontend.boxmatch.BoxMatchRules",
                                   "min_boxes": 1000},
                  "matcher": {"_target_": "posernet.frontend.features.SiftMatcher"},
                  "proposals": {"_target_": "posernet.frontend.proposals.EdgeBoxes"}}
    with pytest.raises(SamplingError, match=r"scene 'chess' split 'train'.*connected") as e:
        generate_sevenscenes(opts, tmp_path / "ds", frontend=frontend_stages(impossible),
                             progress=False,
                             echo=None)
    assert "min_boxes" in str(e.value) and "small.train=0" in str(e.value)
    assert not (tmp_path / "ds" / "manifest.json").exists()


# --------------------------------------------------------------------------- pieces


def test_pools_subsample_split_and_cap(scenes_root):
    from posernet.data.sevenscenes import open_sevenscenes
    from posernet.data.sevenscenes_graphs import scene_pools, sevenscenes_options

    (scene,) = open_sevenscenes(scenes_root, intrinsics=(292.5, 292.5, 160, 120))
    p = scene_pools(scene, sevenscenes_options({"root": "x", "frame_step": 2,
                                                "val_fraction": 0.35}))
    # 6 frames per sequence after the step: train 4 (head), val 2 (tail), test 6
    assert {k: v.size for k, v in p.pools.items()} == {"train": 4, "val": 2, "test": 6}
    keys = [r.key for r in p.records]
    assert keys[:4] == [f"seq-01/frame-{i:06d}.color.png" for i in (0, 2, 4, 6)]
    assert keys[4:6] == ["seq-01/frame-000008.color.png", "seq-01/frame-000010.color.png"]
    assert all(k.startswith("seq-02") for k in keys[6:])
    assert len(set(p.sequence[p.pools["train"]])) == 1
    assert set(p.sequence[p.pools["train"]]).isdisjoint(p.sequence[p.pools["val"]])
    assert p.num_frames == 24
    r = p.records[0]
    assert r.K[0, 0] == 292.5 and r.c2w.shape == (4, 4)
    assert np.allclose(r.c2w, scene.camera_to_world(scene.frames("train")[0]))

    capped = scene_pools(scene, sevenscenes_options({"root": "x", "frame_step": 1,
                                                     "max_frames": 3}))
    test_keys = [capped.records[i].key for i in capped.pools["test"]]
    assert test_keys == [f"seq-02/frame-{i:06d}.color.png" for i in (0, 6, 11)]


@pytest.mark.parametrize(
    ("patch", "field"),
    [
        ({"frame_step": 0}, "sevenscenes.frame_step"),
        ({"locality": 1.5}, "sevenscenes.locality"),
        ({"window": -1}, "sevenscenes.window"),
        ({"max_frames": 1}, "sevenscenes.max_frames"),
        ({"small": {"graph_size": 1}}, "sevenscenes.small.graph_size"),
        ({"small": {"train": -1}}, "sevenscenes.small.train"),
        ({"large": {"sizes": 3}}, "sevenscenes.large"),
        ({"scenes": []}, "sevenscenes.scenes"),
        ({"bogus": 1}, "bogus"),
        ({"root": None}, "root=DIR"),
        ({"edge_rule": "all"}, "sevenscenes.edge_rule"),
    ],
)
def test_bad_options_name_the_field(patch, field):
    from posernet.data.sevenscenes_graphs import sevenscenes_options
    from posernet.data.synthetic import ConfigError

    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        sevenscenes_options({"root": "/data/7scenes", **patch})


def test_options_defaults_are_the_papers():
    from posernet.data.sevenscenes_graphs import sevenscenes_options

    o = sevenscenes_options(compose("source=sevenscenes", "root=/data",
                                    "scenes='chess,fire'").sevenscenes)
    assert o.root == "/data" and o.scenes == ["chess", "fire"] and o.frame_step == 10
    assert (o.small.graph_size, o.small.train, o.small.val, o.small.test) == (8, 2000, 200, 1000)
    assert (o.large.graph_size, o.large.train, o.large.val, o.large.test) == (125, 1, 0, 1)
    assert o.large.scenes == ["chess", "fire", "heads", "office", "pumpkin"]
    assert o.scenes_for("large", ["chess", "fire", "stairs"]) == ["chess", "fire"]


def test_unquoted_lists_become_one_string():
    from posernet.cli.common import quote_list_args

    argv = ["prog", "intrinsics=585,585,320,240", "scenes=chess,fire", "scenes=[chess,fire]",
            "dataset.scenes=[chess]", "intrinsics=cams.json"]
    assert quote_list_args(argv, ("intrinsics", "scenes")) == [
        "prog", "intrinsics='585,585,320,240'", "scenes='chess,fire'", "scenes=[chess,fire]",
        "dataset.scenes=[chess]", "intrinsics=cams.json"]


def test_frontend_defaults_are_the_make_data_configs() -> None:
    """The builder's default stages come from the shipped config groups (one source of
    truth), as make_data.yaml picks them."""
    from posernet.data.sevenscenes_graphs import FRONTEND_GROUPS, frontend_defaults

    d = frontend_defaults()
    assert tuple(d) == FRONTEND_GROUPS
    assert d["proposals"]["_target_"].endswith("SelectiveSearch") and d["proposals"]["top_k"] == 50
    assert d["matcher"] == {"_target_": "posernet.frontend.features.make_matcher", "name": "auto"}
    assert d["box_matching"]["min_boxes"] == 5 and d["relpose"]["method"] == "usac"

"""``posernet-reconstruct`` end to end on a rendered scene: images in, camera poses out.

One small scene (7-Scenes layout, 320x240) is rendered per module; the command runs on its
test sequence, with the 7-Scenes pose files as ground truth, and on bad inputs.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from posernet.checkpoints import default_checkpoint
from posernet.data.render import render_intrinsics, render_sevenscenes
from posernet.data.sevenscenes import SevenScenesScene

BIN = Path(sys.executable).parent
W, H, F = 320, 240, 292.5


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("render")
    return render_sevenscenes(root, "chess", seed=3, train_sequences=0, test_sequences=1,
                              frames_per_sequence=8, width=W, height=H, focal=F, progress=False)


def _composed(scene: Path, out: Path) -> object:
    """The command's config for the scene's first sequence (SIFT, pictures, no bars)."""
    from hydra import compose, initialize_config_module

    with initialize_config_module("posernet.conf", version_base=None):
        return compose("reconstruct", overrides=[f"images={scene / 'seq-01'}",
                                                 f"intrinsics='{_intr(scene)}'", "matcher=sift",
                                                 f"out_dir={out}", "progress=false",
                                                 "pictures=1"])


def _intr(scene: Path) -> str:
    return ",".join(f"{v:g}" for v in render_intrinsics(scene))


def _run(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    return subprocess.run([str(BIN / "posernet-reconstruct"), *args, "progress=false"],
                          capture_output=True, text=True, cwd=cwd, env=env, timeout=600)


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    from posernet.geometry import pose_vec_to_matrix

    return pose_vec_to_matrix(torch.tensor([*q, 0.0, 0.0, 0.0]).double()).numpy()[:3, :3]


def _rot_err_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra @ Rb.T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


@pytest.mark.slow
def test_reconstruct_recovers_rendered_rotations(scene, tmp_path):
    out = tmp_path / "out"
    r = _run(f"images={scene / 'seq-01'}", f"intrinsics={_intr(scene)}", f"out_dir={out}",
             "matcher=sift", "refine=false")
    assert r.returncode == 0, r.stderr
    assert "posernet-reconstruct: error" not in r.stderr
    poses = json.loads((out / "poses.json").read_text())
    assert poses["format"] == "posernet-poses" and poses["stage"] == "initial+ba"
    assert "global scale" in poses["positions"]
    cams = poses["cameras"]
    assert len(cams) == 8 and all(c["solved"] for c in cams.values())
    # ground truth read by the 7-Scenes reader on the same scene
    reader = SevenScenesScene(scene, intrinsics=render_intrinsics(scene))
    frames = {f.key.split("/")[-1]: f for f in reader.frames("test")}
    names = sorted(cams)
    R_est = np.stack([np.asarray(cams[n]["world_to_camera"])[:3, :3] for n in names])
    R_gt = np.stack([reader.world_to_camera(frames[n])[:3, :3] for n in names])
    # relative rotations between every camera pair: gauge-free
    errs = [_rot_err_deg(R_est[j] @ R_est[i].T, R_gt[j] @ R_gt[i].T)
            for i in range(len(names)) for j in range(i + 1, len(names))]
    assert np.median(errs) < 2.0, errs
    # positions: camera centres after a similarity alignment, against the trajectory's size
    from posernet.geometry import umeyama_alignment

    c_est = np.stack([np.asarray(cams[n]["camera_to_world"])[:3, 3] for n in names])
    c_gt = np.stack([np.linalg.inv(reader.world_to_camera(frames[n]))[:3, 3] for n in names])
    sc, Rs, ts = (x.numpy() for x in umeyama_alignment(torch.from_numpy(c_est),
                                                        torch.from_numpy(c_gt)))
    pos_err = np.linalg.norm(sc * c_est @ Rs.T + ts - c_gt, axis=1)
    extent = np.linalg.norm(c_gt - c_gt.mean(0), axis=1).max()
    assert np.median(pos_err) < 0.02 * extent, (pos_err, extent)
    ba = poses["bundle_adjustment"]["initial+ba"][0]
    assert ba["points"] > 100 and ba["runs"][0]["accepted"]
    assert ba["reprojection_px"]["median_after"] < 2.0
    assert all("verification" in e and "rotation_only" in e for e in poses["edges"])
    # the same cameras as a COLMAP text model, with the points
    model = out / "sparse" / "0"
    rows = [ln for ln in (model / "images.txt").read_text().splitlines()
            if not ln.startswith("#")]
    head = {r.split()[-1]: r.split() for r in rows[0::2]}
    assert set(head) == set(cams)
    q = np.array([float(v) for v in head[names[1]][1:5]])
    R_colmap = _quat_to_matrix(q)
    assert np.allclose(R_colmap, np.asarray(cams[names[1]]["world_to_camera"])[:3, :3],
                       atol=1e-6)
    n_points = sum(1 for ln in (model / "points3D.txt").read_text().splitlines()
                   if not ln.startswith("#"))
    assert n_points == ba["points"]
    # the output's gauge: first camera of the component at the identity
    assert np.allclose(np.asarray(cams[names[0]]["world_to_camera"]), np.eye(4), atol=1e-6)
    # tables from the pose files, pictures and the summary
    assert (out / "table.md").is_file() and (out / "abs_table.md").is_file()
    assert "Absolute poses" in r.stdout
    # pose files name no unit: the translation columns say so rather than claim metres
    assert "Translation error (ground-truth units)" in (out / "abs_table.md").read_text()
    img = cv2.imread(str(out / "matches_0.png"))
    assert img is not None and img.shape[1] > 2 * W - 10
    assert cv2.imread(str(out / "cameras.png")) is not None
    view = (out / "cameras.html").read_text()  # the interactive view: cameras, points, GT
    assert view.count('"name":"') == 2 * 8 and '"units":"ground-truth units' in view
    assert re.search(r'"points":\[-?\d', view)
    traj = (out / "trajectory_errors.md").read_text()  # evo-style APE / RPE against the GT
    assert "| APE translation (GT units) |" in traj and "RPE rotation (deg)" in traj
    summary = json.loads((out / "summary.json").read_text())
    assert summary["cameras_placed"] == 8
    assert set(summary["frontend"]["seconds"]) >= {"proposals", "features", "matching"}


@pytest.mark.slow
def test_reconstruct_without_ground_truth_and_with_a_blank_image(scene, tmp_path):
    """No pose files: no tables; a blank image gets no proposals and is reported unplaced."""
    imgs = tmp_path / "photos"
    imgs.mkdir()
    for p in sorted((scene / "seq-01").glob("*.color.png"))[:5]:
        shutil.copy(p, imgs / p.name.replace(".color", ""))
    cv2.imwrite(str(imgs / "zz_blank.png"), np.full((H, W, 3), 127, np.uint8))
    out = tmp_path / "out"
    r = _run(f"images={imgs}", f"intrinsics=[{_intr(scene)}]", f"out_dir={out}",
             "matcher=sift", "refine=true", "guard=true")
    assert r.returncode == 0, r.stderr
    assert "without ground-truth poses" in r.stdout
    assert "1 without any proposal" in r.stdout
    assert "with too few keypoint matches" in r.stdout
    assert not (out / "table.md").exists()
    cams = json.loads((out / "poses.json").read_text())["cameras"]
    blank = cams["zz_blank.png"]
    assert blank["solved"] is False and blank["camera_to_world"] is None
    assert sum(c["solved"] for c in cams.values()) == 5
    record = json.loads((out / "poses.json").read_text())
    assert record["stage"] == "refined+ba" and record["guard"] is True
    # the guard's checks ran against the shipped model's training statistics; the rendered
    # images' graph (no distortion, more boxes and edges per image) is unlike them: one line
    check = record["input_check"]
    assert check["training_stats"] and check["warning"] and check["reasons"]
    warnings = [ln for ln in r.stderr.splitlines() if "WARNING" in ln]
    assert len(warnings) == 1 and warnings[0].startswith("posernet-reconstruct: WARNING: ")
    assert set(check["cycle_deg"]) == {"initial", "refined"}


@pytest.mark.slow
@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["images=/nonexistent/photos", "intrinsics=500,500,160,120"], "image folder not found"),
        (["intrinsics=500,500,160"], "4 numbers"),
        (["intrinsics=[[1,0],[0,1]]"], r"shape \(2, 2\)"),
        (["intrinsics=/nonexistent/cams.json"], "intrinsics file not found"),
        (["intrinsics=500,500,160,120", "out_dir=/proc/posernet-out"],
         "out_dir: '/proc/posernet-out' is not a writable folder"),
        (["intrinsics=500,500,160,120", "estimate=xx"], "estimate: 'xx' is not one of kp, bb"),
        (["intrinsics=500,500,160,120", "refine=true", "ckpt_path=/nonexistent.ckpt"],
         "nonexistent.ckpt"),
        (["intrinsics=500,500,160,120", "guard=maybe"], "guard: 'maybe' is not true or false"),
        (["intrinsics=500,500,160,120", "refine=true", "guard=true",
          f"ckpt_path={default_checkpoint('posernet_synthetic_kp_v1.ckpt')}"],
         "needs a checkpoint with a confidence head"),
        (["intrinsics=500,500,160,120", "proposals=file",
          "proposals.path=/nonexistent/boxes.json"], "boxes.json"),
        (["intrinsics=500,500,160,120", "bundle.loss=bogus"], "bundle.loss"),
        (["intrinsics=500,500,160,120", "verify.min_inliers=2"], "verify.min_inliers"),
        (["intrinsics=500,500,160,120", "ba=sometimes"], "ba: 'sometimes'"),
        (["intrinsics=500,500,160,120", "boxes=false", "refine=true"],
         "boxes=false, but refine=true needs the boxes"),
        (["intrinsics=500,500,160,120", "pairs.mode=nearby"], "pairs.mode"),
        (["intrinsics=500,500,160,120", "max_image_size=8"], "max_image_size"),
    ],
)
def test_reconstruct_bad_input_is_one_line(scene, tmp_path, args, message):
    if not any(a.startswith("images=") for a in args):
        args = [f"images={scene / 'seq-01'}", *args]
    if not any(a.startswith("out_dir=") for a in args):
        args = [*args, f"out_dir={tmp_path / 'out'}"]
    r = _run(*args, "matcher=sift")
    assert r.returncode == 1, (r.stdout, r.stderr)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert lines[-1].startswith("posernet-reconstruct: error: "), r.stderr
    assert "Traceback" not in r.stderr
    import re

    assert re.search(message, lines[-1]), lines[-1]
    assert not (tmp_path / "out" / "poses.json").exists()


@pytest.mark.slow
def test_without_intrinsics_the_focal_length_is_recovered(scene, tmp_path):
    """No intrinsics: the prior (1.2 x the longest side, 22 % too long here) is refined by
    bundle adjustment to the rendering's focal length; having moved by more than
    ``bundle.refocus``, the pairs are verified again with it (not with ``refocus=0``)."""
    out = tmp_path / "out"
    r = _run(f"images={scene / 'seq-01'}", f"out_dir={out}", "matcher=sift", "pictures=0")
    assert r.returncode == 0, r.stderr
    assert "8 from the prior" in r.stdout and "refines the focal length" in r.stdout
    poses = json.loads((out / "poses.json").read_text())
    refocus = poses["refocus"]
    assert refocus["guess_px"] == pytest.approx(1.2 * W)
    assert refocus["adjusted_px"] == pytest.approx(F, rel=0.03)
    assert refocus["kept"] == "again" and refocus["again"] == 8
    assert "so the pairs were verified again with it: 8 cameras placed" in r.stdout
    off = _run(f"images={scene / 'seq-01'}", f"out_dir={tmp_path / 'off'}", "matcher=sift",
               "pictures=0", "bundle.refocus=0")
    assert off.returncode == 0, off.stderr
    assert json.loads((tmp_path / "off" / "poses.json").read_text())["refocus"] is None
    cams = poses["cameras"]
    assert all(c["solved"] and c["intrinsics_source"] == "prior" for c in cams.values())
    f = [c["K"][0][0] for c in cams.values()]
    assert np.allclose(f, F, rtol=0.02), (f, F)
    assert all(c["size"] == [W, H] for c in cams.values())


@pytest.mark.slow
def test_bundle_adjustment_that_fails_is_reported_and_loses_nothing(scene, tmp_path):
    """One solver evaluation cannot converge: the averaged poses are kept and the run says so."""
    out = tmp_path / "out"
    r = _run(f"images={scene / 'seq-01'}", f"intrinsics={_intr(scene)}", f"out_dir={out}",
             "matcher=sift", "bundle.max_nfev=1", "pictures=0")
    assert r.returncode == 0, r.stderr
    poses = json.loads((out / "poses.json").read_text())
    assert poses["stage"] == "initial+ba"
    assert all(c["solved"] for c in poses["cameras"].values())
    ba = poses["bundle_adjustment"]["initial+ba"][0]
    assert not any(run["accepted"] for run in ba["runs"])
    assert "input poses kept" in ba["message"] and "input poses kept" in r.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["bundle_adjustment"] == poses["bundle_adjustment"]
    # the error table has both stages, and the BA row equals the averaging row
    table = (out / "abs_table.md").read_text()
    rows = [ln for ln in table.splitlines() if ln.startswith("| KP |")]
    assert len(rows) == 2 and rows[0].split("|")[3:] == rows[1].split("|")[3:], rows


def _colmap_binary_names(folder: Path) -> list[str]:
    """The image names of a COLMAP binary ``images.bin``, read as COLMAP reads them."""
    import struct

    data = (folder / "images.bin").read_bytes()
    (n,), pos, names = struct.unpack_from("<Q", data), 8, []
    for _ in range(n):
        end = data.index(b"\0", pos + 64)
        names.append(data[pos + 64:end].decode())
        (k,) = struct.unpack_from("<Q", data, end + 1)
        pos = end + 9 + 24 * k
    assert pos == len(data)
    return names


@pytest.mark.slow
def test_image_names_with_spaces_are_kept_in_every_output(scene, tmp_path):
    """``kamera 13.png``: every output names the real file (no ``kamera_13.png``); the COLMAP
    model is binary (COLMAP's text reader would cut the name at the space), the TUM header
    quotes each row's name."""
    from posernet.export import read_tum_image_names

    imgs = tmp_path / "my photos"
    imgs.mkdir()
    for k, p in enumerate(sorted((scene / "seq-01").glob("*.color.png"))[:6]):
        shutil.copy(p, imgs / f"kamera {k + 10}.png")
    names = sorted(p.name for p in imgs.iterdir())
    out = tmp_path / "out"
    r = _run(f"images={imgs}", f"intrinsics={_intr(scene)}", f"out_dir={out}", "matcher=sift",
             "pictures=1")
    assert r.returncode == 0, r.stderr
    assert "COLMAP model in" in r.stdout and "binary" in r.stdout
    cams = json.loads((out / "poses.json").read_text())["cameras"]
    assert sorted(cams) == names and all(c["solved"] for c in cams.values())
    model = out / "sparse" / "0"
    assert sorted(p.name for p in model.iterdir()) == ["cameras.bin", "images.bin",
                                                       "points3D.bin"]
    assert sorted(_colmap_binary_names(model)) == names
    try:
        import pycolmap
    except ImportError:
        pycolmap = None
    if pycolmap is not None:  # COLMAP itself reads the real names back
        rec = pycolmap.Reconstruction(str(model))
        assert sorted(im.name for im in rec.images.values()) == names
    frames = json.loads((out / "transforms.json").read_text())["frames"]
    assert sorted(Path(f["file_path"]).name for f in frames) == names
    assert all((out / f["file_path"]).is_file() for f in frames)  # the real image files
    tum = out / "trajectory_tum.txt"
    assert sorted(read_tum_image_names(tum)) == names
    rows = [ln.split() for ln in tum.read_text().splitlines() if not ln.startswith("#")]
    assert len(rows) == len(names) and all(len(row) == 8 for row in rows)
    view = (out / "cameras.html").read_text()
    assert all(f'"name":"{n}"' in view for n in names) and "kamera_" not in view
    assert not any("kamera_" in p.read_text(errors="replace")
                   for p in out.iterdir() if p.is_file() and p.suffix in (".json", ".txt"))


@pytest.mark.slow
def test_reconstruct_unreadable_image(scene, tmp_path):
    imgs = tmp_path / "photos"
    imgs.mkdir()
    for p in sorted((scene / "seq-01").glob("*.color.png"))[:3]:
        shutil.copy(p, imgs / p.name)
    (imgs / "broken.png").write_bytes(b"\x89PNG not really")
    (imgs / "empty.jpg").write_bytes(b"")
    # skipped with one line each, listed in poses.json; the other images still reconstruct
    r = _run(f"images={imgs}", f"intrinsics={_intr(scene)}", f"out_dir={tmp_path / 'o'}",
             "matcher=sift", "pictures=0")
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if "skipped" in ln]
    assert len(lines) == 2 and "broken.png: not an image file" in lines[0]
    assert "empty.jpg: empty file" in lines[1]
    poses = json.loads((tmp_path / "o" / "poses.json").read_text())
    assert [s["file"] for s in poses["skipped_images"]] == ["broken.png", "empty.jpg"]
    assert sorted(poses["cameras"]) == sorted(p.name for p in imgs.glob("*.color.png"))
    # strict=true: nothing runs, one line naming both
    r = _run(f"images={imgs}", f"intrinsics={_intr(scene)}", f"out_dir={tmp_path / 's'}",
             "strict=true")
    assert r.returncode == 1
    last = r.stderr.splitlines()[-1]
    assert "2 unusable image(s)" in last and "broken.png" in last and "empty.jpg" in last
    assert not (tmp_path / "s").exists()


def test_gauge_fixed_puts_each_component_first_camera_at_identity():
    from posernet.reconstruction import gauge_fixed
    from posernet.testing import random_absolute_poses

    T = random_absolute_poses(5, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    solved = torch.tensor([True, True, False, True, True])
    comp = torch.tensor([0, 0, 0, 1, 1])
    out = gauge_fixed(T, solved, comp)
    assert torch.allclose(out[0], torch.eye(4, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(out[3], torch.eye(4, dtype=torch.float64), atol=1e-12)
    assert torch.equal(out[2], T[2])
    # relative poses inside a component are unchanged
    from posernet.geometry import relative_pose

    assert torch.allclose(relative_pose(out[0], out[1]), relative_pose(T[0], T[1]), atol=1e-12)


@pytest.mark.slow
def test_same_command_again_resumes_from_the_cache(scene, tmp_path):
    args = (f"images={scene / 'seq-01'}", f"intrinsics={_intr(scene)}",
            f"out_dir={tmp_path / 'out'}", "pictures=0", "workers=2")
    first = _run(*args)
    assert first.returncode == 0, first.stderr
    assert "reused from the cache" not in first.stdout
    poses = json.loads((tmp_path / "out" / "poses.json").read_text())
    again = _run(*args)  # a finished run is not replaced silently
    assert again.returncode == 1 and "holds a finished run (poses.json)" in again.stderr
    assert "overwrite=true" in again.stderr.splitlines()[-1]
    again = _run(*args, "overwrite=true")
    assert again.returncode == 0, again.stderr
    assert "reused from the cache: 8 images, 28 pairs" in again.stdout
    assert "replaced the previous outputs" in again.stdout
    assert json.loads((tmp_path / "out" / "poses.json").read_text())["cameras"] == poses["cameras"]
    # without the cache nothing is reused, and the result is the same
    fresh = _run(*args[:2], f"out_dir={tmp_path / 'fresh'}", "pictures=0", "cache=false")
    assert fresh.returncode == 0 and "reused" not in fresh.stdout
    assert not (tmp_path / "fresh" / "cache").exists()
    got = json.loads((tmp_path / "fresh" / "poses.json").read_text())["cameras"]
    assert got == poses["cameras"]


def _cache_entries(out: Path) -> dict[str, int]:
    return {kind: len(list(out.glob(f"cache/*/{kind}/*.npz"))) for kind in ("images", "pairs")}


@pytest.mark.slow
def test_ctrl_c_is_one_line_and_the_same_command_resumes(scene, tmp_path):
    """Ctrl-C while pairs are matched: one line (what the cache keeps, counted), exit status
    130, no traceback, nothing but the cache in out_dir; the same command again reuses
    exactly those images and pairs."""
    import signal
    import time

    out = tmp_path / "out"
    cmd = [str(BIN / "posernet-reconstruct"), f"images={scene / 'seq-01'}",
           f"intrinsics={_intr(scene)}", f"out_dir={out}", "matcher=sift", "pictures=0",
           "workers=1", "progress=false"]
    from helpers import as_from_a_terminal

    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True, env=dict(os.environ, OMP_NUM_THREADS="1"),
                         preexec_fn=as_from_a_terminal)
    deadline = time.monotonic() + 300
    while _cache_entries(out)["pairs"] < 3 and p.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    if p.poll() is None:
        os.killpg(p.pid, signal.SIGINT)  # what Ctrl-C in a terminal does
    _, err = p.communicate(timeout=300)
    if p.returncode == 0:
        pytest.skip("the run finished before the interrupt")
    assert p.returncode == 130, err
    assert "Traceback" not in err
    (line,) = err.strip().splitlines()
    kept = _cache_entries(out)
    assert kept["images"] == 8 and 3 <= kept["pairs"] < 28
    assert line == (
        "posernet-reconstruct: interrupted; run the same command again to resume: it reuses "
        f"the front-end work kept in {out / 'cache'} (8 image(s): features; {kept['pairs']} "
        "image pair(s): matches and two-view verification) and computes the rest again (other "
        "images and pairs, averaging, bundle adjustment, outputs)")
    assert [q.name for q in out.iterdir()] == ["cache"]
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=600,
                           env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert again.returncode == 0, again.stderr
    assert f"reused from the cache: 8 images, {kept['pairs']} pairs" in again.stdout
    assert sum(c["solved"] for c in
               json.loads((out / "poses.json").read_text())["cameras"].values()) == 8


@pytest.mark.slow
@pytest.mark.parametrize(("error", "status"), [(KeyboardInterrupt, 130), (ValueError, 1)])
def test_a_run_stopped_while_writing_leaves_no_partial_outputs(scene, tmp_path, monkeypatch,
                                                              capsys, error, status):
    """Ctrl-C (or an error) once the outputs are being written: those already written are
    removed again, so that out_dir never holds a partial set (a lone poses.json would pass
    for a finished run and make the same command refuse to start); its cache stays."""
    import posernet.export as export_module
    from posernet.cli.reconstruct import _direct

    def stopped(*args, **kwargs):
        raise error("stopped while writing")

    monkeypatch.setattr(export_module, "write_tum", stopped)
    out = tmp_path / "o"
    cfg = _composed(scene, out)
    with pytest.raises(SystemExit) as exc:
        _direct(cfg)
    assert exc.value.code == status
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(
        "posernet-reconstruct: interrupted; run the same command again to resume"
        if status == 130 else "posernet-reconstruct: error: stopped while writing")
    assert [q.name for q in out.iterdir()] == ["cache"]  # no poses.json, sparse/, ...


@pytest.mark.slow
def test_pair_selection_and_boxes_only_when_used(scene, tmp_path):
    args = (f"images={scene / 'seq-01'}", f"intrinsics={_intr(scene)}", "pictures=0")
    r = _run(*args, f"out_dir={tmp_path / 'seq'}", "pairs.mode=sequential", "pairs.window=2",
             "pairs.loop_k=0")
    assert r.returncode == 0, r.stderr
    poses = json.loads((tmp_path / "seq" / "poses.json").read_text())
    sel = poses["pair_selection"]
    assert sel["mode"] == "sequential" and sel["n_pairs"] == 7 + 6 and sel["components"] == 1
    assert sum(c["solved"] for c in poses["cameras"].values()) == 8
    assert "pair selection: sequential, 13 pairs" in r.stdout
    # no stage uses boxes by default: none detected; with boxes=true they are
    assert "no boxes: no stage uses them" in r.stdout
    assert all(e["matched_boxes"] == 0 for e in poses["edges"])
    r = _run(*args, f"out_dir={tmp_path / 'boxes'}", "boxes=true")
    assert r.returncode == 0, r.stderr
    poses = json.loads((tmp_path / "boxes" / "poses.json").read_text())
    assert poses["pair_selection"]["mode"] == "exhaustive"  # auto: few images
    assert any(e["matched_boxes"] > 0 for e in poses["edges"])


@pytest.mark.slow
def test_nothing_placed_still_writes_poses_and_says_why(scene, tmp_path):
    imgs = tmp_path / "noise"
    imgs.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):  # nothing to match between noise images
        cv2.imwrite(str(imgs / f"n{i}.png"), (rng.random((240, 320)) * 255).astype(np.uint8))
    out = tmp_path / "o"
    r = _run(f"images={imgs}", "intrinsics=300,300,160,120", f"out_dir={out}", "pictures=2")
    assert r.returncode == 3, r.stderr
    assert "placed no camera" in r.stderr and "too few keypoint matches" in r.stderr
    poses = json.loads((out / "poses.json").read_text())
    assert poses["format"] == "posernet-poses" and poses["stage"] is None
    assert [c["solved"] for c in poses["cameras"].values()] == [False] * 3
    assert all("no image pair passed" in c["note"] for c in poses["cameras"].values())
    assert {p["reason"] for p in poses["rejected_pairs"]} == {"too_few_matches"}
    assert len(poses["rejected_pairs"]) == 3
    assert json.loads((out / "summary.json").read_text())["cameras_placed"] == 0
    assert sorted(p.name for p in out.glob("matches_*.png")) == ["matches_0.png",
                                                                 "matches_1.png"]
    # one image: a bad input, not a run
    one = tmp_path / "one"
    one.mkdir()
    shutil.copy(imgs / "n0.png", one / "n0.png")
    r = _run(f"images={one}", "intrinsics=300,300,160,120", f"out_dir={tmp_path / 'o1'}")
    assert r.returncode == 1 and "need at least 2" in r.stderr.splitlines()[-1]


@pytest.mark.slow
def test_out_dir_with_other_files_or_an_interrupted_run(scene, tmp_path):
    args = (f"images={scene / 'seq-01'}", f"intrinsics={_intr(scene)}", "pictures=0")
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    r = _run(*args, f"out_dir={other}")
    assert r.returncode == 1 and "1 other file(s), e.g. notes.txt" in r.stderr
    r = _run(*args, f"out_dir={other}", "overwrite=true")
    assert r.returncode == 0, r.stderr
    assert (other / "notes.txt").read_text() == "mine"  # never removes unknown files
    # only a cache left (an interrupted run): resumed without overwrite
    for p in other.iterdir():
        if p.name != "cache":
            shutil.rmtree(p) if p.is_dir() else p.unlink()
    r = _run(*args, f"out_dir={other}")
    assert r.returncode == 0, r.stderr
    assert "reused from the cache: 8 images" in r.stdout
    # a stale output of the earlier run does not survive a replacement
    (other / "matches_9.png").write_bytes(b"old")
    r = _run(*args, f"out_dir={other}", "overwrite=true")
    assert r.returncode == 0 and not (other / "matches_9.png").exists()


@pytest.mark.slow
def test_front_end_refiner_guard_quiet_on_an_ordinary_camera_warns_on_a_long_lens(tmp_path):
    """``refine=true`` uses the front-end checkpoint, whose guard statistics describe the
    front end's graphs of ordinary cameras: degraded 640x480 photos at f = 585 px pass without
    a word; the same photos declared as taken with a 4x longer lens get one warning naming
    the focal length."""
    from posernet.data.degrade import Degradation

    folder = render_sevenscenes(tmp_path / "render", "office", seed=5, train_sequences=0,
                                test_sequences=1, frames_per_sequence=10, progress=False,
                                degrade=Degradation())
    imgs = tmp_path / "photos"
    imgs.mkdir()
    for p in sorted((folder / "seq-01").glob("*.color.png")):
        shutil.copy(p, imgs / p.name.replace(".color", ""))
    ordinary = _run(f"images={imgs}", "intrinsics=585,585,320,240", "refine=true",
                    "pictures=0", f"out_dir={tmp_path / 'a'}")
    assert ordinary.returncode == 0, ordinary.stderr
    assert "WARNING" not in ordinary.stderr
    record = json.loads((tmp_path / "a" / "poses.json").read_text())
    assert record["stage"] == "refined+ba" and not record["input_check"]["warning"]
    long_lens = _run(f"images={imgs}", "intrinsics=2340,2340,320,240", "refine=true",
                     "pictures=0", f"out_dir={tmp_path / 'b'}")
    assert long_lens.returncode == 0, long_lens.stderr
    (warning,) = [ln for ln in long_lens.stderr.splitlines() if "WARNING" in ln]
    assert "node_focal median 2340 outside the training range" in warning


@pytest.mark.slow
def test_a_camera_failing_the_self_check_is_unsolved_in_every_output(scene, tmp_path,
                                                                      monkeypatch):
    """The self-check's verdict reaches every output: the failed camera is unsolved with its
    reason in poses.json and absent from sparse/, transforms.json, the TUM file and
    cameras.html; the others stay placed."""
    from hydra import compose, initialize_config_module

    import posernet.reconstruction as reconstruct_module
    from posernet.cli.reconstruct import run
    from posernet.sfm import selfcheck

    real = selfcheck.check_reconstruction

    def planted(*args, **kwargs):  # camera 2 fails, whatever the evidence says
        out = real(*args, **kwargs)
        if out.passed[2]:
            out.passed[2] = False
            out.reason[2] = "planted failure"
        return out

    monkeypatch.setattr(reconstruct_module, "check_reconstruction", planted)
    out = tmp_path / "o"
    with initialize_config_module("posernet.conf", version_base=None):
        cfg = compose("reconstruct", overrides=[f"images={scene / 'seq-01'}",
                                                f"intrinsics='{_intr(scene)}'",
                                                f"out_dir={out}", "progress=false",
                                                "pictures=1"])
    run(cfg)
    poses = json.loads((out / "poses.json").read_text())
    names = list(poses["cameras"])
    bad = names[2]
    assert poses["cameras"][bad]["solved"] is False
    assert poses["cameras"][bad]["note"] == "failed the self-check: planted failure"
    assert poses["self_check"]["failed"] == {bad: "planted failure"}
    assert poses["self_check"]["verified"] is True
    placed = [n for n, c in poses["cameras"].items() if c["solved"]]
    assert len(placed) == len(names) - 1
    images_txt = (out / "sparse" / "0" / "images.txt").read_text()
    assert bad not in images_txt and all(n in images_txt for n in placed)
    frames = json.loads((out / "transforms.json").read_text())["frames"]
    assert not any(bad in f["file_path"] for f in frames) and len(frames) == len(placed)
    tum = (out / "trajectory_tum.txt").read_text()
    assert bad not in tum
    assert len([line for line in tum.splitlines() if not line.startswith("#")]) == len(placed)
    html = (out / "cameras.html").read_text()
    assert bad not in html and all(n in html for n in placed)
    assert json.loads((out / "summary.json").read_text())["cameras_placed"] == len(placed)


@pytest.mark.slow
def test_html_view_title_and_status_count_the_same_points(scene, tmp_path, monkeypatch):
    """A few points far out (bad triangulations), which the view does not draw: the page's
    title and its status line still give the same number of 3D points, that of the model."""

    import posernet.reconstruction as reconstruct_module
    from posernet.cli.reconstruct import run

    real = reconstruct_module.largest_point_cloud
    seen = {}

    def with_far_points(rec, workers=1):
        cams, pts, colours = real(rec, workers)
        far = pts.mean(0) + 1e5 * np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]])
        seen["points"] = len(pts) + 3
        return cams, np.concatenate([pts, far]), np.concatenate([colours, colours[:3]])

    monkeypatch.setattr(reconstruct_module, "largest_point_cloud", with_far_points)
    out = tmp_path / "o"
    cfg = _composed(scene, out)
    run(cfg)
    page = (out / "cameras.html").read_text()
    title = re.search(r"<title>(.*?)</title>", page).group(1)
    status = json.loads(re.search(r'<script id="data" type="application/json">(.*?)</script>',
                                  page, re.S).group(1))["status"]
    count = re.compile(r"(\d+) points")
    assert count.search(title).group(1) == count.search(status).group(1) == str(seen["points"])
    assert f"({seen['points'] - 3} drawn; left out: 3 far from the cameras)" in status


@pytest.mark.slow
def test_a_run_that_cannot_verify_itself_says_so_and_exits_4(scene, tmp_path):
    out = tmp_path / "o"
    r = _run(f"images={scene / 'seq-01'}", f"intrinsics={_intr(scene)}", f"out_dir={out}",
             "pictures=0", "check.min_points=1000000")
    assert r.returncode == 4, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("posernet-reconstruct: self-check: could not verify") and \
        "(exit status 4)" in last
    poses = json.loads((out / "poses.json").read_text())
    assert not any(c["solved"] for c in poses["cameras"].values())
    assert all("sees" in c["note"] for c in poses["cameras"].values())
    assert poses["self_check"]["verified"] is False
    assert not (out / "sparse" / "0").exists() and not (out / "transforms.json").exists()
    # the check off: the same run places its cameras
    r = _run(f"images={scene / 'seq-01'}", f"intrinsics={_intr(scene)}",
             f"out_dir={tmp_path / 'off'}", "pictures=0", "self_check=false")
    assert r.returncode == 0, r.stderr
    poses = json.loads((tmp_path / "off" / "poses.json").read_text())
    assert poses["self_check"] is None and all(c["solved"] for c in poses["cameras"].values())

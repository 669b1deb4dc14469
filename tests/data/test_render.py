"""Offline renderer: 7-Scenes layout, depth and poses consistent with the geometry, boxes."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from posernet.data.render import (
    Renderer,
    make_trajectory,
    object_ring_scene,
    read_render_info,
    render_intrinsics,
    render_object_ring,
    render_sevenscenes,
)
from posernet.data.synthetic.camera import cuboid_corners, projected_boxes, rotation_z
from posernet.data.synthetic.scenes import Scene, build_scene
from posernet.data.synthetic.seeding import make_rng

W, H, F = 160, 120, 146.25  # 7-Scenes intrinsics scaled by 1/4
FRAMES = 3
SEED = 3


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("render")
    return render_sevenscenes(
        root, "chess", seed=SEED, train_sequences=1, test_sequences=1,
        frames_per_sequence=FRAMES, width=W, height=H, focal=F, progress=False,
    )  # fmt: skip


@pytest.fixture(scope="module")
def scene() -> Scene:
    return build_scene("chess", make_rng(SEED, "chess", "layout"))


STEMS = [f"frame-{k:06d}" for k in range(FRAMES)]
EXTS = (".color.png", ".depth.png", ".pose.txt")


def test_layout(rendered: Path) -> None:
    assert rendered.name == "chess"
    assert sorted(p.name for p in rendered.iterdir()) == [
        "TestSplit.txt", "TrainSplit.txt", "objects.json", "render.json", "seq-01", "seq-02",
    ]  # fmt: skip
    assert (rendered / "TrainSplit.txt").read_text() == "sequence1\n"
    assert (rendered / "TestSplit.txt").read_text() == "sequence2\n"
    for seq in ("seq-01", "seq-02"):
        expect = sorted(f"{s}{ext}" for s in STEMS for ext in EXTS)
        assert sorted(p.name for p in (rendered / seq).iterdir()) == expect  # no temp files left
        img = cv2.imread(str(rendered / seq / "frame-000000.color.png"), cv2.IMREAD_UNCHANGED)
        assert img.dtype == np.uint8 and img.shape == (H, W, 3)
        assert img.std() > 20  # textured, not flat
    info = read_render_info(rendered)
    assert (info["width"], info["height"], info["focal"]) == (W, H, F)
    assert info["principal_point"] == [W / 2, H / 2]
    assert info["seed"] == SEED and info["num_frames"] == 2 * FRAMES
    assert render_intrinsics(rendered) == (F, F, W / 2, H / 2)


def test_depth_png(rendered: Path) -> None:
    d = cv2.imread(str(rendered / "seq-01" / "frame-000001.depth.png"), cv2.IMREAD_UNCHANGED)
    assert d.dtype == np.uint16 and d.shape == (H, W)
    valid = d != 65535
    assert valid.mean() > 0.99  # a closed room: every ray hits something
    assert d[valid].min() > 100 and d[valid].max() < 10000  # millimetres: 0.1 m .. 10 m


def _c2w(path: Path) -> np.ndarray:
    T = np.loadtxt(path)
    assert T.shape == (4, 4)
    return T


def test_pose_is_inverse_of_trajectory(rendered: Path, scene: Scene) -> None:
    for n in (1, 2):
        w2c = make_trajectory(scene, FRAMES, make_rng(SEED, "chess", "render", n))
        for k in range(FRAMES):
            T = _c2w(rendered / f"seq-{n:02d}" / f"frame-{k:06d}.pose.txt")
            np.testing.assert_allclose(T @ w2c[k], np.eye(4), atol=1e-9)
            np.testing.assert_array_equal(T[3], [0, 0, 0, 1])


def _box_sdf(p: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Signed distance of local points ``(N, 3)`` to a box surface (0 on the surface)."""
    q = np.abs(p) - half
    return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0)


def _backproject(rendered: Path, seq: str, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points ``(N, 3)`` of all valid pixels, their pixels ``(N, 2)`` and the c2w pose."""
    d = cv2.imread(str(rendered / seq / f"frame-{k:06d}.depth.png"), cv2.IMREAD_UNCHANGED)
    T = _c2w(rendered / seq / f"frame-{k:06d}.pose.txt")
    v, u = np.nonzero(d != 65535)
    z = d[v, u] / 1000.0
    xc = np.stack(((u - W / 2) / F * z, (v - H / 2) / F * z, z), -1)
    return xc @ T[:3, :3].T + T[:3, 3], np.stack((u, v), -1), T


def test_depth_lies_on_scene_surfaces(rendered: Path, scene: Scene) -> None:
    X, _, _ = _backproject(rendered, "seq-02", 2)
    Rz = rotation_z(scene.yaw)
    dist = [np.abs(_box_sdf(X - scene.room / 2, scene.room / 2))]  # floor, walls, ceiling
    for i in range(scene.num_objects):
        dist.append(np.abs(_box_sdf((X - scene.centre[i]) @ Rz[i], scene.half[i])))
    nearest = np.min(dist, axis=0)
    # millimetre depth quantisation; points are not inside anything either
    assert np.quantile(nearest, 0.99) < 1e-3, nearest.max()
    on_objects = np.min(dist[1:], axis=0) < 1e-3
    assert on_objects.mean() > 0.05  # the camera sees objects, not only walls


def _ray_depth(scene: Scene, C: np.ndarray, d: np.ndarray) -> float:
    """Nearest hit along ``C + t d`` (independent float64 per-ray slab tests)."""
    best = np.inf
    for a in range(3):  # room walls, seen from inside
        if d[a] > 0:
            best = min(best, (scene.room[a] - C[a]) / d[a])
        elif d[a] < 0:
            best = min(best, -C[a] / d[a])
    for i in range(scene.num_objects):
        R = rotation_z(np.array(scene.yaw[i]))
        o, dl, h = R.T @ (C - scene.centre[i]), R.T @ d, scene.half[i]
        tn, tf = -np.inf, np.inf
        for a in range(3):
            if abs(dl[a]) < 1e-12:
                if abs(o[a]) > h[a]:
                    tn, tf = np.inf, -np.inf
                continue
            t1, t2 = (-h[a] - o[a]) / dl[a], (h[a] - o[a]) / dl[a]
            tn, tf = max(tn, min(t1, t2)), min(tf, max(t1, t2))
        if 0 < tn <= tf:
            best = min(best, tn)
    return best


def test_depth_matches_independent_ray_cast(rendered: Path, scene: Scene) -> None:
    d = cv2.imread(str(rendered / "seq-01" / "frame-000000.depth.png"), cv2.IMREAD_UNCHANGED)
    T = _c2w(rendered / "seq-01" / "frame-000000.pose.txt")
    rng = np.random.default_rng(0)
    err = []
    for u, v in zip(rng.integers(0, W, 60), rng.integers(0, H, 60), strict=True):
        ray = T[:3, :3] @ np.array([(u - W / 2) / F, (v - H / 2) / F, 1.0])  # camera z = 1
        err.append(abs(_ray_depth(scene, T[:3, 3], ray) - d[v, u] / 1000.0))
    err = np.array(err)
    assert np.mean(err < 0.6e-3) >= 0.95  # a silhouette pixel may flip between surfaces


def test_objects_json(rendered: Path, scene: Scene) -> None:
    doc = json.loads((rendered / "objects.json").read_text())
    assert doc["format"] == "posernet-boxes" and doc["version"] == 1
    keys = [f"{s}/{f}.color.png" for s in ("seq-01", "seq-02") for f in STEMS]
    assert sorted(doc["images"]) == sorted(keys)
    K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]])
    corners = cuboid_corners(scene.centre, scene.half, scene.rotation)
    for key, entry in doc["images"].items():
        boxes = np.array(entry["boxes"], float).reshape(-1, 4)
        assert len(boxes) >= 3  # the camera looks at the content zone
        assert len(entry["scores"]) == len(boxes) == len(entry["object_ids"])
        assert all(s == 1.0 for s in entry["scores"])
        ids = np.array(entry["object_ids"])
        assert len(set(ids.tolist())) == len(ids) and ids.min() >= 0
        assert ids.max() < scene.num_objects
        assert (boxes[:, 0] >= 0).all() and (boxes[:, 1] >= 0).all()
        assert (boxes[:, 2] <= W).all() and (boxes[:, 3] <= H).all()
        assert (boxes[:, 2] > boxes[:, 0]).all() and (boxes[:, 3] > boxes[:, 1]).all()
        # the visible part lies inside the object's full projection
        T = _c2w(rendered / key.replace(".color.png", ".pose.txt"))
        Rw, tw = T[:3, :3].T, -T[:3, :3].T @ T[:3, 3]
        proj, ok = projected_boxes(corners[ids] @ Rw.T + tw, K, W, H, near=0.01)
        assert ok.all()
        assert (boxes[:, :2] >= proj[:, :2] - 1.0).all()
        assert (boxes[:, 2:] <= proj[:, 2:] + 1.0).all()


def test_deterministic(tmp_path: Path) -> None:
    kw = dict(scene="heads", seed=1, train_sequences=1, test_sequences=0, frames_per_sequence=2,
              width=96, height=72, focal=87.75, progress=False)  # fmt: skip
    a = render_sevenscenes(tmp_path / "a", **kw)
    b = render_sevenscenes(tmp_path / "b", **kw)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert len(files) == 4 + 3 * 2
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f


def test_overwrite(tmp_path: Path) -> None:
    kw = dict(scene="heads", test_sequences=0, width=64, height=48, focal=58.5, progress=False)
    folder = render_sevenscenes(tmp_path, frames_per_sequence=3, **kw)
    (folder / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match=re.escape(str(folder))):
        render_sevenscenes(tmp_path, frames_per_sequence=2, **kw)
    render_sevenscenes(tmp_path, frames_per_sequence=2, overwrite=True, **kw)
    assert sorted(p.name for p in (folder / "seq-01").iterdir()) == sorted(
        f"frame-00000{k}{e}" for k in range(2) for e in EXTS
    )  # no stale frame-000002 left behind
    assert (folder / "notes.txt").read_text() == "mine"  # files it did not write are kept
    # an empty existing folder is fine without overwrite; the folder name can differ
    (tmp_path / "empty").mkdir()
    out = render_sevenscenes(tmp_path, frames_per_sequence=1, name="empty", **kw)
    assert (out / "seq-01" / "frame-000000.color.png").is_file()


def test_bad_arguments(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unknown scene 'kitchen'"):
        render_sevenscenes(tmp_path, "kitchen", progress=False)
    with pytest.raises(ValueError, match="at least one sequence"):
        render_sevenscenes(tmp_path, train_sequences=0, test_sequences=0, progress=False)
    with pytest.raises(ValueError, match="focal"):
        render_sevenscenes(tmp_path, focal=0.0, progress=False)
    assert not any(tmp_path.iterdir())


def test_trajectory_overlaps(scene: Scene) -> None:
    w2c = make_trajectory(scene, 20, make_rng(0, "t"))
    C = np.einsum("fji,fj->fi", w2c[:, :3, :3], -w2c[:, :3, 3])
    step = np.linalg.norm(np.diff(C, axis=0), axis=1)
    assert (step > 0.05).all() and (step < 0.25).all()
    R = w2c[:, :3, :3]
    cos = (np.einsum("fij,fij->f", R[1:], R[:-1]) - 1) / 2
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 8.0
    fwd = R[:, 2]  # optical axes look into the room, slightly down
    assert (fwd[:, 1] > 0.3).all() and (fwd[:, 2] < 0.2).all()


def test_supersampling_keeps_geometry(scene: Scene) -> None:
    w2c = make_trajectory(scene, 1, make_rng(0, "s"))[0]
    a = Renderer(scene, 0, 80, 60, 73.125, supersample=1).render(w2c)
    b = Renderer(scene, 0, 80, 60, 73.125, supersample=2).render(w2c)
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(a.object_id, b.object_id)
    assert np.abs(a.rgb.astype(float) - b.rgb).mean() < 20


def test_low_texture_keeps_geometry_and_loses_keypoints(scene: Scene) -> None:
    """``textured_every`` > 1: the same depth and objects, fewer corners to match; the
    objects it keeps (index % k == 0) look as before."""
    w2c = make_trajectory(scene, 1, make_rng(0, "s"))[0]
    full = Renderer(scene, 0, 320, 240, 292.5).render(w2c)
    plain = Renderer(scene, 0, 320, 240, 292.5, textured_every=4).render(w2c)
    np.testing.assert_array_equal(full.depth, plain.depth)
    np.testing.assert_array_equal(full.object_id, plain.object_id)
    sift = cv2.SIFT_create()

    def corners(rgb: np.ndarray) -> int:
        return len(sift.detect(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), None))

    assert corners(plain.rgb) < 0.7 * corners(full.rgb)  # 132 vs 244 here
    kept = np.isin(full.object_id, np.arange(0, scene.num_objects, 4))
    assert kept.any()
    np.testing.assert_array_equal(full.rgb[kept], plain.rgb[kept])
    with pytest.raises(ValueError, match="textured_every"):
        render_sevenscenes(Path("/nonexistent"), textured_every=0, progress=False)


def test_object_ring_looks_at_a_plain_object_from_all_round(tmp_path: Path) -> None:
    """Views evenly round the object, each camera looking at it; the object's faces are one
    colour (a 1 % drift) in a textured room, and everything is plain without the room."""
    n = 8
    folder = render_object_ring(tmp_path / "ring", n, width=W, height=H, focal=F,
                                progress=False)
    assert render_intrinsics(folder) == (F, F, W / 2, H / 2)
    c2w = np.stack([np.loadtxt(folder / f"frame-{k:06d}.pose.txt") for k in range(n)])
    centres = c2w[:, :3, 3]
    heading = np.degrees(np.arctan2(centres[:, 1] - 3.0, centres[:, 0] - 3.0))
    np.testing.assert_allclose(np.diff(np.unwrap(heading, period=360)), 360 / n, atol=5)
    np.testing.assert_allclose(np.linalg.norm(centres[:, :2] - 3.0, axis=1), 1.5, atol=0.15)
    # the object's centre projects near the image centre: every view looks at it
    x = np.einsum("kji,kj->ki", c2w[:, :3, :3], np.array([3.0, 3.0, 0.55]) - centres)
    uv = F * x[:, :2] / x[:, 2:3] + [W / 2, H / 2]
    assert (x[:, 2] > 0).all() and (np.abs(uv - [W / 2, H / 2]) < [W / 5, H / 5]).all()
    scene = object_ring_scene()
    r = Renderer(scene, 0, W, H, F, plain=frozenset(range(3)))
    view = r.render(np.linalg.inv(c2w[0]))
    body = view.object_id == 0  # the cabinet's body: a flat colour up to shading
    grey = cv2.cvtColor(view.rgb, cv2.COLOR_RGB2GRAY).astype(float)
    assert body.sum() > 0.1 * W * H
    lap = np.abs(cv2.Laplacian(grey, cv2.CV_64F))
    inner = cv2.erode(body.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    room = view.object_id == -1
    assert np.median(lap[inner]) < 3.0 < np.median(lap[room])  # plain object, textured room
    bare = render_object_ring(tmp_path / "bare", 2, width=W, height=H, focal=F,
                              background=False, progress=False)
    assert object_ring_scene(background=False).num_objects == 3
    grey = cv2.cvtColor(cv2.imread(str(bare / "frame-000000.color.png")), cv2.COLOR_BGR2GRAY)
    assert np.median(np.abs(cv2.Laplacian(grey.astype(float), cv2.CV_64F))) < 3.0
    with pytest.raises(ValueError, match="radius"):
        render_object_ring(tmp_path / "x", 4, radius=0.0, progress=False)
    with pytest.raises(FileExistsError, match="not empty"):
        render_object_ring(folder, n, width=W, height=H, focal=F, progress=False)

"""COLMAP export: camera models, ids and tracks consistent, readable by pycolmap; image names
kept as they are (the binary model for names the text model cannot hold)."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from posernet.export import colmap_camera, write_colmap_model, write_colmap_text
from posernet.sfm.synthetic import make_scene

K = np.array([[500.0, 0, 320], [0, 510.0, 240], [0, 0, 1]])


def test_camera_models():
    assert colmap_camera(K, None) == ("PINHOLE", [500.0, 510.0, 320.0, 240.0])
    assert colmap_camera(K, np.zeros(5))[0] == "PINHOLE"
    name, p = colmap_camera(K, np.array([0.1, -0.05]))
    assert name == "OPENCV" and p[4:] == [0.1, -0.05, 0.0, 0.0]
    name, p = colmap_camera(K, np.array([0.1, -0.05, 0.001, 0.002, 0.01]))
    assert name == "FULL_OPENCV" and len(p) == 12
    with pytest.raises(ValueError, match="no COLMAP camera model"):
        colmap_camera(K, np.ones(12))


def _write(tmp_path, images=None, names="img{}.png", binary=False):
    s = make_scene(num_cameras=5, num_points=80, seed=3)
    n = s.w2c.shape[0]
    images = np.arange(n) if images is None else np.asarray(images)
    dist = [None, np.array([0.1, -0.05]), None, np.array([0.1, -0.05, 0.001, 0.002, 0.01]),
            None]
    errors = np.linspace(0.1, 0.9, s.obs_image.size)
    files = write_colmap_model(tmp_path, [names.format(i) for i in range(n)], None,
                               [(640, 480)] * n, s.K, dist, s.w2c, images, s.uv, s.points,
                               s.obs_image, s.obs_kp, s.obs_point, errors, binary=binary)
    return s, files


def _parse(folder):
    lines = {name: [ln for ln in (folder / name).read_text().splitlines()
                    if not ln.startswith("#")]
             for name in ("cameras.txt", "images.txt", "points3D.txt")}
    images = {}
    rows = lines["images.txt"]
    for head, pts in zip(rows[0::2], rows[1::2], strict=True):
        f = head.split()
        vals = pts.split()
        images[int(f[0])] = {"pose": [float(v) for v in f[1:8]], "camera": int(f[8]),
                             "name": f[9],
                             "p2d": [(float(vals[k]), float(vals[k + 1]), int(vals[k + 2]))
                                     for k in range(0, len(vals), 3)]}
    points = {}
    for row in lines["points3D.txt"]:
        f = row.split()
        track = [(int(f[k]), int(f[k + 1])) for k in range(8, len(f), 2)]
        points[int(f[0])] = {"xyz": [float(v) for v in f[1:4]],
                             "rgb": [int(v) for v in f[4:7]], "error": float(f[7]),
                             "track": track}
    return lines["cameras.txt"], images, points


def _parse_binary(folder):
    """COLMAP's binary model, read as its reader does (reconstruction_io_binary.cc), into the
    shapes of :func:`_parse`."""
    models = {1: "PINHOLE", 4: "OPENCV", 6: "FULL_OPENCV"}
    n_params = {"PINHOLE": 4, "OPENCV": 8, "FULL_OPENCV": 12}
    data = (folder / "cameras.bin").read_bytes()
    (n,), pos, cams = struct.unpack_from("<Q", data), 8, []
    for _ in range(n):
        cid, model, w, h = struct.unpack_from("<IiQQ", data, pos)
        pos += 24
        k = n_params[models[model]]
        params = struct.unpack_from(f"<{k}d", data, pos)
        pos += 8 * k
        cams.append((cid, models[model], w, h, params))
    assert pos == len(data)
    data = (folder / "images.bin").read_bytes()
    (n,), pos, images = struct.unpack_from("<Q", data), 8, {}
    for _ in range(n):
        v = struct.unpack_from("<I7dI", data, pos)
        end = data.index(b"\0", pos + 64)
        name = data[pos + 64:end].decode()
        (k,) = struct.unpack_from("<Q", data, end + 1)
        pos = end + 9
        p2d = [struct.unpack_from("<ddQ", data, pos + 24 * j) for j in range(k)]
        pos += 24 * k
        images[v[0]] = {"pose": list(v[1:8]), "camera": v[8], "name": name,
                        "p2d": [(x, y, int(p)) for x, y, p in p2d]}
    assert pos == len(data)
    data = (folder / "points3D.bin").read_bytes()
    (n,), pos, points = struct.unpack_from("<Q", data), 8, {}
    for _ in range(n):
        pid, x, y, z, r, g, b, err, k = struct.unpack_from("<Q3d3BdQ", data, pos)
        pos += 51
        track = [struct.unpack_from("<II", data, pos + 8 * j) for j in range(k)]
        pos += 8 * k
        points[pid] = {"xyz": [x, y, z], "rgb": [r, g, b], "error": err, "track": track}
    assert pos == len(data)
    return cams, images, points


def test_tracks_point_back_at_their_observations(tmp_path):
    s, files = _write(tmp_path)
    assert [f.name for f in files] == ["cameras.txt", "images.txt", "points3D.txt"]
    cams, images, points = _parse(tmp_path)
    assert len(cams) == 5 and cams[0].split()[1] == "PINHOLE"
    assert images[1]["name"] == "img0.png"
    assert len(points) == len(np.unique(s.obs_point))
    for pid, p in points.items():
        for image_id, idx in p["track"]:
            back = images[image_id]["p2d"][idx][2]
            assert back == pid
    # every observation is listed once
    assert sum(len(p["track"]) for p in points.values()) == s.obs_image.size


def test_a_subset_of_images(tmp_path):
    _write(tmp_path, images=[0, 2, 3])
    cams, images, points = _parse(tmp_path)
    assert sorted(images) == [1, 3, 4] and len(cams) == 3
    assert all(i in (1, 3, 4) for p in points.values() for i, _ in p["track"])


def test_names_with_spaces_are_kept_in_the_binary_model(tmp_path):
    """COLMAP's text reader stops a name at its first space: such a name is never renamed, the
    model is written in the binary format, which holds it, with the same content."""
    s = make_scene(num_cameras=2, num_points=10, seed=3)
    with pytest.raises(ValueError, match="'kamera 13.png'.*text model cannot hold"):
        write_colmap_text(tmp_path / "refused", ["kamera 13.png", "b.png"], None,
                          [(640, 480)] * 2, s.K, [None] * 2, s.w2c, np.arange(2), s.uv,
                          s.points, s.obs_image, s.obs_kp, s.obs_point)
    assert not list((tmp_path / "refused").iterdir())
    _, files = _write(tmp_path / "auto", names="img {}.png", binary=None)
    assert [f.name for f in files] == ["cameras.bin", "images.bin", "points3D.bin"]
    _write(tmp_path / "text", names="img{}.png", binary=None)
    assert sorted(p.name for p in (tmp_path / "text").iterdir()) == [
        "cameras.txt", "images.txt", "points3D.txt"]
    cams_b, images_b, points_b = _parse_binary(tmp_path / "auto")
    assert [im["name"] for im in images_b.values()] == [f"img {i}.png" for i in range(5)]
    cams_t, images_t, points_t = _parse(tmp_path / "text")
    # the same cameras, poses, 2D points, points, colours, errors and tracks
    assert [(c[1], c[2], c[3]) for c in cams_b] == [
        (ln.split()[1], int(ln.split()[2]), int(ln.split()[3])) for ln in cams_t]
    assert [c[1] for c in cams_b] == ["PINHOLE", "OPENCV", "PINHOLE", "FULL_OPENCV", "PINHOLE"]
    for c, ln in zip(cams_b, cams_t, strict=True):
        np.testing.assert_allclose(c[4], [float(v) for v in ln.split()[4:]], rtol=1e-9)
    assert images_b.keys() == images_t.keys() and points_b.keys() == points_t.keys()
    for k, im in images_b.items():
        assert im["name"].replace(" ", "") == images_t[k]["name"]
        assert im["camera"] == images_t[k]["camera"] == k
        np.testing.assert_allclose(im["pose"], images_t[k]["pose"], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(im["p2d"], images_t[k]["p2d"], atol=1e-4)
    for k, p in points_b.items():
        np.testing.assert_allclose(p["xyz"], points_t[k]["xyz"], rtol=1e-8)
        assert p["rgb"] == points_t[k]["rgb"] and p["track"] == points_t[k]["track"]
        assert p["error"] == pytest.approx(points_t[k]["error"], rel=1e-5)


@pytest.mark.parametrize("binary", [False, True])
def test_pycolmap_reads_it(tmp_path, binary):
    pycolmap = pytest.importorskip("pycolmap")
    names = "img {}.png" if binary else "img{}.png"
    s, _ = _write(tmp_path, names=names, binary=binary)
    r = pycolmap.Reconstruction(str(tmp_path))
    assert r.num_images() == 5 and r.num_points3D() == len(np.unique(s.obs_point))
    assert r.compute_mean_reprojection_error() < 2.0  # synthetic noise 0.5 px
    img = r.images[2]
    assert np.allclose(img.cam_from_world().matrix(), s.w2c[1][:3], atol=1e-8)
    assert sorted(im.name for im in r.images.values()) == [names.format(i) for i in range(5)]
    assert r.cameras[4].model.name == "FULL_OPENCV"


def _record(n: int = 4, seed: int = 0) -> dict:
    """A poses.json ``cameras`` record: components 0 (3 cameras) and 1 (1), one unsolved."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    cams = {}
    for i in range(n):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * 0.3).as_matrix()
        T[:3, 3] = rng.normal(size=3)
        cams[f"{1305031102.1 + i:.6f}.png"] = {
            "solved": True, "component": 0 if i < 3 else 1, "camera_to_world": T.tolist(),
            "K": K.tolist(), "size": [640, 480], "dist": [0.1, -0.05] if i == 1 else None}
    cams["late.png"] = {"solved": False, "component": None, "camera_to_world": None,
                        "K": K.tolist(), "size": [640, 480], "dist": None}
    return cams


def test_nerfstudio_transforms_of_the_largest_component(tmp_path):
    import json

    from posernet.export import largest_component, write_nerfstudio

    cams = _record()
    assert largest_component(cams) == list(cams)[:3]
    images = tmp_path / "photos"
    path = write_nerfstudio(tmp_path / "out" / "transforms.json", cams, images)
    data = json.loads(path.read_text())
    assert data["camera_model"] == "OPENCV" and len(data["frames"]) == 3
    f0 = data["frames"][0]
    assert f0["file_path"] == "../photos/" + next(iter(cams))
    # OpenGL axes: the camera's viewing direction (+z in OpenCV) is -z of transform_matrix
    c2w = np.asarray(cams[next(iter(cams))]["camera_to_world"])
    M = np.asarray(f0["transform_matrix"])
    np.testing.assert_allclose(M[:3, 3], c2w[:3, 3])
    np.testing.assert_allclose(-M[:3, 2], c2w[:3, 2])
    np.testing.assert_allclose(-M[:3, 1], c2w[:3, 1])
    assert (f0["fl_x"], f0["fl_y"], f0["cx"], f0["cy"], f0["w"], f0["h"]) == (
        500.0, 510.0, 320.0, 240.0, 640, 480)
    assert data["frames"][1]["k1"] == 0.1 and data["frames"][1]["k2"] == -0.05
    with pytest.raises(ValueError, match="no solved camera"):
        write_nerfstudio(tmp_path / "t.json", {"a.png": cams["late.png"]}, images)


def test_tum_trajectory_round_trip(tmp_path):
    import torch

    from posernet.export import write_tum
    from posernet.geometry import pose_vec_to_matrix

    cams = _record()
    path = write_tum(tmp_path / "traj.txt", cams)
    rows = [ln.split() for ln in path.read_text().splitlines() if not ln.startswith("#")]
    assert len(rows) == 3
    names = list(cams)[:3]
    for row, name in zip(rows, names, strict=True):
        assert float(row[0]) == pytest.approx(float(name[:-4]))  # TUM timestamp from the name
        tx, ty, tz, qx, qy, qz, qw = map(float, row[1:])
        T = pose_vec_to_matrix(torch.tensor([qw, qx, qy, qz, tx, ty, tz], dtype=torch.float64))
        np.testing.assert_allclose(T.numpy(), np.asarray(cams[name]["camera_to_world"]),
                                   atol=1e-7)


def test_tum_header_names_the_image_of_every_row(tmp_path):
    """Rows stay the standard 8 columns; the header maps each row to its image by a quoted
    name, also for names with spaces (which a space-separated list could not tell apart)."""
    from posernet.export import read_tum_image_names, write_tum

    cams = {}
    for name, c in zip(["kamera 13.png", "kamera 2.png", "a b c.png", 'odd "q"\u2028.png'],
                       _record().values(), strict=False):
        cams[name] = {**c, "component": 0}
    path = write_tum(tmp_path / "traj.txt", cams)
    text = path.read_text()
    rows = [ln.split() for ln in text.split("\n") if ln and not ln.startswith("#")]
    assert all(len(r) == 8 for r in rows) and len(rows) == 4
    names = read_tum_image_names(path)
    assert names == sorted(cams)  # no TUM timestamps in the names: name order
    assert '# image 0.000000 "a b c.png"' in text.split("\n")
    for row, name in zip(rows, names, strict=True):
        c2w = np.asarray(cams[name]["camera_to_world"])
        np.testing.assert_allclose([float(v) for v in row[1:4]], c2w[:3, 3], atol=1e-7)


@pytest.mark.parametrize("workers", [1, 3])
def test_point_colours_are_the_pixels_under_each_first_observation(tmp_path, workers):
    """Each point takes the colour (RGB) under its first observation, whichever thread read
    that image; an image that cannot be read leaves its points grey."""
    import cv2

    from posernet.export import point_colours

    rng = np.random.default_rng(0)
    paths, uv = [], []
    for i in range(4):
        img = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
        paths.append(tmp_path / f"{i}.png")
        cv2.imwrite(str(paths[-1]), img)
        uv.append(rng.uniform(0, [29, 19], (6, 2)))
    paths[3] = tmp_path / "missing.png"
    obs_image = np.array([2, 0, 1, 3, 0, 2])
    obs_keypoint = np.array([1, 4, 0, 2, 3, 5])
    obs_point = np.array([0, 1, 2, 3, 0, 1])  # points 0 and 1 are seen twice: first wins
    got = point_colours(paths, uv, obs_image, obs_keypoint, obs_point, 5, workers=workers)
    for o in range(4):
        x, y = np.rint(uv[obs_image[o]][obs_keypoint[o]]).astype(int)
        i = obs_image[o]
        expect = [128] * 3 if i == 3 else cv2.imread(str(paths[i]))[y, x, ::-1]
        np.testing.assert_array_equal(got[obs_point[o]], expect)
    np.testing.assert_array_equal(got[4], [128] * 3)  # no observation
    # the image stage's keypoint colours (keypoint_colours) replace reading the files: images
    # 1 and 3 (missing) have them, 0 and 2 do not and are read
    from posernet.frontend.images import keypoint_colours

    known = [None, keypoint_colours(cv2.imread(str(paths[1])), uv[1]), None,
             rng.integers(0, 256, (6, 3), dtype=np.uint8)]
    cv2.imwrite(str(paths[1]), np.zeros((20, 30, 3), np.uint8))  # the file no longer agrees
    mixed = point_colours(paths, uv, obs_image, obs_keypoint, obs_point, 5, workers=workers,
                          keypoint_colours=known)
    np.testing.assert_array_equal(mixed[:3], got[:3])  # from the files (0, 2), known (1)
    np.testing.assert_array_equal(mixed[3], known[3][2])  # point 3: image 3, keypoint 2
    only = point_colours(None, uv, obs_image, obs_keypoint, obs_point, 5,
                         keypoint_colours=known)  # no paths: the rest stays grey
    np.testing.assert_array_equal(only[2], got[2])
    np.testing.assert_array_equal(only[0], [128] * 3)


def test_keypoint_colours_are_rgb_under_each_keypoint_of_colour_and_grey_images() -> None:
    from posernet.frontend.images import keypoint_colours

    bgr = np.zeros((4, 5, 3), np.uint8)
    bgr[1, 3] = (10, 20, 30)  # B, G, R at x=3, y=1
    uv = np.array([[2.6, 0.8], [-5.0, 9.0]])  # rounds to (3, 1); clipped to (0, 3)
    np.testing.assert_array_equal(keypoint_colours(bgr, uv), [[30, 20, 10], [0, 0, 0]])
    grey = np.arange(20, dtype=np.uint8).reshape(4, 5)
    np.testing.assert_array_equal(keypoint_colours(grey, uv), [[8, 8, 8], [15, 15, 15]])

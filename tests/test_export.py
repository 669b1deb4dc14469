"""COLMAP text export: camera models, ids and tracks consistent, readable by pycolmap."""

from __future__ import annotations

import numpy as np
import pytest

from posernet.export import colmap_camera, write_colmap_text
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


def _write(tmp_path, images=None):
    s = make_scene(num_cameras=5, num_points=80, seed=3)
    n = s.w2c.shape[0]
    images = np.arange(n) if images is None else np.asarray(images)
    files = write_colmap_text(tmp_path, [f"img {i}.png" for i in range(n)], None,
                              [(640, 480)] * n, s.K, [None] * n, s.w2c, images, s.uv,
                              s.points, s.obs_image, s.obs_kp, s.obs_point)
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
        images[int(f[0])] = {"pose": [float(v) for v in f[1:8]], "name": f[9],
                             "p2d": [(float(vals[k]), float(vals[k + 1]), int(vals[k + 2]))
                                     for k in range(0, len(vals), 3)]}
    points = {}
    for row in lines["points3D.txt"]:
        f = row.split()
        track = [(int(f[k]), int(f[k + 1])) for k in range(8, len(f), 2)]
        points[int(f[0])] = {"xyz": [float(v) for v in f[1:4]], "track": track}
    return lines["cameras.txt"], images, points


def test_tracks_point_back_at_their_observations(tmp_path):
    s, files = _write(tmp_path)
    assert [f.name for f in files] == ["cameras.txt", "images.txt", "points3D.txt"]
    cams, images, points = _parse(tmp_path)
    assert len(cams) == 5 and cams[0].split()[1] == "PINHOLE"
    assert images[1]["name"] == "img_0.png"  # no spaces in COLMAP names
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


def test_pycolmap_reads_it(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    s, _ = _write(tmp_path)
    r = pycolmap.Reconstruction(str(tmp_path))
    assert r.num_images() == 5 and r.num_points3D() == len(np.unique(s.obs_point))
    assert r.compute_mean_reprojection_error() < 2.0  # synthetic noise 0.5 px
    img = r.images[2]
    assert np.allclose(img.cam_from_world().matrix(), s.w2c[1][:3], atol=1e-8)

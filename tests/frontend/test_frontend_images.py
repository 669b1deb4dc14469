"""Image folders, intrinsics and pose files a user brings: good input and every bad one."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from posernet.frontend.images import (
    ImageError,
    list_images,
    parse_intrinsics,
    read_image,
    read_pose_file,
    records_for_images,
)
from posernet.frontend.relpose import five_point


def _write_images(folder, names, size=(40, 30)):
    folder.mkdir(parents=True, exist_ok=True)
    for n in names:
        cv2.imwrite(str(folder / n), np.full((size[1], size[0], 3), 128, np.uint8))


def test_list_images_skips_depth_maps_and_other_files(tmp_path):
    _write_images(tmp_path, ["frame-000000.color.png", "frame-000000.depth.png", "b.jpg"])
    (tmp_path / "notes.txt").write_text("x")
    names = [p.name for p in list_images(tmp_path)]
    assert names == ["b.jpg", "frame-000000.color.png"]
    assert [p.name for p in list_images(tmp_path, "*.color.png")] == ["frame-000000.color.png"]


def test_list_images_errors(tmp_path):
    with pytest.raises(ImageError, match="not found"):
        list_images(tmp_path / "nope")
    (tmp_path / "f.png").write_bytes(b"")
    with pytest.raises(ImageError, match="a file"):
        list_images(tmp_path / "f.png")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ImageError, match="no image files"):
        list_images(empty)


def test_read_image_errors(tmp_path):
    with pytest.raises(ImageError, match="image not found"):
        read_image(tmp_path / "missing.png")
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"not a png at all")
    with pytest.raises(ImageError, match="broken.png"):
        read_image(bad)
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    with pytest.raises(ImageError, match="empty.png"):
        read_image(empty)


def test_parse_intrinsics_forms(tmp_path):
    K = np.array([[500.0, 0, 320], [0, 510, 240], [0, 0, 1]])
    for spec in ("500,510,320,240", [500, 510, 320, 240], K.tolist(), "[500, 510, 320, 240]"):
        (K1, d), (K2, _) = parse_intrinsics(spec, ["a.png", "b.png"])
        assert np.allclose(K1, K) and np.allclose(K2, K) and d is None
    f = tmp_path / "k.txt"
    np.savetxt(f, K)
    assert np.allclose(parse_intrinsics(str(f), ["a"])[0][0], K)
    j = tmp_path / "cams.json"
    j.write_text(json.dumps({"default": {"fx": 500, "fy": 510, "cx": 320, "cy": 240},
                             "images": {"b.png": {"K": [[400, 0, 300], [0, 400, 200], [0, 0, 1]],
                                                  "dist": [0.1, -0.01]}}}))
    (Ka, da), (Kb, db) = parse_intrinsics(str(j), ["a.png", "sub/b.png"])
    assert np.allclose(Ka, K) and da is None
    assert Kb[0, 0] == 400 and db.tolist() == [0.1, -0.01]


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        ("500,510,320", "3 numbers|4 numbers"),
        ([500, 510, 320, 240, 1], "4 numbers"),
        ([[1, 0], [0, 1]], r"shape \(2, 2\)"),
        ("-5,500,320,240", "positive"),
        ("a,b,c,d", "4 numbers"),
        ([500, float("nan"), 320, 240], "numbers"),
        (None, "required"),
    ],
)
def test_parse_intrinsics_bad(spec, match):
    with pytest.raises(ImageError, match=match):
        parse_intrinsics(spec, ["a.png"])


def test_intrinsics_file_errors(tmp_path):
    with pytest.raises(ImageError, match="intrinsics file not found"):
        parse_intrinsics(str(tmp_path / "none.json"), ["a"])
    bad = tmp_path / "bad.json"
    bad.write_text("{nope")
    with pytest.raises(ImageError, match="bad.json.*malformed"):
        parse_intrinsics(str(bad), ["a"])
    per = tmp_path / "per.json"
    per.write_text(json.dumps({"images": {"x.png": {"fx": 1, "fy": 1, "cx": 0, "cy": 0}}}))
    with pytest.raises(ImageError, match="no intrinsics for image 'y.png'"):
        parse_intrinsics(str(per), ["y.png"])
    dist = tmp_path / "dist.json"
    dist.write_text(json.dumps({"fx": 1, "fy": 1, "cx": 0, "cy": 0, "dist": [1, 2, 3]}))
    with pytest.raises(ImageError, match="dist"):
        parse_intrinsics(str(dist), ["a"])


def test_pose_files(tmp_path):
    good = tmp_path / "frame-000000.pose.txt"
    T = np.eye(4)
    T[:3, 3] = [1, 2, 3]
    np.savetxt(good, T + 1e-5 * np.eye(4) * np.array([1, 1, 1, 0]))  # slightly non-rigid
    P = read_pose_file(good)
    assert np.allclose(P, T, atol=1e-4)
    assert np.allclose(P[:3, :3] @ P[:3, :3].T, np.eye(3), atol=1e-12)
    three = tmp_path / "three.pose.txt"
    np.savetxt(three, np.eye(3))
    with pytest.raises(ImageError, match=r"three.pose.txt is not a 4x4 matrix.*3 rows"):
        read_pose_file(three)
    skew = tmp_path / "skew.pose.txt"
    S = np.eye(4)
    S[0, 1] = 0.5
    np.savetxt(skew, S)
    with pytest.raises(ImageError, match="skew.pose.txt is not a rigid"):
        read_pose_file(skew)
    text = tmp_path / "text.pose.txt"
    text.write_text("a b c d\n" * 4)
    with pytest.raises(ImageError, match="text.pose.txt"):
        read_pose_file(text)


def test_records_pick_up_pose_files_only_when_complete(tmp_path):
    _write_images(tmp_path, ["frame-000000.color.png", "frame-000001.color.png"])
    np.savetxt(tmp_path / "frame-000000.pose.txt", np.eye(4))
    recs = records_for_images(tmp_path, "100,100,20,15")
    assert all(r.c2w is None for r in recs)  # one missing: no ground truth at all
    np.savetxt(tmp_path / "frame-000001.pose.txt", np.eye(4))
    recs = records_for_images(tmp_path, "100,100,20,15")
    assert all(r.c2w is not None for r in recs)
    assert [r.key for r in recs] == ["frame-000000.color.png", "frame-000001.color.png"]
    assert all(r.c2w is None for r in records_for_images(tmp_path, "100,100,20,15", None, "none"))
    with pytest.raises(ImageError, match="gt_poses folder not found"):
        records_for_images(tmp_path, "100,100,20,15", gt_poses=str(tmp_path / "nope"))


def _project(K, R, t, X):
    x = (R @ X.T).T + t
    uv = (K @ x.T).T
    return uv[:, :2] / uv[:, 2:]


def test_five_point_with_two_intrinsics_and_distortion():
    rng = np.random.default_rng(1)
    X = rng.uniform([-1, -1, 3], [1, 1, 5], (200, 3))
    K1 = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    K2 = np.array([[700.0, 0, 300], [0, 690, 250], [0, 0, 1]])
    a = np.deg2rad(8.0)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    t = np.array([-0.5, 0.05, 0.1])
    p1 = _project(K1, np.eye(3), np.zeros(3), X)
    p2 = _project(K2, R, t, X)
    dist2 = np.array([0.08, 0.0, 0.0, 0.0, 0.0])
    # distort image 2's points with OpenCV's model: project through cv2.projectPoints
    rvec, _ = cv2.Rodrigues(R)
    p2d = cv2.projectPoints(X, rvec, t, K2, dist2)[0].reshape(-1, 2)
    est = five_point(p1, p2, K1, K2=K2, threshold=0.5)
    assert est is not None
    R_est, t_est = est
    assert np.degrees(np.arccos(np.clip((np.trace(R_est @ R.T) - 1) / 2, -1, 1))) < 0.1
    assert np.dot(t_est, t / np.linalg.norm(t)) > 0.999
    # ignoring the distortion biases the pose; passing it recovers it
    est_d = five_point(p1, p2d, K1, K2=K2, dist2=dist2, threshold=0.5)
    assert est_d is not None
    assert np.degrees(np.arccos(np.clip((np.trace(est_d[0] @ R.T) - 1) / 2, -1, 1))) < 0.1
    assert np.dot(est_d[1], t / np.linalg.norm(t)) > 0.999
    with pytest.raises(ValueError, match="unknown 5-point method"):
        five_point(p1, p2, K1, method="magic")


def test_guessed_intrinsics_from_exif_or_the_prior(tmp_path):
    from PIL import Image

    from posernet.frontend.images import FOCAL_PRIOR, guess_intrinsics

    im = Image.fromarray(np.zeros((300, 400, 3), np.uint8))
    ex = Image.Exif()
    ex.get_ifd(0x8769)[0xA405] = 28  # 35 mm equivalent focal length
    im.save(tmp_path / "f35.jpg", exif=ex)
    K, src = guess_intrinsics(tmp_path / "f35.jpg")
    assert src == "exif" and np.isclose(K[0, 0], 28 / 36 * 400) and K[0, 2] == 200
    ex = Image.Exif()
    ex[0x0112] = 6  # stored sideways: OpenCV reads it 300 wide, 400 high
    ex.get_ifd(0x8769)[0x920A] = 4.0  # mm
    ex.get_ifd(0x8769)[0xA20E] = 250.0  # pixels per mm on the focal plane
    ex.get_ifd(0x8769)[0xA210] = 4  # unit: mm
    im.save(tmp_path / "plane.jpg", exif=ex)
    K, src = guess_intrinsics(tmp_path / "plane.jpg")
    assert src == "exif" and np.isclose(K[0, 0], 1000.0) and (K[0, 2], K[1, 2]) == (150, 200)
    im.save(tmp_path / "plain.png")
    K, src = guess_intrinsics(tmp_path / "plain.png")
    assert src == "prior" and np.isclose(K[1, 1], FOCAL_PRIOR * 400)
    (tmp_path / "bad.jpg").write_bytes(b"not an image")
    with pytest.raises(ImageError, match="bad.jpg"):
        guess_intrinsics(tmp_path / "bad.jpg")
    records = records_for_images(tmp_path, "auto", pattern="*.png")
    assert [r.intrinsics_source for r in records] == ["prior"]


@pytest.mark.parametrize("workers", [1, 3])
def test_unusable_images_are_named_or_skipped(tmp_path, workers):
    """The same verdicts, in file order, whether the files are checked on one thread or
    several."""
    from functools import partial

    from posernet.frontend.images import image_problem
    from posernet.frontend.images import records_for_images as plain

    records_for_images = partial(plain, workers=workers)

    good = np.full((32, 48, 3), 128, np.uint8)
    good[8:24, 8:40] = 30
    cv2.imwrite(str(tmp_path / "a.png"), good)
    cv2.imwrite(str(tmp_path / "b.jpg"), good)
    (tmp_path / "c.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    (tmp_path / "d.jpg").write_bytes(b"")
    assert image_problem(tmp_path / "a.png") is None and image_problem(tmp_path / "b.jpg") is None
    assert image_problem(tmp_path / "c.png") == "not an image file OpenCV can decode"
    assert image_problem(tmp_path / "d.jpg") == "empty file"
    with pytest.raises(ImageError, match=r"2 unusable image\(s\).*c\.png.*d\.jpg"):
        records_for_images(tmp_path, "50,50,24,16", gt_poses="none")
    skipped: list = []
    recs = records_for_images(tmp_path, "50,50,24,16", gt_poses="none", skipped=skipped)
    assert [r.key for r in recs] == ["a.png", "b.jpg"]
    assert skipped == [("c.png", "not an image file OpenCV can decode"), ("d.jpg", "empty file")]


def test_ground_truth_from_a_tum_trajectory_or_a_colmap_model(tmp_path):
    from posernet.export import write_colmap_text, write_tum
    from posernet.frontend.images import read_colmap_images, read_tum_trajectory
    from posernet.sfm.synthetic import make_scene

    sc = make_scene(num_cameras=4, num_points=60, seed=2)
    c2w = np.linalg.inv(sc.w2c)
    imgs = tmp_path / "rgb"
    imgs.mkdir()
    img = np.full((32, 48, 3), 90, np.uint8)
    img[4:20, 6:30] = 200
    names = [f"{1305031102.1 + 0.5 * i:.6f}.png" for i in range(4)]
    for n in names:
        cv2.imwrite(str(imgs / n), img)
    # TUM trajectory (written by our exporter, read back) with the stamps 5 ms off
    cams = {f"{1305031102.1 + 0.5 * i + 0.005:.6f}.png": {
        "solved": True, "component": 0, "camera_to_world": c2w[i].tolist()} for i in range(4)}
    traj = write_tum(tmp_path / "groundtruth.txt", cams)
    t, poses = read_tum_trajectory(traj)
    assert np.all(np.diff(t) > 0)
    np.testing.assert_allclose(poses, c2w, atol=1e-7)
    recs = records_for_images(imgs, "50,50,24,16", gt_poses=str(traj))
    np.testing.assert_allclose(np.stack([r.c2w for r in recs]), c2w, atol=1e-7)
    # an image 1 s away from every ground-truth pose: named
    cv2.imwrite(str(imgs / "1305031110.000000.png"), img)
    with pytest.raises(ImageError, match=r"no pose within 20 ms of 1 image.*1305031110"):
        records_for_images(imgs, "50,50,24,16", gt_poses=str(traj))
    (imgs / "1305031110.000000.png").unlink()
    # a malformed line is named
    bad = tmp_path / "bad.txt"
    bad.write_text("# header\n1305031102.1 1 2 3 0 0 0\n")
    with pytest.raises(ImageError, match="line 2"):
        read_tum_trajectory(bad)
    # COLMAP text model as ground truth, matched by name
    model = tmp_path / "model"
    write_colmap_text(model, names, None, [(48, 32)] * 4, sc.K, [None] * 4, sc.w2c,
                      np.arange(4), sc.uv, sc.points, sc.obs_image, sc.obs_kp, sc.obs_point)
    got = read_colmap_images(model)
    np.testing.assert_allclose(np.stack([got[n] for n in names]), c2w, atol=1e-6)
    recs = records_for_images(imgs, "50,50,24,16", gt_poses=str(model))
    np.testing.assert_allclose(np.stack([r.c2w for r in recs]), c2w, atol=1e-6)


def test_ground_truth_from_a_colmap_model_with_spaces_in_names(tmp_path):
    """Our binary model (written for names with spaces) and COLMAP's own text model, which
    writes such names unchanged at the end of the line, are both read back by the real name."""
    from posernet.export import write_colmap_model
    from posernet.frontend.images import read_colmap_images
    from posernet.sfm.synthetic import make_scene

    sc = make_scene(num_cameras=4, num_points=60, seed=2)
    c2w = np.linalg.inv(sc.w2c)
    imgs = tmp_path / "photos"
    imgs.mkdir()
    img = np.full((32, 48, 3), 90, np.uint8)
    img[4:20, 6:30] = 200
    names = [f"kamera {i}.png" for i in range(4)]
    for n in names:
        cv2.imwrite(str(imgs / n), img)
    model = tmp_path / "model"
    files = write_colmap_model(model, names, None, [(48, 32)] * 4, sc.K, [None] * 4, sc.w2c,
                               np.arange(4), sc.uv, sc.points, sc.obs_image, sc.obs_kp,
                               sc.obs_point)
    assert files[1].name == "images.bin"
    for src in (model, model / "images.bin"):
        got = read_colmap_images(src)
        assert sorted(got) == names
        np.testing.assert_allclose(np.stack([got[n] for n in names]), c2w, atol=1e-6)
    recs = records_for_images(imgs, "50,50,24,16", gt_poses=str(model))
    np.testing.assert_allclose(np.stack([r.c2w for r in recs]), c2w, atol=1e-6)
    text = tmp_path / "images.txt"
    text.write_text("# COLMAP\n1 1 0 0 0 0.5 0 0 1 kamera 0.png\n\n")
    assert list(read_colmap_images(text)) == ["kamera 0.png"]
    (model / "images.bin").write_bytes(b"\x02\0\0")
    with pytest.raises(ImageError, match="not a readable binary images file"):
        read_colmap_images(model)


def test_given_intrinsics_must_fit_the_images(tmp_path):
    from posernet.frontend.images import image_size

    img = np.full((48, 64, 3), 90, np.uint8)
    img[8:30, 10:40] = 200
    cv2.imwrite(str(tmp_path / "a.png"), img)
    cv2.imwrite(str(tmp_path / "b.jpg"), img)
    assert image_size(tmp_path / "a.png") == (64, 48) == image_size(tmp_path / "b.jpg")
    assert records_for_images(tmp_path, "60,60,32,24", gt_poses="none")  # fits
    with pytest.raises(ImageError, match=r"a\.png: principal point \(320, 240\) lies outside "
                                         r"the 64x48 image"):
        records_for_images(tmp_path, "60,60,320,240", gt_poses="none")
    with pytest.raises(ImageError, match="fx=0.5 px is implausible for a 64x48 image"):
        records_for_images(tmp_path, "0.5,0.5,32,24", gt_poses="none")
    spec = tmp_path / "k.json"
    spec.write_text(json.dumps({"default": {"fx": 60, "fy": 60, "cx": 32, "cy": 24},
                                "images": {"a.png": {"fx": 61, "fy": 61, "cx": 32, "cy": 24},
                                           "zz.png": {"fx": 1, "fy": 1, "cx": 1, "cy": 1}}}))
    with pytest.raises(ImageError, match="not among the images: zz.png"):
        records_for_images(tmp_path, str(spec), gt_poses="none")
    # one shared K for images of different sizes
    cv2.imwrite(str(tmp_path / "c.png"), cv2.resize(img, (128, 96)))
    with pytest.raises(ImageError, match="one camera matrix for images of 2 sizes"):
        records_for_images(tmp_path, "60,60,32,24", gt_poses="none")
    assert len(records_for_images(tmp_path, "auto", gt_poses="none")) == 3  # guessed per image

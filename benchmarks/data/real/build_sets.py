"""Rebuild the real image sets in this folder from their raw sources (see each SOURCE.md).

Not run by tests; kept so the conversions are reproducible. Raw inputs are expected under
``--raw`` (default /tmp/raw): ``dino/`` (Middlebury dinoSparseRing), ``hj/`` and
``fountain/``, ``entry/`` (Strecha Herz-Jesu-P25 / fountain-P11 / entry-P10 images +
``.camera`` files as in openMVG/SfM_quality_evaluation), ``7s/`` (the 7-Scenes frames of
andyzeng/tsdf-fusion-python ``data/``), ``squirrel/`` (``image_N.jpg`` + ``viff.xml`` of
xocoatzin/Voxel-Carving ``assets/``: a glazed ceramic squirrel on a turntable).

Derived sparse sets (the trust benchmark's hard cases; same raw inputs, same conversions):
``herzjesu_every3`` / ``fountain_every3`` / ``entry_every3`` keep every third view of the
full Strecha set (views 0, 3, 6, ...: a chain of far-apart views); ``dino_far8`` and
``herzjesu_far8`` keep 8 views chosen far apart by greedy farthest-point sampling on the
viewing direction (:func:`farthest_views`, starting from the first view). The turntable
squirrel: ``squirrel`` (all 36 views, 10 deg apart) and ``squirrel_far8``, also at the
camera's full 1280x960 (``squirrel_far8_full``). ``dtu24_far8``: 8 views far apart of DTU MVS
scan24 at 1600x1200 (``dtu/scan24/``: ``images/`` and ``cameras_sphere.npz`` of
wqrray/nerf_baseline ``data/dtu_scan24/``); ``dtu97_far8`` the same of scan97 (tuna cans and
food packets; jiangsijia9495/CQ-NIR ``public_data/dtu_scan97/``), ``dtu69_far8`` and
``dtu106_far8`` of scan69 (ceramic snowmen) and scan106 (stone pigeons) from the same
repository, ``dtu65_far8`` of scan65 (tuanduy161202/NeuS_Test
``NeuS/public_data/dtu_scan65/``). ``trust`` builds all thirteen.
``7scenes_wide``: 100 frames equally spaced in path length over all 1000 frames, the pool of the
wide-baseline pairs benchmark (``bench_real.py --pairs``).

    python benchmarks/data/real/build_sets.py dino herzjesu fountain entry 7scenes
    python benchmarks/data/real/build_sets.py trust
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent


def write_pose(path: Path, c2w: np.ndarray) -> None:
    path.write_text("\n".join(" ".join(f"{v:.9f}" for v in row) for row in c2w) + "\n")


def write_jpeg(path: Path, img: np.ndarray, quality: int = 90) -> None:
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    path.write_bytes(buf.tobytes())


def write_intrinsics(out: Path, K: np.ndarray, dist=None) -> None:
    d = {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2])}
    if dist is not None:
        d["dist"] = [float(x) for x in dist]
    (out / "intrinsics.json").write_text(json.dumps(d, indent=2) + "\n")


def clean(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for p in out.iterdir():
        if p.suffix in (".jpg", ".png") or p.name.endswith(".pose.txt") \
                or p.name == "intrinsics.json":
            p.unlink()


def farthest_views(c2w: list[np.ndarray], k: int, first: int = 0) -> list[int]:
    """Indices (sorted) of ``k`` views chosen far apart: greedy farthest-point sampling on the
    viewing direction (camera z axis in the world, ``c2w[:3, 2]``) by angle, starting from view
    ``first``; ties go to the lower index."""
    d = np.array([T[:3, 2] / np.linalg.norm(T[:3, 2]) for T in c2w])
    sel = [first]
    gap = np.arccos(np.clip(d @ d[first], -1, 1))
    while len(sel) < min(k, len(d)):
        i = int(np.argmax(gap))
        sel.append(i)
        gap = np.minimum(gap, np.arccos(np.clip(d @ d[i], -1, 1)))
    return sorted(sel)


def build_dino(raw: Path, name: str = "middlebury_dino_sparse_ring",
               far: int = 0) -> None:
    """Middlebury dinoSparseRing: x = K [R | t] X  (world-to-camera) -> c2w = [R^T | -R^T t].
    ``far > 0``: only that many views, chosen by :func:`farthest_views`."""
    src = raw / "dino"
    out = HERE / name
    clean(out)
    lines = (src / "dinoSR_par.txt").read_text().split("\n")
    n = int(lines[0])
    Ks, views = [], []
    for line in lines[1 : n + 1]:
        tok = line.split()
        vals = np.array([float(x) for x in tok[1:]])
        K, R, t = vals[:9].reshape(3, 3), vals[9:18].reshape(3, 3), vals[18:21]
        Ks.append(K)
        c2w = np.eye(4)
        c2w[:3, :3] = R.T
        c2w[:3, 3] = -R.T @ t
        views.append((tok[0], c2w))
    keep = farthest_views([T for _, T in views], far) if far else range(len(views))
    for i in keep:
        fname, c2w = views[i]
        stem = Path(fname).stem
        img = cv2.imread(str(src / fname), cv2.IMREAD_COLOR)
        write_jpeg(out / f"{stem}.jpg", img, 92)
        write_pose(out / f"{stem}.pose.txt", c2w)
    assert all(np.allclose(K, Ks[0]) for K in Ks), "per-image K differ"
    write_intrinsics(out, Ks[0])


def read_strecha_camera(path: Path):
    """Strecha ``.camera``: K (3 rows), distortion row, R (3 rows), t (1 row), W H.

    Projection is P = K [R^T | -R^T t]: R is the camera-to-world rotation and t the camera
    centre in world coordinates (metres), i.e. c2w = [R | t].
    """
    rows = [list(map(float, r.split())) for r in path.read_text().splitlines() if r.strip()]
    K = np.array(rows[0:3])
    R = np.array(rows[4:7])
    t = np.array(rows[7])
    W, H = int(rows[8][0]), int(rows[8][1])
    return K, R, t, (W, H)


def build_strecha(raw: Path, sub: str, name: str, n_keep: int = 20, scale: int = 4,
                  step: int = 0, far: int = 0) -> None:
    """Strecha et al. 2008 set: every ``len/n_keep``-th image (``step > 0``: every
    ``step``-th, from the first; ``far > 0``: that many views by :func:`farthest_views`),
    downscaled by ``scale``."""
    src = raw / sub
    out = HERE / name
    clean(out)
    cams = sorted(src.glob("*.jpg.camera"))
    if step:
        idx = list(range(0, len(cams), step))
    elif far:
        c2w = []
        for cam in cams:
            _, R, t, _ = read_strecha_camera(cam)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t
            c2w.append(T)
        idx = farthest_views(c2w, far)
    else:
        idx = sorted(set(np.round(np.linspace(0, len(cams) - 1, n_keep)).astype(int).tolist()))
    K0 = None
    for i in idx:
        cam = cams[i]
        K, R, t, (W, H) = read_strecha_camera(cam)
        img = cv2.imread(str(src / cam.name.replace(".camera", "")), cv2.IMREAD_COLOR)
        assert img.shape[1] == W and img.shape[0] == H
        small = cv2.resize(img, (W // scale, H // scale), interpolation=cv2.INTER_AREA)
        Ks = K.copy()
        Ks[0, 0] /= scale
        Ks[1, 1] /= scale
        Ks[0, 2] = (K[0, 2] + 0.5) / scale - 0.5
        Ks[1, 2] = (K[1, 2] + 0.5) / scale - 0.5
        if K0 is None:
            K0 = Ks
        assert np.allclose(K0, Ks)
        c2w = np.eye(4)
        c2w[:3, :3] = R
        c2w[:3, 3] = t
        stem = cam.name.split(".")[0]
        write_jpeg(out / f"{stem}.jpg", small, 90)
        write_pose(out / f"{stem}.pose.txt", c2w)
    write_intrinsics(out, K0)


def quat_to_R(q):
    x, y, z, w = q
    n = np.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def arc_length_pick(pos: np.ndarray, n_keep: int) -> list[int]:
    """Indices of ``n_keep`` frames equally spaced in path length along positions ``pos``."""
    arc = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    return [int(np.argmin(np.abs(arc - a))) for a in np.linspace(0, arc[-1], n_keep)]


def build_7scenes(raw: Path, first: int = 0, last: int = 500, n_keep: int = 20,
                  K=(525.0, 525.0, 320.0, 240.0), name: str = "7scenes_redkitchen") -> None:
    """7-Scenes frames (as shipped in andyzeng/tsdf-fusion-python/data): poses already c2w."""
    src = raw / "7s"
    out = HERE / name
    clean(out)
    ids = list(range(first, last))
    pos = np.array([np.loadtxt(src / f"frame-{i:06d}.pose.txt")[:3, 3] for i in ids])
    for k in arc_length_pick(pos, n_keep):
        i = ids[k]
        c2w = np.loadtxt(src / f"frame-{i:06d}.pose.txt")
        # the source JPEGs (640x480) are copied byte for byte: no second lossy encoding
        shutil.copyfile(src / f"frame-{i:06d}.color.jpg", out / f"frame-{i:06d}.color.jpg")
        write_pose(out / f"frame-{i:06d}.pose.txt", c2w)
    write_intrinsics(out, np.array([[K[0], 0, K[2]], [0, K[1], K[3]], [0, 0, 1.0]]))


def build_squirrel(raw: Path, name: str = "squirrel_turntable", far: int = 0,
                   scale: int = 2) -> None:
    """Turntable squirrel of xocoatzin/Voxel-Carving: ``viff.xml`` holds per view a 3x4
    projection ``P = K [R | t]`` (world to image, OpenCV axes): decomposed, c2w = [R^T | C].
    Images renamed ``squirrel_NNN`` (zero-padded: name order = ring order), downscaled by
    ``scale``; ``far > 0``: that many views by :func:`farthest_views`."""
    src = raw / "squirrel"
    out = HERE / name
    clean(out)
    fs = cv2.FileStorage(str(src / "viff.xml"), cv2.FILE_STORAGE_READ)
    views, K0 = [], None
    centre = np.array([0.70, 0.95, -0.75])  # the object's box centre in the world
    for i in range(36):
        P = fs.getNode(f"viff{i:03d}_matrix").mat().astype(np.float64)
        K, R, Ch = cv2.decomposeProjectionMatrix(P)[:3]
        K = K / K[2, 2]
        C = Ch[:3, 0] / Ch[3, 0]
        assert np.linalg.det(R) > 0 and (R @ (centre - C))[2] > 0, "camera faces away"
        assert K0 is None or np.allclose(K, K0, atol=1e-3), "per-view K differ"
        K0 = K
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = R.T, C
        views.append(c2w)
    fs.release()
    keep = farthest_views(views, far) if far else range(len(views))
    for i in keep:
        img = cv2.imread(str(src / f"image_{i}.jpg"), cv2.IMREAD_COLOR)
        H, W = img.shape[:2]
        small = cv2.resize(img, (W // scale, H // scale), interpolation=cv2.INTER_AREA)
        write_jpeg(out / f"squirrel_{i:03d}.jpg", small, 90)
        write_pose(out / f"squirrel_{i:03d}.pose.txt", views[i])
    Ks = K0.copy()
    Ks[0, 1] = 0.0
    Ks[:2, :2] /= scale
    Ks[:2, 2] = (K0[:2, 2] + 0.5) / scale - 0.5
    write_intrinsics(out, Ks)


def _decompose(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, c2w) of a 3x4 projection P = K [R | t] (known up to scale): c2w = [R^T | C]."""
    if np.linalg.det(P[:, :3]) < 0:
        P = -P
    K, R, Ch = cv2.decomposeProjectionMatrix(P)[:3]
    S = np.diag(np.sign(np.diag(K)))  # negative diagonal entries of K folded into R
    K, R = K @ S, S @ R
    K = K / K[2, 2]
    assert np.linalg.det(R) > 0
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = R.T, (Ch[:3] / Ch[3]).ravel()
    return K, c2w


def build_dtu(raw: Path, scan: str = "scan24", far: int = 8) -> None:
    """A DTU MVS scan in the IDR / NeuS layout (``images/000000.png ...``, rectified
    1600x1200, and ``cameras_sphere.npz`` with ``world_mat_i`` = K [R | t] in the DTU frame,
    millimetres): ``far`` views by :func:`farthest_views`, full size, named ``rect_NNN`` by
    their 1-based DTU view number. The scale_mat is not applied (metric poses)."""
    src = raw / "dtu" / scan
    out = HERE / f"dtu_{scan}_far{far}"
    clean(out)
    cams = np.load(src / "cameras_sphere.npz")
    files = sorted((src / "images").glob("*.png"))
    centre = cams["scale_mat_0"][:3, 3]  # the object's centre
    Ks, views = [], []
    for i in range(len(files)):
        K, c2w = _decompose(cams[f"world_mat_{i}"][:3, :4].astype(np.float64))
        w2c = np.linalg.inv(c2w)
        assert (w2c[:3, :3] @ centre + w2c[:3, 3])[2] > 0, f"view {i} faces away"
        Ks.append(K)
        views.append(c2w)
    keep = farthest_views(views, far)
    assert all(np.allclose(Ks[i], Ks[keep[0]], atol=0.5) for i in keep), "per-view K differ"
    for i in keep:
        img = cv2.imread(str(files[i]), cv2.IMREAD_COLOR)
        write_jpeg(out / f"rect_{i + 1:03d}.jpg", img, 92)
        write_pose(out / f"rect_{i + 1:03d}.pose.txt", views[i])
    write_intrinsics(out, np.mean([Ks[i] for i in keep], axis=0))


TRUST = ("herzjesu_every3", "fountain_every3", "entry_every3", "dino_far8", "herzjesu_far8",
         "squirrel", "squirrel_far8", "squirrel_far8_full", "dtu24_far8", "dtu97_far8",
         "dtu69_far8", "dtu106_far8", "dtu65_far8")


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("sets", nargs="+")
    ap.add_argument("--raw", default="/tmp/raw", type=Path)
    a = ap.parse_args()
    for s in [x for t in a.sets for x in (TRUST if t == "trust" else (t,))]:
        if s == "dino":
            build_dino(a.raw)
        elif s == "herzjesu":
            build_strecha(a.raw, "hj", "strecha_herzjesu_p25")
        elif s == "fountain":
            build_strecha(a.raw, "fountain", "strecha_fountain_p11", n_keep=11)
        elif s == "entry":
            build_strecha(a.raw, "entry", "strecha_entry_p10", n_keep=10)
        elif s == "7scenes":
            build_7scenes(a.raw)
        elif s == "7scenes_wide":  # the pairs benchmark's pool: 100 frames of the whole path
            build_7scenes(a.raw, last=1000, n_keep=100, name="7scenes_redkitchen_wide")
        elif s == "herzjesu_every3":
            build_strecha(a.raw, "hj", "strecha_herzjesu_p25_every3", step=3)
        elif s == "fountain_every3":
            build_strecha(a.raw, "fountain", "strecha_fountain_p11_every3", step=3)
        elif s == "entry_every3":
            build_strecha(a.raw, "entry", "strecha_entry_p10_every3", step=3)
        elif s == "dino_far8":
            build_dino(a.raw, "middlebury_dino_sparse_ring_far8", far=8)
        elif s == "herzjesu_far8":
            build_strecha(a.raw, "hj", "strecha_herzjesu_p25_far8", far=8)
        elif s == "squirrel":
            build_squirrel(a.raw)
        elif s == "squirrel_far8":
            build_squirrel(a.raw, "squirrel_turntable_far8", far=8)
        elif s == "squirrel_far8_full":  # the same views at the camera's own 1280x960
            build_squirrel(a.raw, "squirrel_turntable_far8_full", far=8, scale=1)
        elif s in ("dtu24_far8", "dtu97_far8", "dtu69_far8", "dtu106_far8", "dtu65_far8"):
            build_dtu(a.raw, f"scan{s[3:].split('_')[0]}", far=8)
        else:
            raise SystemExit(f"unknown set {s}")

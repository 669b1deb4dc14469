"""A reconstruction in the formats other tools read: a COLMAP sparse model, nerfstudio's
``transforms.json`` and a TUM RGB-D trajectory (for evo and the TUM / ETH3D evaluation tools).

COLMAP:

``cameras.txt``, ``images.txt`` and ``points3D.txt`` (COLMAP's documented text model) hold the
bundle-adjusted cameras and the triangulated points: multi-view stereo, Gaussian splatting and
NeRF tool chains read such a model, as do COLMAP and pycolmap. One camera per image (PINHOLE,
or OPENCV / FULL_OPENCV with the image's distortion); ``images.txt`` lists, per image, the
keypoints that observe a point (``POINT2D_IDX`` counts within that list); ids start at 1.
Poses are COLMAP's world-to-camera (quaternion ``w x y z``, translation), the same frame as
``poses.json`` (the component's first camera at the identity); the scale is the
reconstruction's (arbitrary).

Image names are written as they are (the image's path relative to the image folder), so that
tools find the image files by name. COLMAP's text reader takes an image's ``NAME`` as one
whitespace-delimited token (``kamera 13.png`` would be read back as ``kamera``), and the text
format has no quoting; a model with such a name is therefore written in COLMAP's binary format
(``cameras.bin``, ``images.bin``, ``points3D.bin``: the same content, names NUL-terminated),
which COLMAP and pycolmap read as well (it is COLMAP's own default output format;
:func:`write_colmap_model`).

nerfstudio (:func:`write_nerfstudio`) and TUM (:func:`write_tum`) are written from a
``poses.json`` record (its ``cameras``: ``camera_to_world``, ``K``, ``size``, ``dist``,
``component``) and hold the largest component only: both formats describe one coordinate frame,
and separate components have unrelated frames and scales.
"""

from __future__ import annotations

import json
import os
import struct
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from .frontend.images import keypoint_colours as pixels_under
from .geometry import matrix_to_pose_vec
from .io import atomic_write_bytes, atomic_write_text

__all__ = ["colmap_camera", "colmap_text_name_ok", "largest_component", "point_colours",
           "read_tum_image_names", "write_colmap_binary", "write_colmap_model",
           "write_colmap_text", "write_nerfstudio", "write_tum"]

#: COLMAP's camera model ids (``CameraModelId`` in its ``sensor/models.h``), for the binary model
_COLMAP_MODEL_ID = {"PINHOLE": 1, "OPENCV": 4, "FULL_OPENCV": 6}
#: what COLMAP's text reader (``std::istream >> name``) stops a name at
_TEXT_SPACE = " \t\n\r\v\f"

#: OpenCV camera axes (x right, y down, z forward) -> OpenGL / nerfstudio (x right, y up, z back)
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def colmap_camera(K: np.ndarray, dist: np.ndarray | None) -> tuple[str, list[float]]:
    """COLMAP camera model name and parameters for intrinsics ``K (3, 3)`` and OpenCV
    distortion ``dist`` (``k1, k2, p1, p2[, k3[, k4, k5, k6]]``) or ``None``."""
    f = [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]
    d = np.zeros(0) if dist is None else np.asarray(dist, np.float64).reshape(-1)
    if not d.size or not np.any(d):
        return "PINHOLE", f
    if d.size > 8:
        raise ValueError(f"distortion with {d.size} coefficients has no COLMAP camera model "
                         "(at most k1, k2, p1, p2, k3, k4, k5, k6)")
    if d.size <= 4:
        return "OPENCV", f + list(np.pad(d, (0, 4 - d.size)))
    return "FULL_OPENCV", f + list(np.pad(d, (0, 8 - d.size)))


def point_colours(image_paths: Sequence[str | os.PathLike[str]] | None,
                  uv: Sequence[np.ndarray], obs_image: np.ndarray, obs_keypoint: np.ndarray,
                  obs_point: np.ndarray, num_points: int, workers: int = 1,
                  keypoint_colours: Sequence[np.ndarray | None] | None = None) -> np.ndarray:
    """RGB colour ``(P, 3)`` int64 of each point: the pixel under its first observation
    (``obs_* (O,)`` as in :func:`write_colmap_text`). ``keypoint_colours[i] (K_i, 3)``: image
    ``i``'s keypoint colours from the image stage (``None``, or an image without them: the
    image is read once, on ``workers`` threads); grey where neither gives one (no colours,
    ``image_paths`` None or the image unreadable)."""
    colour = np.full((num_points, 3), 128, np.int64)
    if not len(obs_point) or (image_paths is None and keypoint_colours is None):
        return colour
    is_first = np.zeros(obs_point.size, bool)  # one observation per point gives its colour
    is_first[np.unique(obs_point, return_index=True)[1]] = True
    first = np.flatnonzero(is_first)
    order = first[np.argsort(obs_image[first], kind="stable")]
    ims, starts = np.unique(obs_image[order], return_index=True)
    groups = np.split(order, starts[1:])

    def known(i: int) -> np.ndarray | None:
        return None if keypoint_colours is None else keypoint_colours[i]

    def sample(i: int, sel: np.ndarray) -> np.ndarray | None:
        kc = known(i)
        if kc is not None:
            return np.asarray(kc)[obs_keypoint[sel]]
        if image_paths is None:
            return None
        img = cv2.imread(str(image_paths[i]), cv2.IMREAD_COLOR)
        return None if img is None else pixels_under(img, uv[i][obs_keypoint[sel]])

    reads = sum(known(i) is None for i in ims.tolist())
    if workers > 1 and reads > 1:  # decoding releases the GIL
        with ThreadPoolExecutor(min(workers, reads)) as pool:
            rgbs = list(pool.map(sample, ims.tolist(), groups))
    else:
        rgbs = [sample(i, sel) for i, sel in zip(ims.tolist(), groups, strict=True)]
    for sel, rgb in zip(groups, rgbs, strict=True):
        if rgb is not None:
            colour[obs_point[sel]] = rgb
    return colour


def colmap_text_name_ok(name: str) -> bool:
    """Whether COLMAP's text model can carry image name ``name``: its reader takes the name as
    one whitespace-delimited token, so a name with a space (tab, line break) cannot be read
    back (and the format has no quoting); an empty name neither."""
    return bool(name) and not any(c in _TEXT_SPACE for c in name)


@dataclass
class _ColmapModel:
    """What both COLMAP formats hold: per exported image (1-based ids ``image + 1``) its
    camera, pose and observed keypoints; per point its position, colour, error and track."""

    images: np.ndarray  # (I,) input indices of the exported images
    cameras: list[tuple[str, int, int, list[float]]]  # model, width, height, params
    poses: np.ndarray  # (I, 7) qw qx qy qz tx ty tz (world to camera)
    names: list[str]
    xy: list[np.ndarray]  # per image (K_i, 2) keypoint pixels of its observations
    xy_point: list[np.ndarray]  # per image (K_i,) their point ids
    point_ids: np.ndarray  # (P',) COLMAP ids, from 1
    xyz: np.ndarray  # (P', 3)
    rgb: np.ndarray  # (P', 3)
    error: np.ndarray  # (P',)
    tracks: list[tuple[np.ndarray, np.ndarray]]  # per point (image ids, POINT2D_IDX)
    n_obs: int


def _colmap_model(names: Sequence[str], image_paths: Sequence[str | os.PathLike[str]] | None,
                  sizes: Sequence[tuple[int, int]], K: np.ndarray,
                  dist: Sequence[np.ndarray | None], w2c: np.ndarray, images: np.ndarray,
                  uv: Sequence[np.ndarray], points: np.ndarray, obs_image: np.ndarray,
                  obs_keypoint: np.ndarray, obs_point: np.ndarray,
                  errors: np.ndarray | None, workers: int = 1,
                  keypoint_colours: Sequence[np.ndarray | None] | None = None) -> _ColmapModel:
    images = np.asarray(images, np.int64).reshape(-1)
    keep = np.isin(obs_image, images)
    # a point left with one view because its others were not exported is not triangulated
    before = np.bincount(obs_point, minlength=points.shape[0])
    after = np.bincount(obs_point[keep], minlength=points.shape[0])
    keep &= (after >= np.minimum(before, 2))[obs_point]
    oi, ok, op = obs_image[keep], obs_keypoint[keep], obs_point[keep]
    err = np.zeros(oi.size) if errors is None else np.asarray(errors, np.float64)[keep]
    used = np.unique(op)
    pid = np.zeros(points.shape[0], np.int64)
    pid[used] = np.arange(1, used.size + 1)  # COLMAP ids from 1
    order = np.lexsort((ok, oi))  # per image, keypoints in index order
    oi, ok, op, err = oi[order], ok[order], op[order], err[order]
    # position of each observation within its image's POINTS2D list
    starts = np.searchsorted(oi, oi, side="left")
    p2d_idx = np.arange(oi.size) - starts
    colour = point_colours(image_paths, uv, oi, ok, op, points.shape[0], workers,
                           keypoint_colours)
    cameras, poses, xy, xy_point = [], [], [], []
    for i in images.tolist():
        model, params = colmap_camera(K[i], dist[i])
        w, h = sizes[i]
        cameras.append((model, int(w), int(h), params))
        poses.append(matrix_to_pose_vec(torch.from_numpy(np.asarray(w2c[i], np.float64)))
                     .numpy())
        sel = oi == i
        xy.append(np.asarray(uv[i], np.float64)[ok[sel]].reshape(-1, 2))
        xy_point.append(pid[op[sel]])
    n_obs = np.bincount(op, minlength=points.shape[0])
    mean_err = np.bincount(op, weights=err, minlength=points.shape[0]) / np.maximum(n_obs, 1)
    by_point = np.argsort(op, kind="stable")
    bounds = np.concatenate(([0], np.cumsum(n_obs)))
    tracks = []
    for p in used.tolist():
        obs = by_point[bounds[p]:bounds[p + 1]]
        tracks.append((oi[obs] + 1, p2d_idx[obs]))
    return _ColmapModel(images=images, cameras=cameras, poses=np.asarray(poses).reshape(-1, 7),
                        names=[str(names[i]) for i in images.tolist()], xy=xy,
                        xy_point=xy_point, point_ids=pid[used], xyz=points[used],
                        rgb=colour[used], error=mean_err[used], tracks=tracks, n_obs=int(oi.size))


def _colmap_text(out: Path, m: _ColmapModel) -> list[Path]:
    bad = [n for n in m.names if not colmap_text_name_ok(n)]
    if bad:
        raise ValueError(f"image name {bad[0]!r}: COLMAP's text model cannot hold a name with "
                         "whitespace (its reader stops at the first space); write the binary "
                         "model (write_colmap_model, binary=None or True)")
    n_img = m.images.size
    cam_lines = ["# Camera list with one line of data per camera:",
                 "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
                 f"# Number of cameras: {n_img}"]
    img_lines = ["# Image list with two lines of data per image:",
                 "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
                 "#   POINTS2D[] as (X, Y, POINT3D_ID)",
                 f"# Number of images: {n_img}, mean observations per image: "
                 f"{m.n_obs / max(n_img, 1):.1f}"]
    for k, i in enumerate(m.images.tolist()):
        model, w, h, params = m.cameras[k]
        cam_lines.append(f"{i + 1} {model} {w} {h} " + " ".join(f"{v:.10g}" for v in params))
        img_lines.append(f"{i + 1} " + " ".join(f"{v:.12g}" for v in m.poses[k])
                         + f" {i + 1} {m.names[k]}")
        img_lines.append(" ".join(f"{x:.4f} {y:.4f} {p}" for (x, y), p in
                                  zip(m.xy[k].tolist(), m.xy_point[k].tolist(), strict=True)))
    pt_lines = ["# 3D point list with one line of data per point:",
                "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
                f"# Number of points: {m.point_ids.size}, mean track length: "
                f"{m.n_obs / max(m.point_ids.size, 1):.2f}"]
    for k, p in enumerate(m.point_ids.tolist()):
        img, idx = m.tracks[k]
        track = " ".join(f"{a} {b}" for a, b in zip(img.tolist(), idx.tolist(), strict=True))
        x, y, z = m.xyz[k]
        r, g, b = m.rgb[k]
        pt_lines.append(f"{p} {x:.9g} {y:.9g} {z:.9g} {r} {g} {b} {m.error[k]:.6g} " + track)
    return [atomic_write_text(out / "cameras.txt", "\n".join(cam_lines) + "\n"),
            atomic_write_text(out / "images.txt", "\n".join(img_lines) + "\n"),
            atomic_write_text(out / "points3D.txt", "\n".join(pt_lines) + "\n")]


def _colmap_binary(out: Path, m: _ColmapModel) -> list[Path]:
    """COLMAP's binary model (``reconstruction_io_binary.cc``): little-endian; cameras as
    ``id u32, model i32, width u64, height u64, params f64[]``; images as ``id u32, q, t f64[7],
    camera u32, name\\0, n u64, (x, y f64, point id u64)[n]``; points as ``id u64, xyz f64[3],
    rgb u8[3], error f64, n u64, (image u32, point2D u32)[n]``."""
    n_img = m.images.size
    cams = [struct.pack("<Q", n_img)]
    imgs = [struct.pack("<Q", n_img)]
    for k, i in enumerate(m.images.tolist()):
        model, w, h, params = m.cameras[k]
        cams.append(struct.pack("<IiQQ", i + 1, _COLMAP_MODEL_ID[model], w, h)
                    + np.asarray(params, "<f8").tobytes())
        name = m.names[k].encode("utf-8")
        if not name or b"\0" in name:
            raise ValueError(f"image name {m.names[k]!r} cannot be stored in a COLMAP model")
        obs = np.zeros(len(m.xy[k]), dtype=[("x", "<f8"), ("y", "<f8"), ("p", "<u8")])
        obs["x"], obs["y"], obs["p"] = m.xy[k][:, 0], m.xy[k][:, 1], m.xy_point[k]
        imgs.append(struct.pack("<I7dI", i + 1, *m.poses[k].tolist(), i + 1) + name + b"\0"
                    + struct.pack("<Q", len(obs)) + obs.tobytes())
    pts = [struct.pack("<Q", m.point_ids.size)]
    for k, p in enumerate(m.point_ids.tolist()):
        img, idx = m.tracks[k]
        track = np.zeros(img.size, dtype=[("i", "<u4"), ("j", "<u4")])
        track["i"], track["j"] = img, idx
        pts.append(struct.pack("<Q3d3BdQ", p, *m.xyz[k].tolist(),
                               *np.clip(m.rgb[k], 0, 255).astype(int).tolist(),
                               float(m.error[k]), img.size) + track.tobytes())
    return [atomic_write_bytes(out / "cameras.bin", b"".join(cams)),
            atomic_write_bytes(out / "images.bin", b"".join(imgs)),
            atomic_write_bytes(out / "points3D.bin", b"".join(pts))]


def write_colmap_model(
    folder: str | os.PathLike[str],
    names: Sequence[str],
    image_paths: Sequence[str | os.PathLike[str]] | None,
    sizes: Sequence[tuple[int, int]],
    K: np.ndarray,
    dist: Sequence[np.ndarray | None],
    w2c: np.ndarray,
    images: np.ndarray,
    uv: Sequence[np.ndarray],
    points: np.ndarray,
    obs_image: np.ndarray,
    obs_keypoint: np.ndarray,
    obs_point: np.ndarray,
    errors: np.ndarray | None = None,
    binary: bool | None = None,
    workers: int = 1,
    keypoint_colours: Sequence[np.ndarray | None] | None = None,
) -> list[Path]:
    """Write a COLMAP model of ``images`` (indices into the ``N`` inputs) to ``folder``.

    ``names (N,)`` image names (as in the image folder; written unchanged), ``image_paths``
    to colour the points (``None``: grey), ``sizes (N,)`` (W, H), ``K (N, 3, 3)``, ``dist``
    per image or ``None``, ``w2c (N, 4, 4)``; ``uv[i] (K_i, 2)`` keypoint pixels; ``points
    (P, 3)`` and their observations ``obs_image, obs_keypoint, obs_point (O,)``; ``errors
    (O,)`` reprojection errors (pixels; a point's ``ERROR`` is their mean, 0 without).

    ``binary``: ``False`` the text model (``cameras.txt``, ``images.txt``, ``points3D.txt``;
    a name with whitespace is a ``ValueError``, see :func:`colmap_text_name_ok`), ``True`` the
    binary one (``cameras.bin``, ``images.bin``, ``points3D.bin``), ``None`` the text model
    unless an exported image's name needs the binary one. ``keypoint_colours[i] (K_i, 3)``
    uint8 RGB: image ``i``'s keypoint colours (:attr:`posernet.frontend.ImageFeatures.colours`;
    ``None``: the images are read for the points' colours, on ``workers`` threads). Files are
    written atomically.
    """
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    m = _colmap_model(names, image_paths, sizes, K, dist, w2c, images, uv, points, obs_image,
                      obs_keypoint, obs_point, errors, workers, keypoint_colours)
    if binary is None:
        binary = not all(colmap_text_name_ok(n) for n in m.names)
    return _colmap_binary(out, m) if binary else _colmap_text(out, m)


def write_colmap_text(folder: str | os.PathLike[str], *args: object, **kwargs: object
                      ) -> list[Path]:
    """:func:`write_colmap_model` with ``binary=False``: the text model."""
    return write_colmap_model(folder, *args, binary=False, **kwargs)  # type: ignore[arg-type]


def write_colmap_binary(folder: str | os.PathLike[str], *args: object, **kwargs: object
                        ) -> list[Path]:
    """:func:`write_colmap_model` with ``binary=True``: the binary model."""
    return write_colmap_model(folder, *args, binary=True, **kwargs)  # type: ignore[arg-type]


def largest_component(cameras: dict[str, dict]) -> list[str]:
    """Names of the solved cameras of the largest component of a ``poses.json`` ``cameras``
    record (ties: the smaller component id), in the record's order."""
    solved = {k: c for k, c in cameras.items()
              if c.get("solved") and c.get("camera_to_world") is not None}
    if not solved:
        return []
    sizes: dict[int, int] = {}
    for c in solved.values():
        sizes[int(c.get("component") or 0)] = sizes.get(int(c.get("component") or 0), 0) + 1
    best = min(sizes, key=lambda comp: (-sizes[comp], comp))
    return [k for k, c in solved.items() if int(c.get("component") or 0) == best]


def write_nerfstudio(path: str | os.PathLike[str], cameras: dict[str, dict],
                     image_dir: str | os.PathLike[str]) -> Path:
    """nerfstudio's ``transforms.json`` for the largest component of a ``poses.json``
    ``cameras`` record: per frame ``file_path`` (relative to ``path``'s folder),
    ``transform_matrix`` (camera to world in OpenGL axes), intrinsics ``fl_x, fl_y, cx, cy,
    w, h`` and OpenCV distortion ``k1, k2, p1, p2`` (``k3`` when given); ``camera_model``
    OPENCV. ``image_dir``: the folder the record's names are relative to (``file_path`` is
    the image file's real path, whatever characters its name holds)."""
    out = Path(path)
    names = largest_component(cameras)
    if not names:
        raise ValueError(f"{out}: no solved camera to export")
    frames = []
    for name in names:
        c = cameras[name]
        K = np.asarray(c["K"], np.float64)
        d = np.zeros(5) if c.get("dist") is None else np.pad(
            np.asarray(c["dist"], np.float64).reshape(-1), (0, 5))[:5]
        w, h = (c.get("size") or [None, None])[:2]
        rel = os.path.relpath(os.path.abspath(Path(image_dir) / name),
                              os.path.abspath(out.parent))
        frame = {"file_path": Path(rel).as_posix(),
                 "transform_matrix": (np.asarray(c["camera_to_world"]) @ _CV_TO_GL).tolist(),
                 "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]),
                 "cy": float(K[1, 2]), "w": w, "h": h, "k1": float(d[0]), "k2": float(d[1]),
                 "p1": float(d[2]), "p2": float(d[3])}
        if d[4]:
            frame["k3"] = float(d[4])
        frames.append(frame)
    body = {"camera_model": "OPENCV", "frames": frames,
            "posernet": "largest component of poses.json; positions up to one similarity "
                        "(no metric scale)"}
    return atomic_write_text(out, json.dumps(body, indent=1) + "\n")


def _timestamp(name: str, index: int) -> float:
    """TUM-style timestamp from a file name (``1305031102.175304.png``), else ``index``."""
    from .frontend.images import image_timestamp

    t = image_timestamp(name)
    return float(index) if t is None else t


def write_tum(path: str | os.PathLike[str], cameras: dict[str, dict]) -> Path:
    """TUM RGB-D trajectory text (``timestamp tx ty tz qx qy qz qw``, camera to world) of the
    largest component of a ``poses.json`` ``cameras`` record, one line per camera in time
    order; timestamps from TUM-style file names, else the camera's index in name order.

    The rows are the standard 8 columns; which image each row is stands in the header, one
    comment line per row in the same order: ``# image <timestamp> <name>`` with the name as a
    JSON string (quoted, so names with spaces or other characters are unambiguous;
    :func:`read_tum_image_names` reads them back)."""
    names = largest_component(cameras)
    if not names:
        raise ValueError(f"{path}: no solved camera to export")
    names = sorted(names)
    stamps = [_timestamp(n, i) for i, n in enumerate(names)]
    order = np.argsort(stamps, kind="stable")
    c2w = torch.as_tensor(np.stack([np.asarray(cameras[n]["camera_to_world"], np.float64)
                                    for n in names]))
    q = matrix_to_pose_vec(c2w)[:, :4].numpy()  # w x y z
    lines = ["# posernet camera-to-world poses (largest component; positions up to one "
             "similarity), TUM format: timestamp tx ty tz qx qy qz qw",
             f"# images: {len(names)}, one '# image <timestamp> <file name as a JSON string>' "
             "line per row below, in the same order"]
    lines += [f"# image {stamps[i]:.6f} {json.dumps(names[i], ensure_ascii=False)}"
              for i in order.tolist()]
    for i in order.tolist():
        t = c2w[i, :3, 3].numpy()
        w, x, y, z = q[i]
        lines.append(f"{stamps[i]:.6f} {t[0]:.9g} {t[1]:.9g} {t[2]:.9g} "
                     f"{x:.9g} {y:.9g} {z:.9g} {w:.9g}")
    return atomic_write_text(path, "\n".join(lines) + "\n")


def read_tum_image_names(path: str | os.PathLike[str]) -> list[str]:
    """The image name of each row of a trajectory :func:`write_tum` wrote, in row order."""
    names = []
    for line in Path(path).read_text(encoding="utf-8").split("\n"):  # not at U+2028 & co.
        if line.startswith("# image "):
            names.append(json.loads(line.split(" ", 3)[3]))
    return names

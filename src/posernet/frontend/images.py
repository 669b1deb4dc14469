"""Images a user brings: listing a folder, reading files, intrinsics and optional pose files.

Every failure names the offending file or value: a missing or unreadable image, intrinsics of
the wrong shape, a pose file that is not a rigid 4x4 matrix.

Intrinsics come as ``fx, fy, cx, cy`` (4 numbers), a ``3x3`` matrix, or a JSON file holding
either one entry for all images or one per image::

    {"fx": 585, "fy": 585, "cx": 320, "cy": 240, "dist": [k1, k2, p1, p2, k3]}     # shared
    {"default": {...}, "images": {"IMG_001.jpg": {"K": [[...], [...], [...]]}, ...}}  # per image

``dist`` (OpenCV order, optional) is the lens distortion; the 5-point step undistorts with it.

Without known intrinsics (``intrinsics=auto``, or ``None``), each image gets a pinhole camera
centred on the image whose focal length comes from its EXIF data (35 mm equivalent focal
length, or focal length and focal-plane resolution) when present, else the prior
``FOCAL_PRIOR`` x the longest image side that SfM tools use; ``ImageRecord.intrinsics_source``
says which (``"given"``, ``"exif"`` or ``"prior"``) so that bundle adjustment can refine it.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from ..geometry import quaternion_to_rotation_matrix

__all__ = [
    "FOCAL_PRIOR",
    "IMAGE_SUFFIXES",
    "ImageError",
    "ImageRecord",
    "associate",
    "check_intrinsics",
    "guess_intrinsics",
    "image_problem",
    "image_size",
    "image_timestamp",
    "intrinsics_matrix",
    "list_images",
    "parse_intrinsics",
    "read_colmap_images",
    "read_image",
    "read_pose_file",
    "read_tum_trajectory",
    "records_for_images",
]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
#: focal length (pixels) of an image without known intrinsics or EXIF, times its longest side
FOCAL_PRIOR = 1.2
# 7-Scenes keeps depth maps beside the colour images: never take them for photos
_SKIP_SUFFIXES = (".depth.png",)


class ImageError(ValueError):
    """A user-supplied image, intrinsics or pose file is missing or malformed."""


@dataclass
class ImageRecord:
    """One input image: ``key`` is its name relative to the image folder (used in outputs).

    ``K (3, 3)``, ``dist (D,)`` OpenCV distortion or ``None``; ``size`` (W, H) once read;
    ``c2w (4, 4)`` the ground-truth camera-to-world pose when known.
    """

    path: Path
    key: str
    K: np.ndarray
    dist: np.ndarray | None = None
    size: tuple[int, int] | None = None
    c2w: np.ndarray | None = None
    intrinsics_source: str = "given"  # "given", "exif" or "prior" (see the module docstring)

    @property
    def k1(self) -> float:
        return float(self.dist[0]) if self.dist is not None and self.dist.size else 0.0


def list_images(folder: str | os.PathLike[str], pattern: str | None = None) -> list[Path]:
    """Image files in ``folder`` (sorted; ``pattern`` a glob such as ``*.color.png``).

    Without a pattern every file with an image suffix is taken except 7-Scenes depth maps.
    """
    root = Path(folder)
    if not root.exists():
        raise ImageError(f"image folder not found: {root}")
    if not root.is_dir():
        raise ImageError(f"images must be a folder of image files, got a file: {root}")
    if pattern:
        files = sorted(p for p in root.glob(pattern) if p.is_file())
    else:
        files = sorted(
            p
            for p in root.iterdir()
            if p.is_file()
            and p.suffix.lower() in IMAGE_SUFFIXES
            and not p.name.lower().endswith(_SKIP_SUFFIXES)
        )
    if not files:
        what = f"matching {pattern!r}" if pattern else f"({', '.join(IMAGE_SUFFIXES)})"
        raise ImageError(f"no image files {what} in {root}")
    return files


def check_intrinsics(K: np.ndarray, size: tuple[int, int], where: str) -> None:
    """Raise :class:`ImageError` (naming ``where``) when ``K (3, 3)`` cannot belong to an
    image of ``size`` (W, H): the principal point outside the image, or a focal length
    outside 0.1-30 times the longer side (a field of view from about 2 to 160 degrees; a
    focal length given in mm rather than pixels falls below it)."""
    w, h = size
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not (0 <= cx <= w and 0 <= cy <= h):
        raise ImageError(f"{where}: principal point ({cx:g}, {cy:g}) lies outside the {w}x{h} "
                         "image (intrinsics are in pixels of this image)")
    long = max(w, h)
    for name, f in (("fx", fx), ("fy", fy)):
        if not 0.1 * long <= f <= 30 * long:
            raise ImageError(f"{where}: focal length {name}={f:g} px is implausible for a "
                             f"{w}x{h} image (expected {0.1 * long:g}-{30 * long:g} px; in "
                             "pixels, not mm)")


def image_size(path: str | os.PathLike[str]) -> tuple[int, int] | None:
    """``(W, H)`` of an image file read from its header (PNG, JPEG), or None."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 16)
    except OSError:
        return None
    if head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) >= 24:
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if head[:2] == b"\xff\xd8":  # JPEG: walk the markers to a start-of-frame
        i = 2
        while i + 9 < len(head):
            if head[i] != 0xFF:
                return None
            marker, seg = head[i + 1], int.from_bytes(head[i + 2:i + 4], "big")
            if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD,
                          0xCE, 0xCF):
                return (int.from_bytes(head[i + 7:i + 9], "big"),
                        int.from_bytes(head[i + 5:i + 7], "big"))
            i += 2 + seg
    return None


def image_problem(path: str | os.PathLike[str]) -> str | None:
    """Why ``path`` cannot be used as an image (``None`` when it can): unreadable, empty, or
    not decodable by OpenCV. Decodes at 1/8 size (JPEG decodes that way cheaply), so a folder
    is checked before any heavy work."""
    try:
        data = np.fromfile(Path(path), dtype=np.uint8)
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    if data.size == 0:
        return "empty file"
    img = cv2.imdecode(data, cv2.IMREAD_REDUCED_GRAYSCALE_8)
    if img is None or img.size == 0:
        return "not an image file OpenCV can decode"
    return None


def read_image(path: str | os.PathLike[str]) -> np.ndarray:
    """``(H, W, 3)`` uint8 BGR image; a clear error for a missing or unreadable file."""
    p = Path(path)
    if not p.is_file():
        raise ImageError(f"image not found: {p}")
    data = np.fromfile(p, dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if img is None or img.size == 0:
        raise ImageError(f"cannot read image {p}: not an image file OpenCV can decode")
    return img


def keypoint_colours(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """``(K, 3)`` uint8 RGB of the pixels under keypoints ``uv (K, 2)`` (x, y; rounded, clipped
    to the image) of a BGR ``(H, W, 3)`` or grey ``(H, W)`` image: the colours of the points
    they triangulate, kept from the image stage so that no export reads the image again."""
    h, w = img.shape[:2]
    xy = np.rint(np.asarray(uv, np.float64).reshape(-1, 2)).astype(np.int64)
    px = img[np.clip(xy[:, 1], 0, h - 1), np.clip(xy[:, 0], 0, w - 1)]
    return np.repeat(px[:, None], 3, axis=1) if img.ndim == 2 else px[:, ::-1].copy()


def intrinsics_matrix(
    value: Any, where: str = "intrinsics"
) -> tuple[np.ndarray, np.ndarray | None]:
    """``(K (3, 3), dist)`` from 4 numbers ``fx, fy, cx, cy``, a 3x3 matrix, or a mapping with
    ``fx``/``fy``/``cx``/``cy`` or ``K`` (and optional ``dist``); errors start with ``where``."""
    dist = None
    if isinstance(value, Mapping):
        if "K" in value:
            K = np.asarray(value["K"], dtype=np.float64) if _numeric(value["K"]) else None
        elif all(k in value for k in ("fx", "fy", "cx", "cy")):
            vals = [value[k] for k in ("fx", "fy", "cx", "cy")]
            K = intrinsics_matrix(vals, where)[0] if _numeric(vals) else None
        else:
            raise ImageError(f"{where}: intrinsics need 'fx', 'fy', 'cx', 'cy' or 'K'")
        if K is None:
            raise ImageError(f"{where}: values must be numbers")
        if value.get("dist") is not None:
            d = value["dist"]
            if not _numeric(d) or np.asarray(d, dtype=np.float64).ndim != 1 or \
                    np.asarray(d).size not in (1, 2, 4, 5, 8, 12, 14):
                raise ImageError(f"{where}: 'dist' must be 1, 2, 4, 5, 8, 12 or 14 numbers "
                                 "(OpenCV order k1, k2, p1, p2, k3, ...)")
            dist = np.asarray(d, dtype=np.float64)
    else:
        if not _numeric(value):
            raise ImageError(f"{where}: values must be numbers, got {value!r}")
        a = np.asarray(value, dtype=np.float64)
        if a.shape == (4,):
            fx, fy, cx, cy = a
            K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        elif a.shape == (3, 3):
            K = a
        else:
            raise ImageError(f"{where}: expected 4 numbers fx,fy,cx,cy or a 3x3 "
                             f"matrix, got shape {a.shape}")
    if K.shape != (3, 3):
        raise ImageError(f"{where}: K must be 3x3, got shape {K.shape}")
    if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ImageError(f"{where}: focal lengths must be positive and finite, got "
                         f"fx={K[0, 0]}, fy={K[1, 1]}")
    if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0 or K[2, 0] != 0:
        raise ImageError(f"{where}: K must be upper triangular with last row 0 0 1")
    return K, dist


def _numeric(v: Any) -> bool:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        return False
    return bool(a.size) and bool(np.isfinite(a).all())


# EXIF tags (Exif IFD 0x8769): focal length (mm), its 35 mm equivalent, focal-plane resolution
_EXIF_IFD, _FOCAL, _FOCAL_35 = 0x8769, 0x920A, 0xA405
_PLANE_X, _PLANE_UNIT, _ORIENTATION = 0xA20E, 0xA210, 0x0112
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # inch, cm, mm, um


def guess_intrinsics(path: str | os.PathLike[str]) -> tuple[np.ndarray, str]:
    """``(K (3, 3), source)`` for an image without known intrinsics: the focal length from its
    EXIF data (``source="exif"``) or ``FOCAL_PRIOR`` x the longest side (``"prior"``), the
    principal point at the centre of the image as OpenCV reads it (EXIF orientation applied)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            w, h = im.size
            exif = im.getexif()
    except (OSError, UnidentifiedImageError) as exc:
        raise ImageError(f"cannot read image {path} ({exc})") from None
    if exif.get(_ORIENTATION) in (5, 6, 7, 8):  # stored sideways: OpenCV turns it upright
        w, h = h, w
    tags = exif.get_ifd(_EXIF_IFD)
    side = float(max(w, h))
    f = None
    try:
        if tags.get(_FOCAL_35):  # 35 mm equivalent: a 36 mm wide frame
            f = float(tags[_FOCAL_35]) / 36.0 * side
        elif tags.get(_FOCAL) and tags.get(_PLANE_X) and tags.get(_PLANE_UNIT) in _UNIT_MM:
            f = float(tags[_FOCAL]) * float(tags[_PLANE_X]) / _UNIT_MM[tags[_PLANE_UNIT]]
    except (TypeError, ValueError, ZeroDivisionError):
        f = None
    source = "exif"
    if f is None or not np.isfinite(f) or not 0.1 * side < f < 20 * side:
        f, source = FOCAL_PRIOR * side, "prior"
    K = np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])
    return K, source


def parse_intrinsics(
    spec: Any, keys: Sequence[str]
) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """Per-image ``(K, dist)`` for images ``keys`` from a spec (see the module docstring).

    ``spec``: 4 numbers, a ``"fx,fy,cx,cy"`` string, a 3x3 nested list, a mapping, or the path
    of a JSON file (shared or per image) or a text file with a 3x3 matrix.
    """
    if spec is None:
        raise ImageError("intrinsics are required: intrinsics=FX,FY,CX,CY or a file")
    if isinstance(spec, str) and "," in spec and not Path(spec).exists():
        parts = [s.strip() for s in spec.strip("[]()").split(",")]
        try:
            spec = [float(p) for p in parts]
        except ValueError:
            raise ImageError(f"intrinsics {spec!r}: expected 4 numbers FX,FY,CX,CY") from None
    if isinstance(spec, str | os.PathLike):
        return _intrinsics_file(Path(spec), keys)
    shared = intrinsics_matrix(spec, "intrinsics")
    return [shared] * len(keys)


def _intrinsics_file(path: Path, keys: Sequence[str]) -> list[tuple[np.ndarray, np.ndarray | None]]:
    if not path.is_file():
        raise ImageError(f"intrinsics file not found: {path}")
    text = path.read_text(encoding="utf-8", errors="replace")
    if path.suffix.lower() != ".json":
        try:
            K = np.loadtxt(path, dtype=np.float64, ndmin=2)
        except ValueError as exc:
            raise ImageError(f"{path}: not a 3x3 matrix of numbers ({exc})") from None
        shared = intrinsics_matrix(K.reshape(-1) if K.size == 4 else K, str(path))
        return [shared] * len(keys)
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ImageError(f"{path}: malformed JSON ({exc})") from None
    if isinstance(data, Mapping) and "images" in data:
        per = data["images"]
        if not isinstance(per, Mapping):
            raise ImageError(f"{path}: 'images' must map image names to intrinsics")
        default = data.get("default")
        out = []
        for key in keys:
            entry = per.get(key, per.get(Path(key).name, default))
            if entry is None:
                raise ImageError(f"{path}: no intrinsics for image {key!r} and no 'default'")
            out.append(intrinsics_matrix(entry, f"{path} [{key}]"))
        known = set(keys) | {Path(k).name for k in keys}
        unknown = sorted(str(k) for k in per if str(k) not in known)
        if unknown:  # a typo would otherwise give its image the default silently
            raise ImageError(f"{path}: 'images' names {len(unknown)} file(s) that are not among "
                             f"the images: {', '.join(unknown[:5])}"
                             + (" ..." if len(unknown) > 5 else ""))
        return out
    shared = intrinsics_matrix(data, str(path))
    return [shared] * len(keys)


# Real 7-Scenes rotations are slightly non-orthonormal: accept max |R^T R - I| up to this and
# re-orthonormalise; anything further off is not a rigid pose.
ROTATION_TOL = 5e-3


def read_pose_file(path: str | os.PathLike[str]) -> np.ndarray:
    """A rigid 4x4 camera-to-world matrix from a text file (7-Scenes ``.pose.txt``), validated.

    The rotation is re-orthonormalised (SVD) when within :data:`ROTATION_TOL` of a rotation,
    since real pose files carry a few digits only.
    """
    p = Path(path)
    if not p.is_file():
        raise ImageError(f"pose file not found: {p}")
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise ImageError(f"cannot read pose file {p}: {e}") from None
    rows = [line.split() for line in text.splitlines() if line.strip()]
    try:
        T = np.array([[float(x) for x in r] for r in rows], dtype=np.float64)
    except ValueError:
        raise ImageError(f"pose file {p} is not a 4x4 matrix of numbers") from None
    if T.shape != (4, 4) or any(len(r) != 4 for r in rows):
        raise ImageError(
            f"pose file {p} is not a 4x4 matrix of numbers "
            f"(found {len(rows)} rows of {sorted({len(r) for r in rows})} values)"
        )
    if not np.isfinite(T).all():
        raise ImageError(f"pose file {p} holds non-finite values")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise ImageError(f"pose file {p}: last row must be 0 0 0 1, got {T[3].tolist()}")
    R = T[:3, :3]
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > ROTATION_TOL or np.linalg.det(R) <= 0:
        raise ImageError(
            f"pose file {p} is not a rigid transform (rotation part off orthonormal by "
            f"{err:.2g}, det {np.linalg.det(R):.3g})"
        )
    U, _, Vt = np.linalg.svd(R)
    out = np.eye(4)
    out[:3, :3] = U @ Vt
    out[:3, 3] = T[:3, 3]
    return out


def _quat_to_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` rotations of quaternions ``(N, 4)`` (w, x, y, z; normalised here), by
    :func:`posernet.geometry.quaternion_to_rotation_matrix`."""
    q = torch.from_numpy(np.asarray(q_wxyz, np.float64))
    return quaternion_to_rotation_matrix(q).numpy()


def read_tum_trajectory(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """A TUM RGB-D trajectory file (``groundtruth.txt``: ``timestamp tx ty tz qx qy qz qw``
    per line, camera to world, ``#`` comments) -> timestamps ``(N,)`` and ``c2w (N, 4, 4)``,
    sorted by time; a clear error naming the file and line otherwise."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise ImageError(f"cannot read trajectory {p}: {e}") from None
    rows = []
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        vals = line.replace(",", " ").split()
        try:
            row = [float(v) for v in vals]
        except ValueError:
            row = []
        if len(row) != 8 or not np.isfinite(row).all():
            raise ImageError(f"trajectory {p} line {n}: expected 'timestamp tx ty tz qx qy qz "
                             f"qw', got {line.strip()[:60]!r}")
        rows.append(row)
    if not rows:
        raise ImageError(f"trajectory {p} holds no pose")
    a = np.array(rows)
    a = a[np.argsort(a[:, 0], kind="stable")]
    c2w = np.tile(np.eye(4), (len(a), 1, 1))
    c2w[:, :3, :3] = _quat_to_matrix(a[:, [7, 4, 5, 6]])
    c2w[:, :3, 3] = a[:, 1:4]
    return a[:, 0], c2w


def image_timestamp(name: str) -> float | None:
    """The timestamp in a TUM-style image name (``rgb/1305031102.175304.png``), or None."""
    stem = Path(name).name
    for suffix in (".color.png", ".color.jpg"):
        stem = stem.removesuffix(suffix)
    stem = stem.rsplit(".", 1)[0] if stem.count(".") >= 1 else stem
    try:
        return float(stem)
    except ValueError:
        return None


def associate(stamps: np.ndarray, gt_stamps: np.ndarray, max_diff: float = 0.02) -> np.ndarray:
    """Index into sorted ``gt_stamps`` of the nearest ground-truth time for each of ``stamps``
    (``-1`` where the nearest is more than ``max_diff`` seconds away; TUM's association rule)."""
    stamps = np.asarray(stamps, np.float64)
    j = np.clip(np.searchsorted(gt_stamps, stamps), 1, max(len(gt_stamps) - 1, 1))
    left = np.abs(stamps - gt_stamps[j - 1])
    right = np.abs(gt_stamps[np.minimum(j, len(gt_stamps) - 1)] - stamps)
    best = np.where(left <= right, j - 1, np.minimum(j, len(gt_stamps) - 1))
    return np.where(np.abs(gt_stamps[best] - stamps) <= max_diff, best, -1)


def read_colmap_images(folder: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Camera-to-world poses by image name from a COLMAP model's images: ``images.bin`` (the
    binary model, preferred when ``folder`` holds both, as COLMAP does) or ``images.txt``, in
    ``folder`` or the file itself. A text line's name is the rest of the line after its camera
    id (COLMAP writes names unchanged, spaces included)."""
    p = Path(folder)
    if p.is_dir():
        p = p / "images.bin" if (p / "images.bin").is_file() else p / "images.txt"
    if p.suffix == ".bin":
        return _read_colmap_images_bin(p)
    try:
        lines = [ln for ln in p.read_text(encoding="utf-8").splitlines()
                 if ln.strip() and not ln.startswith("#")]
    except (OSError, UnicodeDecodeError) as e:
        raise ImageError(f"cannot read COLMAP model {p}: {e}") from None
    out = {}
    for head in lines[0::2]:  # each image: a pose line, then its 2D points line
        f = head.split(maxsplit=9)
        try:
            q = np.array([float(v) for v in f[1:5]])[None]
            t = np.array([float(v) for v in f[5:8]])
            name = f[9]
        except (ValueError, IndexError):
            raise ImageError(f"COLMAP model {p}: bad image line {head[:60]!r}") from None
        out[name] = _c2w(q, t)
    return out


def _c2w(q_wxyz: np.ndarray, t: np.ndarray) -> np.ndarray:
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = _quat_to_matrix(q_wxyz)[0], t
    return np.linalg.inv(w2c)


def _read_colmap_images_bin(p: Path) -> dict[str, np.ndarray]:
    """COLMAP's binary ``images.bin``: per image ``id u32, qw qx qy qz tx ty tz f64, camera
    u32, name\\0, n u64, (x, y f64, point id u64)[n]``, little-endian."""
    import struct

    try:
        data = p.read_bytes()
    except OSError as e:
        raise ImageError(f"cannot read COLMAP model {p}: {e}") from None
    out = {}
    try:
        (n,), pos = struct.unpack_from("<Q", data), 8
        for _ in range(n):
            v = struct.unpack_from("<I7dI", data, pos)
            end = data.index(b"\0", pos + 64)
            name = data[pos + 64:end].decode("utf-8")
            (k,) = struct.unpack_from("<Q", data, end + 1)
            pos = end + 9 + 24 * k
            if pos > len(data):
                raise ValueError("truncated")
            out[name] = _c2w(np.array(v[1:5])[None], np.array(v[5:8]))
    except (struct.error, ValueError, UnicodeDecodeError) as e:
        raise ImageError(f"COLMAP model {p}: not a readable binary images file ({e})") from None
    return out


def _pose_path(image: Path, pose_dir: Path | None) -> Path:
    name = image.name
    for suffix in (".color.png", ".color.jpg"):
        if name.endswith(suffix):
            name = name[: -len(suffix)] + ".pose.txt"
            break
    else:
        name = image.stem + ".pose.txt"
    return (pose_dir or image.parent) / name


def _external_gt(records: list[ImageRecord], src: Path) -> list[ImageRecord]:
    """Ground truth from a COLMAP model or a TUM trajectory file for every record."""
    if src.is_dir() or src.name in ("images.txt", "images.bin"):
        poses = read_colmap_images(src)
        missing = [r.key for r in records if r.key not in poses and r.path.name not in poses]
        if missing:
            raise ImageError(f"gt_poses: {src} has no pose for {len(missing)} image(s), e.g. "
                             f"{missing[0]}")
        for r in records:
            r.c2w = poses.get(r.key, poses.get(r.path.name))
        return records
    gt_t, gt_c2w = read_tum_trajectory(src)
    stamps = [image_timestamp(r.key) for r in records]
    if any(s is None for s in stamps):
        bad = next(r.key for r, s in zip(records, stamps, strict=True) if s is None)
        raise ImageError(f"gt_poses: {src} is a trajectory, but {bad} has no timestamp in its "
                         "name (TUM style: 1305031102.175304.png)")
    idx = associate(np.array(stamps), gt_t)
    if (idx < 0).any():
        k = int(np.flatnonzero(idx < 0)[0])
        raise ImageError(f"gt_poses: {src} has no pose within 20 ms of {int((idx < 0).sum())} "
                         f"image(s), e.g. {records[k].key}")
    for r, i in zip(records, idx.tolist(), strict=True):
        r.c2w = gt_c2w[i].copy()
    return records


def records_for_images(
    folder: str | os.PathLike[str],
    intrinsics: Any,
    pattern: str | None = None,
    gt_poses: str | None = "auto",
    skipped: list[tuple[str, str]] | None = None,
    workers: int = 1,
) -> list[ImageRecord]:
    """Records of the images in ``folder`` with their intrinsics and, optionally, poses.

    Every file is checked first (:func:`image_problem`, on ``workers`` threads): with a
    ``skipped`` list, unusable files are left out and appended to it as ``(name, reason)``;
    without one, they raise :class:`ImageError` naming each of them.

    ``intrinsics``: a spec for :func:`parse_intrinsics`, or ``"auto"`` / ``None`` to guess
    them per image (:func:`guess_intrinsics`).

    ``gt_poses``: ``"auto"`` uses ``<name>.pose.txt`` files beside the images when every image
    has one (7-Scenes layout: ``frame-000000.color.png`` -> ``frame-000000.pose.txt``),
    ``"none"``/``None`` ignores them; a folder requires one pose file per image there, a COLMAP
    model (a folder with ``images.bin`` or ``images.txt``) one image entry per image (matched
    by name), and
    a TUM trajectory file (``groundtruth.txt``) a pose within 20 ms of each image's
    timestamp (from TUM-style names, ``1305031102.175304.png``).
    """
    root = Path(folder)
    files = list_images(root, pattern)
    if workers > 1 and len(files) > 1:  # decoding releases the GIL
        with ThreadPoolExecutor(min(workers, len(files))) as pool:
            problems = list(pool.map(image_problem, files))
    else:
        problems = [image_problem(p) for p in files]
    listed = [str(p.relative_to(root)) for p in files]  # skipped ones too (intrinsics files)
    bad = [(str(p.relative_to(root)), why) for p, why in zip(files, problems, strict=True)
           if why]
    if bad and skipped is None:
        raise ImageError(f"{len(bad)} unusable image(s) in {root}: "
                         + "; ".join(f"{k}: {why}" for k, why in bad))
    if bad:
        skipped.extend(bad)
        files = [p for p, why in zip(files, problems, strict=True) if not why]
    keys = [str(p.relative_to(root)) for p in files]
    if intrinsics is None or (isinstance(intrinsics, str) and intrinsics.lower() == "auto"):
        records = []
        for p, k in zip(files, keys, strict=True):
            K, source = guess_intrinsics(p)
            records.append(ImageRecord(path=p, key=k, K=K, intrinsics_source=source))
    else:
        by_key = dict(zip(listed, parse_intrinsics(intrinsics, listed), strict=True))
        cams = [by_key[k] for k in keys]
        records = [ImageRecord(path=p, key=k, K=K, dist=d)
                   for p, k, (K, d) in zip(files, keys, cams, strict=True)]
        sizes = {}
        for r in records:  # given intrinsics must fit the image they are for
            size = image_size(r.path)
            if size is not None:
                check_intrinsics(r.K, size, f"intrinsics for {r.key}")
                sizes.setdefault(size, r.key)
        shared = all(np.array_equal(r.K, records[0].K) for r in records)
        if shared and len(sizes) > 1:
            eg = ", ".join(f"{w}x{h} ({k})" for (w, h), k in list(sizes.items())[:3])
            raise ImageError(f"intrinsics: one camera matrix for images of {len(sizes)} sizes "
                             f"({eg}); give per-image intrinsics in a JSON file, or "
                             "intrinsics=auto")
    mode = "none" if gt_poses is None else str(gt_poses)
    if mode.lower() == "none":
        return records
    pose_dir = None if mode == "auto" else Path(mode)
    if pose_dir is not None and (pose_dir.is_file() or (pose_dir / "images.txt").is_file()
                                 or (pose_dir / "images.bin").is_file()):
        return _external_gt(records, pose_dir)
    if pose_dir is not None and not pose_dir.is_dir():
        raise ImageError(f"gt_poses folder not found: {pose_dir}")
    paths = [_pose_path(r.path, pose_dir) for r in records]
    if mode == "auto" and not all(p.is_file() for p in paths):
        return records
    for r, p in zip(records, paths, strict=True):
        r.c2w = read_pose_file(p)
    return records

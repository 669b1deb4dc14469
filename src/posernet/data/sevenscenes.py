"""Reader of the Microsoft 7-Scenes dataset layout (real data or :mod:`posernet.data.render`).

Layout of one scene folder (any folder name)::

    TrainSplit.txt, TestSplit.txt            lines "sequence1", "sequence2", ... (-> seq-01, ...)
    seq-01/frame-000000.color.png            8-bit RGB, 640x480
    seq-01/frame-000000.depth.png            uint16 millimetres, 65535 (or 0) = invalid
    seq-01/frame-000000.pose.txt             4x4 camera-to-world matrix

Intrinsics are not stored; the dataset authors give f = 585 and principal point (320, 240).
The layout is validated eagerly when a scene is opened (file names only); pose files are parsed
and checked when read. Every user-caused failure raises :class:`SevenScenesError` naming the
offending path.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..frontend.images import ImageError, intrinsics_matrix, read_pose_file

__all__ = [
    "DEFAULT_INTRINSICS",
    "SPLITS",
    "SevenScenesError",
    "SevenScenesFrame",
    "SevenScenesScene",
    "open_sevenscenes",
    "read_color",
    "read_depth",
]

DEFAULT_INTRINSICS = (585.0, 585.0, 320.0, 240.0)  # fx, fy, cx, cy
SPLITS = {"train": "TrainSplit.txt", "test": "TestSplit.txt"}
DEPTH_INVALID = 65535

_SPLIT_LINE = re.compile(r"sequence(\d+)")
_FRAME = re.compile(r"frame-(\d+)\.color\.png")


class SevenScenesError(ValueError):
    """A path does not hold what the 7-Scenes layout requires (the message names it)."""


@dataclass(frozen=True)
class SevenScenesFrame:
    """One frame: its scene, split, sequence folder (``"seq-01"``), number and files."""

    scene: str
    split: str
    sequence: str
    index: int
    color: Path
    depth: Path | None  # None: no depth image (building graphs never reads depth)
    pose: Path

    @property
    def key(self) -> str:
        """Colour image path relative to the scene folder, e.g. ``seq-01/frame-000000.color.png``
        (the key of ``objects.json`` / box files)."""
        return f"{self.sequence}/{self.color.name}"


def _intrinsics_matrix(intrinsics: object) -> np.ndarray:
    """``(3, 3)`` K from ``None`` (7-Scenes defaults), ``(fx, fy, cx, cy)`` or a 3x3 matrix."""
    try:
        return intrinsics_matrix(DEFAULT_INTRINSICS if intrinsics is None else intrinsics)[0]
    except ImageError as e:
        raise SevenScenesError(str(e)) from None


def _read_split(path: Path) -> list[int]:
    """Sequence numbers listed in a split file (blank lines ignored)."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise SevenScenesError(f"cannot read split file {path}: {e}") from None
    nums: list[int] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        m = _SPLIT_LINE.fullmatch(s)
        if not m:
            raise SevenScenesError(
                f"{path} line {lineno}: expected 'sequenceN' (e.g. sequence1), got {s!r}"
            )
        n = int(m.group(1))
        if n in nums:
            raise SevenScenesError(f"{path} lists sequence{n} twice")
        nums.append(n)
    return nums


def _parse_pose(path: Path) -> np.ndarray:
    """The validated rigid ``(4, 4)`` matrix of a pose file (rotation re-orthonormalised)."""
    try:
        return read_pose_file(path)
    except ImageError as e:
        raise SevenScenesError(str(e)) from None


def read_depth(path: str | os.PathLike[str]) -> np.ndarray:
    """Depth image -> ``(H, W)`` float32 metres, NaN where the sensor gave none (65535 or 0)."""
    p = Path(path)
    if not p.is_file():
        raise SevenScenesError(f"depth image {p} does not exist")
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SevenScenesError(f"cannot read depth image {p}")
    if img.ndim != 2 or img.dtype != np.uint16:
        raise SevenScenesError(
            f"depth image {p} must be single-channel uint16 millimetres, "
            f"got {img.dtype} with shape {img.shape}"
        )
    d = img.astype(np.float32) * np.float32(1e-3)
    d[(img == DEPTH_INVALID) | (img == 0)] = np.nan
    return d


def read_color(path: str | os.PathLike[str]) -> np.ndarray:
    """Colour image -> ``(H, W, 3)`` uint8 RGB."""
    p = Path(path)
    if not p.is_file():
        raise SevenScenesError(f"colour image {p} does not exist")
    img = cv2.imread(str(p), cv2.IMREAD_COLOR)
    if img is None:
        raise SevenScenesError(f"cannot read colour image {p}")
    return img[..., ::-1].copy()


class SevenScenesScene:
    """One scene folder in 7-Scenes layout; the layout is checked when it is opened.

    ``intrinsics``: ``(fx, fy, cx, cy)`` or a 3x3 K; default :data:`DEFAULT_INTRINSICS`
    (for a rendered scene at another size, see :func:`posernet.data.render.render_intrinsics`).
    """

    def __init__(self, path: str | os.PathLike[str], intrinsics: object = None) -> None:
        self.path = Path(path)
        self.name = Path(os.path.abspath(self.path)).name  # "." -> its name; keeps symlink names
        self._K = _intrinsics_matrix(intrinsics)
        if not self.path.exists():
            raise SevenScenesError(f"7-Scenes scene folder {self.path} does not exist")
        if not self.path.is_dir():
            raise SevenScenesError(f"7-Scenes scene {self.path} is not a folder")
        missing = [f for f in SPLITS.values() if not (self.path / f).is_file()]
        if missing:
            raise SevenScenesError(
                f"{self.path} is not a 7-Scenes scene folder: {' and '.join(missing)} missing"
            )
        self._sequences: dict[str, list[str]] = {}
        owner: dict[str, str] = {}
        for split, fname in SPLITS.items():
            seqs = []
            for n in _read_split(self.path / fname):
                seq = f"seq-{n:02d}"
                folder = self.path / seq
                if seq in owner:
                    raise SevenScenesError(
                        f"{self.path / fname} lists sequence{n}, already in {owner[seq]}"
                    )
                if not folder.is_dir():
                    hint = " (unzip it first)" if folder.with_suffix(".zip").exists() else ""
                    raise SevenScenesError(
                        f"{self.path / fname} lists sequence{n} but folder {folder} "
                        f"does not exist{hint}"
                    )
                owner[seq] = fname
                seqs.append(seq)
            self._sequences[split] = sorted(seqs)
        if not owner:
            raise SevenScenesError(f"the split files of {self.path} list no sequences")
        self._frames: dict[str, list[SevenScenesFrame]] = {
            split: [f for seq in seqs for f in self._scan(split, seq)]
            for split, seqs in self._sequences.items()
        }

    def _scan(self, split: str, seq: str) -> list[SevenScenesFrame]:
        """Frames of one sequence folder, by number; each needs its pose file (its depth image
        is optional: RGB-only data in this layout builds graphs the same way)."""
        folder = self.path / seq
        names = {e.name for e in os.scandir(folder)}
        found = []
        for name in names:
            m = _FRAME.fullmatch(name)
            if m:
                found.append((int(m.group(1)), name[: -len(".color.png")]))
        if not found:
            raise SevenScenesError(f"sequence folder {folder} holds no frame-*.color.png images")
        frames = []
        for idx, stem in sorted(found):
            if stem + ".pose.txt" not in names:
                raise SevenScenesError(
                    f"frame {folder / (stem + '.color.png')}: "
                    f"{folder / (stem + '.pose.txt')} is missing"
                )
            frames.append(
                SevenScenesFrame(
                    scene=self.name,
                    split=split,
                    sequence=seq,
                    index=idx,
                    color=folder / f"{stem}.color.png",
                    depth=(folder / f"{stem}.depth.png"
                           if stem + ".depth.png" in names else None),
                    pose=folder / f"{stem}.pose.txt",
                )
            )
        return frames

    def __repr__(self) -> str:
        n = {s: len(f) for s, f in self._frames.items()}
        return f"SevenScenesScene({str(self.path)!r}, train={n['train']}, test={n['test']})"

    @staticmethod
    def _check_split(split: str) -> str:
        if split not in SPLITS:
            raise SevenScenesError(f"split must be one of {sorted(SPLITS)}, got {split!r}")
        return split

    def sequences(self, split: str) -> list[str]:
        """Sequence folders of a split (``"train"`` / ``"test"``), e.g. ``["seq-01", ...]``."""
        return list(self._sequences[self._check_split(split)])

    def frames(self, split: str) -> list[SevenScenesFrame]:
        """Frames of a split, sorted by sequence then frame number."""
        return list(self._frames[self._check_split(split)])

    def camera_to_world(self, frame: SevenScenesFrame) -> np.ndarray:
        """``(4, 4)`` float64 camera-to-world pose of ``frame`` (validated, rigid)."""
        return _parse_pose(Path(frame.pose))

    def world_to_camera(self, frame: SevenScenesFrame) -> np.ndarray:
        """``(4, 4)`` world-to-camera pose ``x_cam = R X + t`` (OpenCV camera axes)."""
        T = self.camera_to_world(frame)
        out = np.eye(4)
        out[:3, :3] = T[:3, :3].T
        out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
        return out

    def K(self) -> np.ndarray:
        """``(3, 3)`` intrinsics."""
        return self._K.copy()


def _is_scene(path: Path) -> bool:
    return any((path / f).is_file() for f in SPLITS.values())


def open_sevenscenes(
    root: str | os.PathLike[str],
    scenes: str | Iterable[str] | None = None,
    intrinsics: object = None,
) -> list[SevenScenesScene]:
    """Scenes under a dataset ``root`` (or ``root`` itself when it is a scene folder).

    ``scenes`` picks folder names (in that order); default: every scene folder, by name.
    """
    root_p = Path(root)
    if not root_p.exists():
        raise SevenScenesError(f"7-Scenes root {root_p} does not exist")
    if not root_p.is_dir():
        raise SevenScenesError(f"7-Scenes root {root_p} is not a folder")
    _intrinsics_matrix(intrinsics)  # fail before scanning anything
    wanted: list[str] | None
    if scenes is None:
        wanted = None
    elif isinstance(scenes, str):
        wanted = [scenes]
    else:
        wanted = list(scenes)
        if not wanted:
            raise SevenScenesError(f"no scenes asked for under {root_p}")
    if _is_scene(root_p):
        found = {Path(os.path.abspath(root_p)).name: root_p}
    else:
        found = {p.name: p for p in sorted(root_p.iterdir()) if p.is_dir() and _is_scene(p)}
        if not found:
            raise SevenScenesError(
                f"{root_p} is not in 7-Scenes layout: no scene folders with "
                f"TrainSplit.txt/TestSplit.txt found"
            )
    if wanted is None:
        names: Sequence[str] = sorted(found)
    else:
        unknown = [n for n in wanted if n not in found]
        if unknown:
            raise SevenScenesError(
                f"scene(s) {unknown} not found under {root_p}; available: {sorted(found)}"
            )
        names = wanted
    return [SevenScenesScene(found[n], intrinsics) for n in names]

"""Read a dataset directory written by ``posernet-make-data``.

Layout: ``ROOT/manifest.json`` plus ``ROOT/<size>/<split>/<scene>.pt`` (``save_graphs`` files),
size in {small, large}, split in {train, val, test}. The manifest is written last, so a
directory without one is an incomplete (interrupted) run and is refused here.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..graph import ViewGraph, load_graphs
from .layout import MANIFEST, SIZES, SPLITS

__all__ = [
    "SIZES",
    "SPLITS",
    "DatasetError",
    "available_scenes",
    "open_split",
    "read_manifest",
]



class DatasetError(FileNotFoundError):
    """A dataset directory (or a file in it) is missing, incomplete or malformed."""


def read_manifest(root: str | os.PathLike[str]) -> dict[str, Any]:
    """The parsed ``ROOT/manifest.json``; clear errors naming the path otherwise."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"dataset directory not found: {root}")
    path = root / MANIFEST
    if not path.is_file():
        hint = (
            " (an interrupted posernet-make-data run? re-run it with resume=true)"
            if any(root.iterdir())
            else ""
        )
        raise DatasetError(f"{path}: missing, {root} is not a complete dataset{hint}")
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: malformed manifest ({exc})") from exc
    if not isinstance(manifest, dict) or not isinstance(manifest.get("splits"), dict):
        raise DatasetError(f"{path}: malformed manifest (no 'splits' table)")
    return manifest


def available_scenes(
    root: str | os.PathLike[str], size: str = "small", split: str = "train"
) -> list[str]:
    """Scenes that have ``size``/``split`` graphs according to the manifest."""
    _check(size, split)
    manifest = read_manifest(root)
    scenes = manifest["splits"].get(size, {}).get(split, [])
    return [str(s) for s in scenes]


def _check(size: str, split: str) -> None:
    if size not in SIZES:
        raise ValueError(f"size must be one of {list(SIZES)}, got {size!r}")
    if split not in SPLITS:
        raise ValueError(f"split must be one of {list(SPLITS)}, got {split!r}")


def open_split(
    root: str | os.PathLike[str],
    size: str = "small",
    split: str = "train",
    scenes: Sequence[str] | str | None = None,
) -> list[ViewGraph]:
    """All graphs of ``size``/``split`` (optionally only some ``scenes``), scene by scene.

    Returns an empty list when the dataset has no graphs of that size and split (e.g. no large
    validation graphs); an unknown scene or a missing file is an error naming the path.
    """
    _check(size, split)
    root = Path(root)
    have = available_scenes(root, size, split)
    if scenes is None:
        wanted = have
    else:
        wanted = [scenes] if isinstance(scenes, str) else list(scenes)
        every = set()
        for sz in SIZES:
            for sp in SPLITS:
                every.update(available_scenes(root, sz, sp))
        unknown = [s for s in wanted if s not in every]
        if unknown:
            raise DatasetError(
                f"{root}: unknown scene(s) {unknown}; the dataset has {sorted(every)}"
            )
        wanted = [s for s in wanted if s in have]
    graphs: list[ViewGraph] = []
    for scene in wanted:
        path = root / size / split / f"{scene}.pt"
        if not path.is_file():
            raise DatasetError(f"{path}: listed in the manifest but missing")
        graphs.extend(load_graphs(path))
    return graphs

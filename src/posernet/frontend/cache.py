"""On-disk cache of the image front end's work, so that an interrupted or repeated run resumes.

Layout (inside a run's output folder, ``<out_dir>/cache``)::

    cache/<options>/images/<image>.npz      proposals, keypoints, descriptors of one image
    cache/<options>/pairs/<a>_<b>.npz        matches and two-view verification of one pair
    cache/<options>/options.json             the front-end options the folder was made with

``<options>`` is a hash of every front-end option that changes a result (proposal, matcher,
box-matching, 5-point and verification settings, the seed): changing one starts a new folder
and removes the stale ones. ``<image>`` hashes the file's bytes (so an edited or replaced
image is recomputed, a renamed one is not) and ``<a>_<b>`` the two images' hashes plus their
intrinsics and distortion (a pair's geometry depends on them). Entries are written atomically
as they are computed: a run killed half-way keeps every finished image and pair. An entry that
cannot be read (truncated, other format) is a miss, recomputed and rewritten.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..io import atomic_write_bytes, atomic_write_json

__all__ = ["FrontendCache", "file_digest", "options_digest"]

log = logging.getLogger("posernet.frontend")

FORMAT = 2  # 2: a kept fallback edge also carries the main matcher's matches it explains


def file_digest(path: str | Path) -> str:
    """Hex digest of a file's bytes (blake2b, 20 hex characters)."""
    h = hashlib.blake2b(digest_size=10)
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def options_digest(options: Mapping[str, Any]) -> str:
    """Hex digest of JSON-able ``options`` (key order does not matter)."""
    text = json.dumps({"format": FORMAT, **options}, sort_keys=True, default=str)
    return hashlib.blake2b(text.encode(), digest_size=8).hexdigest()


def _array_digest(*arrays: np.ndarray | None) -> str:
    h = hashlib.blake2b(digest_size=6)
    for a in arrays:
        h.update(b"none" if a is None else np.ascontiguousarray(a, np.float64).tobytes())
    return h.hexdigest()


class FrontendCache:
    """Per-image and per-pair entries of one set of front-end ``options`` under ``root``.

    Entries are dictionaries of numpy arrays plus one JSON-able ``meta`` dictionary. Loading
    returns ``None`` on a miss (absent or unreadable entry); saving never raises on a full
    disk or a permission problem, it logs one warning and turns the cache off.
    """

    def __init__(self, root: str | Path, options: Mapping[str, Any]) -> None:
        self.root = Path(root)
        self.options = dict(options)
        self.key = options_digest(self.options)
        self.folder = self.root / self.key
        self.enabled = True
        self.hits = {"images": 0, "pairs": 0}
        try:
            if self.root.is_dir():
                for old in self.root.iterdir():
                    if old.is_dir() and old.name != self.key and (old / "options.json").is_file():
                        shutil.rmtree(old, ignore_errors=True)
            (self.folder / "images").mkdir(parents=True, exist_ok=True)
            (self.folder / "pairs").mkdir(parents=True, exist_ok=True)
            atomic_write_json(self.folder / "options.json",
                              {"format": FORMAT, "options": self.options})
        except OSError as exc:
            self._off(exc)

    def _off(self, exc: Exception) -> None:
        if self.enabled:
            log.warning("front-end cache in %s turned off: %s", self.root, exc)
        self.enabled = False

    # -------------------------------------------------------------- keys

    @staticmethod
    def pair_key(digest_a: str, digest_b: str, K_a: np.ndarray, K_b: np.ndarray,
                 dist_a: np.ndarray | None, dist_b: np.ndarray | None) -> str:
        """Entry name of a pair: both images' digests and their camera models."""
        return f"{digest_a}_{digest_b}_{_array_digest(K_a, K_b, dist_a, dist_b)}"

    # -------------------------------------------------------------- entries

    def _path(self, kind: str, name: str) -> Path:
        return self.folder / kind / f"{name}.npz"

    def load(self, kind: str, name: str) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None:
        """``(arrays, meta)`` of entry ``name`` of ``kind`` (``"images"`` or ``"pairs"``)."""
        if not self.enabled:
            return None
        path = self._path(kind, name)
        if not path.is_file():
            return None
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
            meta = json.loads(bytes(arrays.pop("__meta__")).decode())
        except Exception as exc:  # any unreadable entry is a miss
            log.warning("cache entry %s unreadable (%s); recomputing it", path, exc)
            return None
        self.hits[kind] += 1
        return arrays, meta

    def save(self, kind: str, name: str, arrays: Mapping[str, np.ndarray],
             meta: Mapping[str, Any]) -> None:
        """Write entry ``name`` atomically (``arrays``: no object arrays; ``meta``: JSON)."""
        if not self.enabled:
            return
        buf = io.BytesIO()
        blob = np.frombuffer(json.dumps(dict(meta), default=_json_default).encode(), np.uint8)
        try:
            np.savez(buf, __meta__=blob, **{k: np.asarray(v) for k, v in arrays.items()})
            atomic_write_bytes(self._path(kind, name), buf.getvalue())
        except OSError as exc:
            self._off(exc)


def _json_default(x: Any) -> Any:
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")

"""Deterministic random streams keyed by names, so results never depend on evaluation order.

Every random decision of the simulator draws from a stream identified by what it is about
(``seed``, scene, frame id, pair of frames ...). A frame or an image pair therefore looks the same
whichever graph, worker or chunk asks for it first, which makes the output bit-identical for
any number of worker processes.
"""

from __future__ import annotations

import zlib

import numpy as np

__all__ = ["key_int", "make_rng", "stream_seed"]


def key_int(key: object) -> int:
    """Stable 32-bit integer of an int or a string (``hash()`` is salted per process)."""
    if isinstance(key, bool | np.bool_):
        return int(key)
    if isinstance(key, int | np.integer):
        if key < 0:
            raise ValueError(f"seed keys must be non-negative, got {key}")
        return int(key)
    return zlib.crc32(str(key).encode("utf-8"))


def stream_seed(seed: int, *keys: object) -> np.random.SeedSequence:
    """SeedSequence for the stream named ``keys`` under the master ``seed``."""
    return np.random.SeedSequence([key_int(seed), *(key_int(k) for k in keys)])


def make_rng(seed: int, *keys: object) -> np.random.Generator:
    """Independent generator for the stream named ``keys`` (e.g. ``("chess", "frame", 12)``)."""
    return np.random.Generator(np.random.PCG64(stream_seed(seed, *keys)))

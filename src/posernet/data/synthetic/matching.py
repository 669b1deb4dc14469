"""Simulated keypoint matching between two images, and simulated box-matching mistakes.

* Keypoints (SuperGlue-like): a 3D keypoint detected in both images is matched with a
  probability that fades with the change of viewing direction and fails beyond a scale change;
  a fraction of matches is wrong (the second image's point is another keypoint).
* A few matched box pairs are re-assigned to a wrong box (:func:`reassign_wrong`).

The box-matching rules themselves (shared keypoints, span, edges) are the image front end's:
:mod:`posernet.frontend.boxmatch`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import KeypointOptions

__all__ = ["KeypointMatches", "match_keypoints", "reassign_wrong"]


@dataclass
class KeypointMatches:
    """Matched keypoints of two images: pixels ``uv_a, uv_b (M, 2)``; ``outlier (M,)`` marks
    wrong matches; ``ids (M,)`` the 3D keypoint seen in image a."""

    uv_a: np.ndarray
    uv_b: np.ndarray
    ids: np.ndarray
    outlier: np.ndarray


def match_keypoints(
    xyz: np.ndarray,
    owner: np.ndarray,
    twin: np.ndarray,
    ids_a: np.ndarray,
    uv_a: np.ndarray,
    centre_a: np.ndarray,
    ids_b: np.ndarray,
    uv_b: np.ndarray,
    centre_b: np.ndarray,
    opts: KeypointOptions,
    rng: np.random.Generator,
) -> KeypointMatches:
    """Match the keypoints detected in two images (sorted unique ``ids``, pixels ``uv``).

    ``xyz (P, 3)``, ``owner (P,)`` and ``twin (P,)`` describe the scene keypoints. A keypoint of
    image a is matched to the same 3D keypoint in image b, or, when its object is "confused" in
    this pair (probability ``opts.confusion`` for objects with a twin), to the look-alike
    keypoint of the twin: a consistent but wrong group of matches.
    """
    n_obj = int(owner.max()) + 1 if owner.size else 1
    u_conf = rng.random(n_obj)
    own_a = owner[ids_a]
    confused = (twin[ids_a] >= 0) & (u_conf[np.maximum(own_a, 0)] < opts.confusion)
    target = np.where(confused, twin[ids_a], ids_a)
    pos = np.searchsorted(ids_b, target)
    pos = np.minimum(pos, max(ids_b.size - 1, 0))
    ok = (ids_b.size > 0) & (ids_b[pos] == target) if ids_b.size else np.zeros(target.size, bool)
    ia = np.nonzero(ok)[0]
    ib = pos[ia]
    n = ia.size
    # fixed-size draws so the stream does not depend on what gets filtered
    u_match = rng.random(n)
    u_out = rng.random(n)
    if n == 0:
        z = np.zeros((0, 2))
        return KeypointMatches(z, z.copy(), np.zeros(0, np.int64), np.zeros(0, bool))
    Xa, Xb = xyz[ids_a[ia]], xyz[ids_b[ib]]
    ra, rb = centre_a - Xa, centre_b - Xb
    da, db = np.linalg.norm(ra, axis=1), np.linalg.norm(rb, axis=1)
    cos = (ra * rb).sum(1) / np.maximum(da * db, 1e-12)
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    ratio = np.maximum(da / db, db / da)
    # descriptor matching degrades smoothly with the viewpoint change, then fails
    p = opts.match_prob * np.clip(1.0 - (angle / opts.max_view_angle) ** 2, 0.0, 1.0)
    p = np.where(ratio <= opts.max_scale_change, p, 0.0)
    keep = u_match < p
    out = keep & (u_out < opts.outlier_rate)
    kb = ib.copy()
    n_out = int(out.sum())
    if n_out:
        # a wrong match lands on another keypoint of image b (similar-looking texture)
        kb[out] = rng.integers(0, uv_b.shape[0], size=n_out)
    wrong = (out & (kb != ib)) | confused[ia]
    return KeypointMatches(
        uv_a=uv_a[ia[keep]], uv_b=uv_b[kb[keep]], ids=ids_a[ia[keep]], outlier=wrong[keep]
    )


def reassign_wrong(
    ia: np.ndarray, ib: np.ndarray, n_boxes_b: int, rate: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Re-assign each matched pair with probability ``rate`` to a random other box of image b.

    Returns ``(ia, ib, wrong)``; duplicates created by the re-assignment are dropped.
    """
    u = rng.random(ia.size)
    shift = rng.integers(1, max(n_boxes_b, 2), size=ia.size)
    wrong = (u < rate) & (n_boxes_b > 1)
    ib = np.where(wrong, (ib + shift) % max(n_boxes_b, 1), ib)
    key = ia * max(n_boxes_b, 1) + ib
    _, first = np.unique(key, return_index=True)
    first.sort()
    return ia[first], ib[first], wrong[first]

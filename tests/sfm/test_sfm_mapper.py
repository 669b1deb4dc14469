"""The mapper's doubt about a start: a camera collapsed onto its neighbour is one, a long
regular sequence is not, nor a spot the sequence revisits where the two views saw no
baseline."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from posernet.pinhole import look_at
from posernet.sfm.bundle import BundleOptions
from posernet.sfm.mapper import _doubts, baseline_pairs


def _result(centres: np.ndarray, pairs: np.ndarray) -> SimpleNamespace:
    """An adjustment's result with every camera refined, looking at the origin, and 20
    points near it seen by every camera."""
    n = centres.shape[0]
    w2c = look_at(centres, np.zeros_like(centres), up=np.array([0.0, 1.0, 0.0]))
    pts = np.random.default_rng(0).normal(0, 0.3, (20, 3))
    obs_image = np.repeat(np.arange(n), 20)
    obs_point = np.tile(np.arange(20), n)
    return SimpleNamespace(refined=np.ones(n, bool), w2c=w2c, points=pts,
                           obs_image=obs_image, obs_point=obs_point,
                           tracks=SimpleNamespace(track=obs_point), stats={}), pairs


def _ring(n: int, moved: float | None = None) -> tuple[SimpleNamespace, np.ndarray]:
    a = 2 * np.pi * np.arange(n) / n
    c = np.stack([4 * np.sin(a), np.zeros(n), 4 * np.cos(a)], 1)
    if moved is not None:  # camera 1 onto camera 2, at this share of the spacing
        c[1] = c[2] + moved * (c[1] - c[2])
    pairs = np.array([(i, (i + k) % n) for i in range(n) for k in (1, 2, 3)])
    return _result(c, pairs)


def test_a_camera_collapsed_onto_its_neighbour_is_a_doubt() -> None:
    opt = BundleOptions()
    ring, pairs = _ring(36)
    assert "camera centres coincide" not in _doubts(ring, np.ones(36, bool), opt, pairs)
    # 6 % of the spacing: 2.1 % of the median distance over matched pairs, which a test
    # against 2 % of that median let through
    ring, pairs = _ring(36, moved=0.06)
    assert "camera centres coincide" in _doubts(ring, np.ones(36, bool), opt, pairs)


def test_a_long_regular_sequence_is_no_doubt() -> None:
    n = 1024
    c = np.stack([0.05 * np.arange(n), np.zeros(n), np.full(n, -4.0)], 1)
    pairs = np.array([(i, i + 2 ** k) for i in range(n) for k in range(4) if i + 2 ** k < n])
    r, pairs = _result(c, pairs)
    r.w2c = look_at(c, c + np.array([0.0, 0.0, 4.0]), up=np.array([0.0, 1.0, 0.0]))
    assert "camera centres coincide" not in _doubts(r, np.ones(n, bool), BundleOptions(), pairs)


def test_a_revisited_spot_with_a_rotation_only_pair_is_no_doubt() -> None:
    """A sequence that passes one spot twice (frames 10 and 30, 5 mm apart, as in a rendered
    room sequence): their pair, verified as rotation-only, leaves the start alone; the same
    pair with a baseline in its two-view geometry is a collapse."""
    n = 40
    a = 2 * np.pi * np.arange(n) / n * 0.9
    c = np.stack([4 * np.sin(a), 0.01 * np.arange(n), 4 * np.cos(a)], 1)
    c[30] = c[10] + np.array([0.005, 0.0, 0.0])
    seq = {(i, i + 1): np.zeros((30, 2), np.int64) for i in range(n - 1)}
    matches = {**seq, (30, 10): np.zeros((300, 2), np.int64), (3, 5): np.zeros((0, 2))}
    r, _ = _result(c, np.zeros((0, 2), np.int64))
    opt = BundleOptions()
    with_baseline = baseline_pairs(matches)
    assert len(with_baseline) == n  # the empty pair (3, 5) is not matched
    assert "camera centres coincide" in _doubts(r, np.ones(n, bool), opt, with_baseline)
    no_baseline = baseline_pairs(matches, rotation_only=[(10, 30)])  # either order
    assert len(no_baseline) == n - 1
    assert "camera centres coincide" not in _doubts(r, np.ones(n, bool), opt, no_baseline)

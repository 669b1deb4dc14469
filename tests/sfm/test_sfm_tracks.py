"""Tracks from pairwise matches: union of matches, inconsistent and malformed input."""

from __future__ import annotations

import numpy as np
import pytest

from posernet.sfm import build_tracks
from posernet.sfm.synthetic import make_scene


def _track_points(scene, tracks) -> list[set[int]]:
    """The true 3D point ids seen by each track."""
    pid = np.array([scene.kp_point[i][k] for i, k in zip(tracks.image, tracks.keypoint,
                                                          strict=True)])
    return [set(pid[tracks.track == t].tolist()) for t in range(tracks.num_tracks)]


def test_tracks_from_synthetic_matches_are_the_points() -> None:
    scene = make_scene(num_cameras=6, num_points=150, seed=1)
    tracks = build_tracks(scene.pair_matches, [len(u) for u in scene.uv])
    # Every track is one 3D point, every point seen by >= 2 images is one track.
    assert all(len(s) == 1 for s in _track_points(scene, tracks))
    seen = np.bincount(scene.obs_point, minlength=150)
    assert tracks.num_tracks == int((seen >= 2).sum())
    assert tracks.dropped == {"inconsistent": 0, "single_view": 0, "conflicting_views": 0}
    # Sorted by (track, image), one observation per image per track.
    key = tracks.track * 100 + tracks.image
    assert np.all(np.diff(key) > 0)
    assert tracks.length.sum() == tracks.num_observations
    assert tracks.observations_per_image().sum() == tracks.num_observations
    assert "tracks:" in tracks.lines()[0]


def test_inconsistent_track_is_dropped_and_others_kept() -> None:
    # Track A: img0 kp0 - img1 kp0 - img2 kp0; a wrong match img2 kp0 - img0 kp1 closes a loop
    # onto another keypoint of image 0. Track B: img0 kp2 - img1 kp1 (clean).
    matches = {
        (0, 1): np.array([[0, 0], [2, 1]]),
        (1, 2): np.array([[0, 0]]),
        (0, 2): np.array([[1, 0]]),
    }
    tracks = build_tracks(matches, [3, 2, 1], resolve_conflicts=False)
    assert tracks.dropped["inconsistent"] == 1
    assert tracks.num_tracks == 1
    assert sorted(zip(tracks.image.tolist(), tracks.keypoint.tolist(), strict=True)) == \
        [(0, 2), (1, 1)]


def test_inconsistent_match_in_synthetic_scene() -> None:
    scene = make_scene(num_cameras=5, num_points=100, seed=2)
    clean = build_tracks(scene.pair_matches, [len(u) for u in scene.uv])
    # Link a keypoint of point p in image 0 to a keypoint of another point q in image 1,
    # where q is also seen in image 0: the merged track has two keypoints of image 0.
    k0 = {int(p): k for k, p in enumerate(scene.kp_point[0])}
    k1 = {int(p): k for k, p in enumerate(scene.kp_point[1])}
    common = sorted(set(k0) & set(k1))
    p, q = common[0], common[1]
    bad = dict(scene.pair_matches)
    bad[(0, 1)] = np.vstack((bad[(0, 1)], [[k0[p], k1[q]]]))
    tracks = build_tracks(bad, [len(u) for u in scene.uv], resolve_conflicts=False)
    # p and q merge into one track, which is dropped as a whole.
    assert tracks.dropped["inconsistent"] == 1
    assert tracks.num_tracks == clean.num_tracks - 2
    assert all(len(s) == 1 for s in _track_points(scene, tracks))


def test_empty_and_malformed_matches() -> None:
    empty = build_tracks({}, [3, 4])
    assert empty.num_tracks == 0 and empty.num_observations == 0
    assert build_tracks({(0, 1): np.zeros((0, 2), int)}, [3, 4]).num_tracks == 0
    with pytest.raises(ValueError, match="out of range"):
        build_tracks({(0, 1): np.array([[0, 5]])}, [3, 4])
    with pytest.raises(ValueError, match="out of range"):
        build_tracks({(0, 2): np.array([[0, 0]])}, [3, 4])
    with pytest.raises(ValueError, match="itself"):
        build_tracks({(1, 1): np.array([[0, 1]])}, [3, 4])
    with pytest.raises(ValueError, match="integer"):
        build_tracks({(0, 1): np.array([[0.0, 1.0]])}, [3, 4])
    with pytest.raises(ValueError, match=r"\(M, 2\)"):
        build_tracks({(0, 1): np.array([0, 1, 2])}, [3, 4])


def test_duplicate_and_reversed_matches_merge() -> None:
    # The same match listed twice and in both directions gives one two-view track.
    matches = {(0, 1): np.array([[1, 2], [1, 2]]), (1, 0): np.array([[2, 1]])}
    tracks = build_tracks(matches, [2, 3])
    assert tracks.num_tracks == 1
    assert tracks.image.tolist() == [0, 1] and tracks.keypoint.tolist() == [1, 2]


def test_conflicts_are_resolved_by_match_count() -> None:
    """A wrong match links keypoint 3 of image 0 into a track whose true keypoint 0 of image 0
    is matched in three pairs: keypoint 3 leaves, the rest of the track stays."""
    matches = {
        (0, 1): np.array([[0, 0]]),
        (0, 2): np.array([[0, 0]]),
        (0, 3): np.array([[0, 0]]),
        (1, 2): np.array([[0, 0]]),
        (2, 3): np.array([[0, 0]]),
        (1, 4): np.array([[0, 0]]),
        (0, 4): np.array([[3, 0]]),  # wrong: image 0 keypoint 3
    }
    tracks = build_tracks(matches, [4, 1, 1, 1, 1])
    assert tracks.num_tracks == 1 and tracks.dropped["conflicting_views"] == 1
    assert sorted(zip(tracks.image.tolist(), tracks.keypoint.tolist(), strict=True)) == \
        [(0, 0), (1, 0), (2, 0), (3, 0), (4, 0)]
    # without resolution the whole track goes
    strict = build_tracks(matches, [4, 1, 1, 1, 1], resolve_conflicts=False)
    assert strict.num_tracks == 0 and strict.dropped["inconsistent"] == 1

"""Feature tracks: chain verified pairwise keypoint matches into multi-view observations.

A node is one keypoint of one image, ``(image, keypoint)``. Every verified match links two
nodes; the connected components of that graph are the tracks (the union-find of classic SfM,
computed here in one call to :func:`scipy.sparse.csgraph.connected_components`). A track that
holds two different keypoints of the same image is in conflict: some match in the chain is
wrong. The keypoint linked by strictly the most matches in that image stays, the others leave
the track (``conflicting_views`` counts them; a tie removes them all), the track is split
where that cut it, and a track still in conflict is dropped as a whole (``inconsistent``). A
track seen by one image only cannot be triangulated and is dropped too.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

__all__ = ["Tracks", "build_tracks"]


@dataclass(frozen=True)
class Tracks:
    """Observations of all tracks as flat arrays, sorted by track then image.

    ``track, image, keypoint (O,)`` int64: observation ``o`` says keypoint ``keypoint[o]`` of
    image ``image[o]`` belongs to track ``track[o]`` (``0..num_tracks-1``). ``length (T,)``:
    views per track. ``dropped`` counts the tracks removed and why (``"inconsistent"``: two
    keypoints of one image, ``"single_view"``) and ``"conflicting_views"`` the keypoints that
    left a track to resolve a conflict; ``num_matches`` the match rows read.
    """

    track: np.ndarray
    image: np.ndarray
    keypoint: np.ndarray
    num_tracks: int
    num_images: int
    length: np.ndarray
    dropped: dict[str, int] = field(default_factory=dict)
    num_matches: int = 0

    @property
    def num_observations(self) -> int:
        return int(self.track.size)

    def observations_per_image(self) -> np.ndarray:
        """``(N,)`` number of track observations in each image."""
        return np.bincount(self.image, minlength=self.num_images)

    def lines(self) -> list[str]:
        """Human-readable summary, one fact per line."""
        mean = float(self.length.mean()) if self.num_tracks else 0.0
        return [
            f"tracks: {self.num_tracks} from {self.num_matches} matches "
            f"({self.num_observations} observations, {mean:.2f} views per track)",
            "dropped tracks: " + (", ".join(f"{k} {v}" for k, v in self.dropped.items())
                                  or "none"),
        ]


def _check_matches(pair_matches: Mapping[tuple[int, int], np.ndarray],
                   num_keypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate the matches; returns the two global node ids of every match row, ``(M,)`` each."""
    n_img = num_keypoints.size
    offset = np.concatenate(([0], np.cumsum(num_keypoints)))
    left, right = [], []
    for key, m in pair_matches.items():
        a, b = (int(key[0]), int(key[1]))
        if not (0 <= a < n_img and 0 <= b < n_img):
            raise ValueError(f"pair_matches key {key}: image index out of range 0..{n_img - 1}")
        if a == b:
            raise ValueError(f"pair_matches key {key}: an image cannot be matched to itself")
        arr = np.asarray(m)
        if arr.size == 0:
            continue
        if arr.ndim != 2 or arr.shape[1] != 2 or not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f"pair_matches[{key}] must be an (M, 2) integer array, got "
                             f"{arr.dtype} {arr.shape}")
        if (arr < 0).any() or (arr[:, 0] >= num_keypoints[a]).any() or \
                (arr[:, 1] >= num_keypoints[b]).any():
            raise ValueError(f"pair_matches[{key}]: keypoint index out of range (image {a} has "
                             f"{num_keypoints[a]} keypoints, image {b} has {num_keypoints[b]})")
        left.append(offset[a] + arr[:, 0].astype(np.int64))
        right.append(offset[b] + arr[:, 1].astype(np.int64))
    if not left:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(left), np.concatenate(right)


def _components(n_nodes: int, a: np.ndarray, b: np.ndarray) -> tuple[int, np.ndarray]:
    graph = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(n_nodes, n_nodes))
    return connected_components(graph, directed=False)


def _groups(comp: np.ndarray, image: np.ndarray, n_img: int) -> tuple[np.ndarray, np.ndarray]:
    """Per node: its (component, image) group id and the size of that group."""
    key = comp.astype(np.int64) * n_img + image
    _, key_inv, key_count = np.unique(key, return_inverse=True, return_counts=True)
    return key_inv, key_count[key_inv]


def build_tracks(pair_matches: Mapping[tuple[int, int], np.ndarray],
                 num_keypoints: Sequence[int] | np.ndarray,
                 resolve_conflicts: bool = True) -> Tracks:
    """Tracks from verified pairwise matches.

    ``pair_matches[(a, b)]``: ``(M, 2)`` int array, row = (keypoint in image a, keypoint in
    image b); ``num_keypoints (N,)``: keypoints per image (the node count). With
    ``resolve_conflicts`` a track holding several keypoints of one image keeps the one linked
    by strictly the most matches and loses the others (a tie loses them all), the track splits
    where that cut it, and only what is still inconsistent is dropped (module docstring).
    Raises ValueError on malformed input (bad key, index out of range, self pair). Vectorised:
    sparse connected components, no loop over matches.
    """
    nk = np.asarray(num_keypoints, dtype=np.int64).reshape(-1)
    if (nk < 0).any():
        raise ValueError("num_keypoints must be non-negative")
    n_img = nk.size
    src, dst = _check_matches(pair_matches, nk)
    empty = np.zeros(0, np.int64)
    if src.size == 0:
        return Tracks(empty, empty, empty, 0, n_img, empty,
                      {"inconsistent": 0, "single_view": 0, "conflicting_views": 0}, 0)
    # Only nodes touched by a match take part: compress them to 0..V-1 first.
    nodes, inv = np.unique(np.concatenate((src, dst)), return_inverse=True)
    n_nodes = nodes.size
    a, b = inv[: src.size], inv[src.size:]
    offset = np.concatenate(([0], np.cumsum(nk)))
    image = np.searchsorted(offset, nodes, side="right") - 1
    keypoint = nodes - offset[image]
    n_comp, comp = _components(n_nodes, a, b)
    group, count = _groups(comp, image, n_img)
    alive = np.ones(n_nodes, bool)
    if resolve_conflicts and (count > 1).any():
        # In a conflicting (track, image) group the true keypoint is usually the one matched
        # in many pairs; a wrong match links its keypoint once.
        degree = np.bincount(a, minlength=n_nodes) + np.bincount(b, minlength=n_nodes)
        best = np.zeros(group.max() + 1, np.int64)
        np.maximum.at(best, group, degree)
        n_best = np.bincount(group, weights=(degree == best[group]), minlength=best.size)
        alive = (count == 1) | ((degree == best[group]) & (n_best[group] == 1))
        live_edge = alive[a] & alive[b]
        n_comp, comp = _components(n_nodes, a[live_edge], b[live_edge])
        group, count = _groups(comp, image, n_img)
    conflicting = int((~alive).sum())
    bad = np.zeros(n_comp, bool)
    bad[comp[alive & (count > 1)]] = True
    size = np.bincount(comp[alive], minlength=n_comp)
    single = (size < 2) & ~bad
    keep_comp = ~bad & ~single & (size > 0)
    # Relabel kept components 0..T-1, then sort observations by (track, image).
    new_id = np.full(n_comp, -1, np.int64)
    new_id[keep_comp] = np.arange(int(keep_comp.sum()))
    tr = new_id[comp]
    keep = (tr >= 0) & alive
    tr, image, keypoint = tr[keep], image[keep], keypoint[keep]
    order = np.lexsort((image, tr))
    tr, image, keypoint = tr[order], image[order].astype(np.int64), keypoint[order]
    n_tracks = int(keep_comp.sum())
    return Tracks(track=tr, image=image, keypoint=keypoint.astype(np.int64),
                  num_tracks=n_tracks, num_images=n_img,
                  length=np.bincount(tr, minlength=n_tracks),
                  dropped={"inconsistent": int(bad.sum()),
                           "single_view": int((single & (size > 0)).sum()),
                           "conflicting_views": conflicting},
                  num_matches=int(src.size))

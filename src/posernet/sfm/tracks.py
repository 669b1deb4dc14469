"""Feature tracks: chain verified pairwise keypoint matches into multi-view observations.

A node is one keypoint of one image, ``(image, keypoint)``. Every verified match links two
nodes; the connected components of that graph are the tracks (the union-find of classic SfM,
computed here in one call to :func:`scipy.sparse.csgraph.connected_components`). A component
that holds two different keypoints of the same image is in conflict: some match in its chain is
wrong, or slid to a neighbouring keypoint. Dense detectors (XFeat: thousands of keypoints a few
pixels apart along the few edges of a weakly textured scene) chain such slides into components
of hundreds of keypoints, so conflicts are resolved by rebuilding each conflicting component
with a union-find that refuses any merge putting two keypoints of one image into one track,
taking first the matches that close the most triangles (a third keypoint matched to both ends)
and then those between the most often matched keypoints. A component thus splits into
consistent tracks instead of losing all its keypoints; keypoints left alone count as
``conflicting_views``. Without resolution a component in conflict is dropped as a whole
(``inconsistent``). A track seen by one image only cannot be triangulated and is dropped too.
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


def _merge_order(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Order in which to try the edges ``a[e] - b[e]`` of ``n`` nodes: most triangles closed
    (common neighbours of the two ends) first, then the larger smaller-degree of the two ends,
    then input order."""
    adj = coo_matrix((np.ones(2 * a.size), (np.r_[a, b], np.r_[b, a])), shape=(n, n)).tocsr()
    adj.data[:] = 1.0  # repeated matches count once
    support = np.asarray(adj[a].multiply(adj[b]).sum(1)).ravel()
    degree = np.asarray(adj.sum(1)).ravel()
    return np.lexsort((np.arange(a.size), -np.minimum(degree[a], degree[b]), -support))


def _consistent_components(n: int, a: np.ndarray, b: np.ndarray,
                           image: np.ndarray) -> np.ndarray:
    """Component label per node of a union-find over the edges (in :func:`_merge_order`) that
    never merges two components holding keypoints of the same image."""
    parent = list(range(n))
    images = [1 << int(i) for i in image]  # image set of each root, as a bit mask
    size = [1] * n

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for e in _merge_order(n, a, b).tolist():
        ra, rb = find(int(a[e])), find(int(b[e]))
        if ra == rb or images[ra] & images[rb]:
            continue
        if size[ra] < size[rb]:
            ra, rb = rb, ra
        parent[rb] = ra
        size[ra] += size[rb]
        images[ra] |= images[rb]
    return np.fromiter((find(x) for x in range(n)), np.int64, n)


def _resolve(comp: np.ndarray, n_comp: int, a: np.ndarray, b: np.ndarray, image: np.ndarray,
             n_img: int) -> tuple[int, np.ndarray]:
    """Rebuild the components that hold two keypoints of one image with
    :func:`_consistent_components`; the others keep their labels."""
    _, count = _groups(comp, image, n_img)
    bad = np.zeros(n_comp, bool)
    bad[comp[count > 1]] = True
    node = bad[comp]
    edge = node[a]  # both ends share a component
    sub = np.flatnonzero(node)
    local = np.full(comp.size, -1, np.int64)
    local[sub] = np.arange(sub.size)
    lab = _consistent_components(sub.size, local[a[edge]], local[b[edge]], image[sub])
    out = comp.astype(np.int64).copy()
    _, lab = np.unique(lab, return_inverse=True)
    out[sub] = n_comp + lab
    _, out = np.unique(out, return_inverse=True)
    return int(out.max()) + 1, out


def build_tracks(pair_matches: Mapping[tuple[int, int], np.ndarray],
                 num_keypoints: Sequence[int] | np.ndarray,
                 resolve_conflicts: bool = True) -> Tracks:
    """Tracks from verified pairwise matches.

    ``pair_matches[(a, b)]``: ``(M, 2)`` int array, row = (keypoint in image a, keypoint in
    image b); ``num_keypoints (N,)``: keypoints per image (the node count). With
    ``resolve_conflicts`` a component holding several keypoints of one image is rebuilt into
    consistent tracks (module docstring); without, it is dropped. Raises ValueError on
    malformed input (bad key, index out of range, self pair). Vectorised (sparse connected
    components) except the rebuild of conflicting components, a union-find over their matches.
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
    _, count = _groups(comp, image, n_img)
    alive = np.ones(n_nodes, bool)
    if resolve_conflicts and (count > 1).any():
        n_comp, comp = _resolve(comp, n_comp, a, b, image, n_img)
        _, count = _groups(comp, image, n_img)
        alive = np.bincount(comp, minlength=n_comp)[comp] > 1  # a keypoint every merge refused
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

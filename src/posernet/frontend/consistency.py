"""Checks of the verified pairs against each other, before the view graph is built.

Two-view verification judges one pair at a time, so it passes geometry that is self-consistent
but wrong: a learned matcher pairing up the two sides of a textureless object, a repetitive
facade matched one bay off, a pose fitted on matches crowded on the only textured patch. Such
edges poison motion averaging. Two cheap checks catch most of them once every pair is known:

* **Crowded inliers** (:func:`posernet.frontend.verify.inlier_spread`): inliers covering a tiny
  part of either image fix the relative pose badly (a narrow field of view confuses rotation
  and translation); the pair is rejected with reason ``crowded``.
* **Loop consistency** (:func:`loop_outliers`): around every triangle of edges the relative
  rotations must compose to the identity, ``R_ac^T R_bc R_ab ~ I``. A wrong edge breaks every
  triangle it is on while a right edge breaks only those that share a wrong one, so an edge
  that breaks most of its triangles (weighted by the inlier counts of the triangle's other two
  edges), and at least two, is rejected with reason ``loop``, the worst first, again until
  none is left. Edges on no triangle cannot be judged and are kept.

:func:`screen_edges` applies both to verified pairs and returns what it rejects; the
:class:`~posernet.frontend.pipeline.ImageFrontend` books those like any other rejection
(pair status, ``reason``, summary).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .verify import VerifyRules, inlier_spread

__all__ = ["MIN_INCONSISTENT", "LoopCheck", "Screening", "cycle_errors", "loop_outliers",
           "screen_edges", "triangles"]

#: an edge is judged wrong only on two or more inconsistent triangles: one alone says that one
#: of its three edges is wrong, not which (on sparse rings, guessing lost right edges)
MIN_INCONSISTENT = 2


def triangles(edges: np.ndarray, num_nodes: int) -> np.ndarray:
    """Every triangle of the undirected graph ``edges (E, 2)`` as the ids of its three edges
    ``(T, 3)``, ordered ``(ab, bc, ac)`` for nodes ``a, b, c`` (in an order of the nodes by
    degree, so each triangle comes once).

    Each edge points from its lower- to its higher-ranked node (rank: degree, then id); a
    triangle is a path ``a -> b -> c`` closed by the edge ``a -> c``. Only these paths are
    expanded, ``O(E^1.5)`` in all, with no Python loop.
    """
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    E = edges.shape[0]
    if E < 3:
        return np.zeros((0, 3), np.int64)
    deg = np.bincount(edges.ravel(), minlength=num_nodes)
    rank = np.empty(num_nodes, np.int64)
    rank[np.lexsort((np.arange(num_nodes), deg))] = np.arange(num_nodes)
    lo = rank[edges[:, 0]] > rank[edges[:, 1]]
    src = np.where(lo, edges[:, 1], edges[:, 0])
    dst = np.where(lo, edges[:, 0], edges[:, 1])
    order = np.lexsort((dst, src))  # oriented edges as CSR rows, sorted within each row
    src, dst = src[order], dst[order]
    indptr = np.concatenate(([0], np.cumsum(np.bincount(src, minlength=num_nodes))))
    # every path a -> b -> c: first edge k (a -> b), second edge at position p (b -> c)
    out = indptr[dst + 1] - indptr[dst]
    first = np.repeat(np.arange(E), out)
    if first.size == 0:
        return np.zeros((0, 3), np.int64)
    start = np.repeat(indptr[dst] - (np.cumsum(out) - out), out)
    second = start + np.arange(first.size)
    a, c = src[first], dst[second]
    # the closing edge a -> c, looked up among the sorted (src, dst) codes
    code = src * num_nodes + dst
    want = a * num_nodes + c
    at = np.minimum(np.searchsorted(code, want), E - 1)
    hit = code[at] == want
    tri = np.stack([first[hit], second[hit], at[hit]], axis=1)
    return order[tri]


def cycle_errors(R: np.ndarray, edges: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Rotation error (degrees) around each triangle ``tri (T, 3)`` of edge ids, for edges
    ``(E, 2)`` ``i -> j`` with rotations ``R (E, 3, 3)`` taking camera ``i``'s frame to
    ``j``'s: the angle of the product of the three rotations along the loop (0 when they
    agree)."""
    if tri.shape[0] == 0:
        return np.zeros(0)
    R = np.asarray(R, np.float64)
    edges = np.asarray(edges, np.int64)
    e = edges[tri]  # (T, 3, 2)
    # nodes a -> b -> c -> a: b is shared by the first two edges
    x0, y0, x1, y1 = e[:, 0, 0], e[:, 0, 1], e[:, 1, 0], e[:, 1, 1]
    b = np.where((x0 == x1) | (x0 == y1), x0, y0)
    a = np.where(b == x0, y0, x0)
    c = np.where(x1 == b, y1, x1)
    loop = np.broadcast_to(np.eye(3), (tri.shape[0], 3, 3)).copy()
    for k, frm in enumerate((a, b, c)):
        Rk = R[tri[:, k]]
        fwd = e[:, k, 0] == frm  # an edge met head first is walked inverted
        Rk = np.where(fwd[:, None, None], Rk, np.transpose(Rk, (0, 2, 1)))
        loop = Rk @ loop
    cos = (np.trace(loop, axis1=1, axis2=2) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


@dataclass
class LoopCheck:
    """Outcome of :func:`loop_outliers`, per edge ``(E,)``: ``rejected``; ``triangles`` the
    edge is on; ``inconsistent`` of them; ``share`` the weighted share of inconsistent ones
    when it was judged (NaN: on no triangle); and ``errors (T,)`` of all ``tri (T, 3)``."""

    rejected: np.ndarray
    triangles: np.ndarray
    inconsistent: np.ndarray
    share: np.ndarray
    tri: np.ndarray
    errors: np.ndarray


def loop_outliers(edges: np.ndarray, R: np.ndarray, weight: np.ndarray, num_nodes: int,
                  max_deg: float = 6.0, max_share: float = 0.5) -> LoopCheck:
    """Edges whose rotation contradicts the graph's triangles.

    ``edges (E, 2)`` ``i -> j``, rotations ``R (E, 3, 3)`` (camera ``i`` to ``j``), ``weight
    (E,)`` evidence (inlier counts). A triangle is inconsistent when its loop error exceeds
    ``max_deg``. In a triangle an edge is judged by the other two, so its vote counts
    ``min(weight)`` of those two; an edge whose inconsistent votes exceed ``max_share`` of its
    votes, on at least :data:`MIN_INCONSISTENT` inconsistent triangles, is a candidate. The
    candidate most to blame in each inconsistent triangle (highest share, then most
    inconsistent triangles, then weakest) is rejected, its triangles are dropped, and the
    shares recomputed until no candidate is left: a right edge that shared triangles with a
    wrong one is cleared once the wrong one is gone.
    """
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    E = edges.shape[0]
    w = np.maximum(np.asarray(weight, np.float64).reshape(E), 1e-9)
    tri = triangles(edges, num_nodes)
    err = cycle_errors(R, edges, tri)
    bad = err > max_deg
    # each edge's vote in a triangle: the weaker of the other two edges
    wt = w[tri]
    vote = np.stack([np.minimum(wt[:, 1], wt[:, 2]), np.minimum(wt[:, 0], wt[:, 2]),
                     np.minimum(wt[:, 0], wt[:, 1])], axis=1)
    n_tri = np.bincount(tri.ravel(), minlength=E)
    n_bad = np.bincount(tri[bad].ravel(), minlength=E)
    rejected = np.zeros(E, bool)
    alive_t = np.ones(tri.shape[0], bool)
    share = np.full(E, np.nan)
    while True:
        tot = np.bincount(tri[alive_t].ravel(), vote[alive_t].ravel(), minlength=E)
        neg = np.bincount(tri[alive_t & bad].ravel(), vote[alive_t & bad].ravel(),
                          minlength=E)
        judged = tot > 0
        share = np.where(judged, neg / np.where(judged, tot, 1.0), np.nan)
        n_neg = np.bincount(tri[alive_t & bad].ravel(), minlength=E)
        cand = (judged & ~rejected & (np.nan_to_num(share) > max_share)
                & (n_neg >= MIN_INCONSISTENT))
        if not cand.any():
            break
        # most to blame per inconsistent triangle: the candidate with the highest share, then
        # the most inconsistent triangles, then the weakest
        rank = np.empty(E, np.int64)
        rank[np.lexsort((-w, n_neg, np.nan_to_num(share)))] = np.arange(E)
        rank = np.where(cand, rank, -1)
        t_bad = tri[alive_t & bad]
        blamed = t_bad[np.arange(t_bad.shape[0]), np.argmax(rank[t_bad], axis=1)]
        drop = np.zeros(E, bool)
        drop[blamed] = True
        drop &= cand
        rejected |= drop
        alive_t &= ~rejected[tri].any(axis=1)
    return LoopCheck(rejected=rejected, triangles=n_tri, inconsistent=n_bad, share=share,
                     tri=tri, errors=err)


def _edge_pose(p: Any, estimate: str) -> tuple[np.ndarray, np.ndarray] | None:
    """The pose a pair's edge carries in the graph (as graph assembly picks it)."""
    first, other = (p.kp, p.bb) if estimate == "kp" else (p.bb, p.kp)
    return first if first is not None else other


@dataclass(frozen=True)
class Screening:
    """What :func:`screen_edges` found: ``rejected`` ``(edge, reason)`` in the order judged
    (reason ``crowded`` or ``loop``) and ``triangles`` the loop check looked at."""

    rejected: tuple[tuple[Any, str], ...]
    triangles: int

    def counts(self) -> dict[str, int]:
        """``{"crowded": n, "loop": n, "triangles": n}``."""
        reasons = [r for _, r in self.rejected]
        return {"crowded": reasons.count("crowded"), "loop": reasons.count("loop"),
                "triangles": self.triangles}


def screen_edges(edges: Sequence[Any], uv: Callable[[int], np.ndarray],
                 sizes: Sequence[tuple[int, int] | None], estimate: str,
                 rules: VerifyRules) -> Screening:
    """Judge the verified ``edges`` (pair results: ``a``, ``b``, ``inliers [k, 2]`` keypoint
    indices, ``kp`` / ``bb`` poses, ``info``): those whose inliers are crowded on a small part
    of either image, then those that contradict the triangles of the rest (see the module
    docstring). ``uv(i)`` gives image ``i``'s keypoints ``[K, 2]``, ``sizes[i]`` its
    ``(width, height)`` (``None``: unknown, no spread test), ``estimate`` the pose an edge
    carries (``kp`` / ``bb``).

    Each judged edge records its inlier spread and loop numbers in its ``info``; nothing else
    changes: the caller books the rejections (status, reason, counts).
    """
    rejected: list[tuple[Any, str]] = []
    kept = []
    for p in edges:
        sp = _spread(p, uv, sizes)
        if sp is not None:
            p.info["spread"] = round(sp, 4)
        if sp is not None and sp < rules.min_spread:
            rejected.append((p, "crowded"))
        else:
            kept.append(p)
    poses = [_edge_pose(p, estimate) for p in kept]
    if rules.max_loop_deg <= 0 or len(kept) < 3 or any(q is None for q in poses):
        return Screening(tuple(rejected), 0)
    pairs = np.array([(p.a, p.b) for p in kept], np.int64)
    R = np.stack([np.asarray(q[0], np.float64) for q in poses])
    weight = np.array([0 if p.inliers is None else len(p.inliers) for p in kept], np.float64)
    weight = np.where(weight > 0, weight, float(rules.min_inliers))
    chk = loop_outliers(pairs, R, weight, len(sizes), rules.max_loop_deg, rules.max_loop_share)
    for k, p in enumerate(kept):
        if chk.triangles[k]:
            p.info["loop_triangles"] = int(chk.triangles[k])
            p.info["loop_inconsistent"] = int(chk.inconsistent[k])
        if chk.rejected[k]:
            rejected.append((p, "loop"))
    return Screening(tuple(rejected), int(chk.tri.shape[0]))


def _spread(p: Any, uv: Callable[[int], np.ndarray],
            sizes: Sequence[tuple[int, int] | None]) -> float | None:
    """The smaller of the two images' inlier spreads of pair ``p`` (None: unknown)."""
    if p.inliers is None or len(p.inliers) < 3:
        return None
    vals = []
    for img, col in ((p.a, 0), (p.b, 1)):
        size = sizes[img]
        if not size:
            return None
        vals.append(inlier_spread(uv(img)[p.inliers[:, col]], size))
    return min(vals)

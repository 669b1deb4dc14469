"""What the front end's stages hand on: small frozen records of numpy arrays.

Each stage's result can be built by hand, cached, tested and consumed without the
:class:`~posernet.frontend.pipeline.ImageFrontend` that made it:

* the image stage: one :class:`ImageFeatures` per image (keypoints, image size, ROI boxes);
* the pair stage: a :class:`MatchResult`, one :class:`PairMatches` per evaluated image pair
  (the matcher's keypoint matches and their verified :class:`TwoViewGeometry`) together with
  every image's keypoints the matches index (the fallback matcher may add keypoints while
  matching, so the pairs and the keypoints travel together);
* the graph stage: a :class:`FrontendResult`, the view graph assembled from those
  (:func:`assemble_frontend_result`) with the images, the pair selection and the run's counts
  (:class:`FrontendSummary`).

Arrays are shared, not copied: treat them as read-only.
"""

from __future__ import annotations

import copy
import dataclasses
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from ..graph import ViewGraph
from .assembly import GraphStats, PairResult, assemble_view_graph
from .features import Matches
from .images import ImageRecord
from .pairs import PairSelection

__all__ = ["FrontendResult", "FrontendSummary", "ImageFeatures", "MatchResult", "PairMatches",
           "TwoViewGeometry", "assemble_frontend_result"]

@dataclass
class FrontendSummary:
    """Counts and per-stage wall times (seconds) of a front-end run."""

    images: int = 0
    images_without_boxes: int = 0
    pairs: Counter = field(default_factory=Counter)  # status -> count, plus "too_few_matches"
    seconds: Counter = field(default_factory=Counter)  # stage -> wall time
    rejected: Counter = field(default_factory=Counter)  # "kp:<reason>" / "bb:<reason>" -> count
    rotation_only: int = 0  # edges whose translation direction is meaningless
    flat_keypoints: int = 0  # keypoints dropped on uniform patches
    reused: Counter = field(default_factory=Counter)  # "images" / "pairs" read from the cache
    boxes: bool = True  # False: no proposals were made (keypoints only)
    # matcher fallback: "images" with fallback features, pairs "tried" again, results "kept";
    # of those tried, "screened" (the screen's matches alone) and "alone" (of an image no
    # main-matcher pair ties); "main_kept": the main matcher's pass of a sparse or weak set,
    # kept over the fallback's
    fallback: Counter = field(default_factory=Counter)

    def lines(self) -> list[str]:
        """Human-readable summary lines (counts, then time per image / per pair)."""
        n_pairs = sum(v for k, v in self.pairs.items()
                      if k not in ("too_few_matches", "edge_few_boxes"))
        s = self.seconds
        few_boxes = self.pairs["unmatched"] - self.pairs["too_few_matches"]
        out = [
            f"images: {self.images} " + (f"({self.images_without_boxes} without any proposal)"
                                         if self.boxes else "(no boxes: no stage uses them)"),
            f"pairs: {n_pairs} checked, {self.pairs['edge']} edges; skipped: "
            f"{self.pairs['too_few_matches']} with too few keypoint matches, "
            + (f"{few_boxes} with too few matched boxes, {self.pairs['kp_failed']} KP and "
               f"{self.pairs['bb_failed']} BB two-view rejections"
               + (f"; {self.pairs['edge_few_boxes']} edges with fewer matched boxes than the "
                  "paper's rule" if self.pairs["edge_few_boxes"] else "")
               if self.boxes else f"{few_boxes} rejected by two-view verification"),
        ]
        if self.rejected or self.rotation_only:
            why = ", ".join(f"{k} {v}" for k, v in sorted(self.rejected.items()))
            out.append(f"verification: {self.rotation_only} rotation-only edges"
                       + (f"; rejected: {why}" if why else "")
                       + f"; {self.flat_keypoints} keypoints on flat patches dropped")
        if self.fallback:
            f = self.fallback
            sparse = " in a sparse set (any pair may be matched again)" if f.get("sparse") else ""
            head = f"fallback matcher: {f['images']} weakly textured images{sparse}"
            if f.get("main_kept"):  # the main matcher's pass, kept over the fallback's
                out.append(f"{head}; these pairs are the main matcher's alone, its result "
                           "kept over the fallback's (below)")
            else:
                notes = ([f"{f['screened']} on their best keypoints alone: too few matches "
                          "there"] if f.get("screened") else []) + (
                    [f"{f['alone']} of an image no pair of SIFT matches ties"]
                    if f.get("alone") else [])
                out.append(f"{head}, {f['tried']} pairs matched again"
                           + (f" ({'; '.join(notes)})" if notes else "")
                           + f", {f['kept']} of them kept ({s['fallback']:.1f} s)")
        if self.reused:
            out.append(f"reused from the cache: {self.reused['images']} images, "
                       f"{self.reused['pairs']} pairs")
        done = self.images - self.reused["images"]
        if done > 0:
            per = ", ".join(f"{k} {1000 * s[k] / done:.0f} ms"
                            for k in ("read", "proposals", "features")
                            if k in s and (self.boxes or k != "proposals"))
            out.append(f"per image: {per}")
        done = n_pairs - self.reused["pairs"]
        if done > 0:
            per = ", ".join(f"{k} {1000 * s[k] / done:.1f} ms"
                            for k in ("matching", "box_matching", "five_point")
                            if k in s and (self.boxes or k != "box_matching"))
            out.append(f"per pair: {per}")
        return out

    def merge(self, other: FrontendSummary) -> None:
        """Add ``other``'s pair counts, rejections and seconds (one pair's, evaluated on a
        worker thread) to this summary."""
        self.pairs.update(other.pairs)
        self.rejected.update(other.rejected)
        self.seconds.update(other.seconds)
        self.rotation_only += other.rotation_only
        self.reused.update(other.reused)
        self.fallback.update(other.fallback)

    def to_dict(self) -> dict[str, Any]:
        return {"images": self.images, "images_without_boxes": self.images_without_boxes,
                "pairs": dict(self.pairs), "rejected": dict(self.rejected),
                "rotation_only": self.rotation_only, "flat_keypoints": self.flat_keypoints,
                "reused": dict(self.reused), "fallback": dict(self.fallback),
                "seconds": {k: round(v, 3) for k, v in self.seconds.items()}}


@dataclass(frozen=True)
class ImageFeatures:
    """The image stage's result for one image.

    Attributes:
        keypoints: ``(K, 2)`` float64 pixel coordinates (x, y), pixel centres at integers.
        size: the image's (width, height) in pixels.
        boxes: ``(B, 4)`` ROI proposals as pixel xyxy; ``(0, 4)`` without proposals.
        colours: ``(K, 3)`` uint8 RGB of the image under each keypoint (the colours of the
            points they triangulate), or ``None``: the exports then read the image.
    """

    keypoints: np.ndarray
    size: tuple[int, int]
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    colours: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])


@dataclass(frozen=True)
class TwoViewGeometry:
    """The verified two-view geometry of images ``a < b`` (image ids); poses map camera a to
    camera b. Same fields as :class:`~posernet.frontend.assembly.PairResult` (so graph assembly
    takes either), frozen.

    Attributes:
        status: ``"edge"``, ``"unmatched"``, ``"kp_failed"`` or ``"bb_failed"``.
        reason: why the pair is not an edge (``""`` for an edge).
        kp, bb: ``(R (3, 3), t (3,) or (3, 1))`` 5-point estimates on keypoints / box
            centres, or None.
        rotation_only: the translation direction is meaningless (pure rotation or too small a
            baseline).
        inliers: ``(I, 2)`` int keypoint index pairs (into images a and b) that the verified
            pose explains (the input of keypoint tracks), or None.
        box_a, box_b: ``(P,)`` matched ROI boxes (indices into each image's boxes).
        wrong: ``(P,)`` bool box pairs known to be wrong (simulator only).
        n_kp, n_kp_outliers: keypoints that fed the KP 5-point, of them known wrong.
        info: the verification's counts and angles (JSON-able).
    """

    a: int
    b: int
    status: str
    reason: str = ""
    kp: tuple[np.ndarray, np.ndarray] | None = None
    bb: tuple[np.ndarray, np.ndarray] | None = None
    rotation_only: bool = False
    inliers: np.ndarray | None = None
    box_a: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    box_b: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    wrong: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    n_kp: int = 0
    n_kp_outliers: int = 0
    info: Mapping[str, Any] = field(default_factory=dict)

    @property
    def is_edge(self) -> bool:
        return self.status == "edge"

    @property
    def num_inliers(self) -> int:
        """Keypoint matches the verified pose explains (0 without)."""
        return 0 if self.inliers is None else len(self.inliers)

    @classmethod
    def from_pair(cls, p: PairResult) -> TwoViewGeometry:
        """A frozen snapshot of the front end's (mutable) pair record."""
        return cls(int(p.a), int(p.b), p.status, p.reason, p.kp, p.bb, bool(p.rotation_only),
                   p.inliers, p.box_a, p.box_b, p.wrong, int(p.n_kp), int(p.n_kp_outliers),
                   MappingProxyType(copy.deepcopy(dict(p.info))))


@dataclass(frozen=True)
class PairMatches:
    """The pair stage's result for one image pair: the matcher's keypoint matches (None when
    the front end keeps none) and their verified two-view geometry."""

    geometry: TwoViewGeometry
    matches: Matches | None = None

    @property
    def key(self) -> tuple[int, int]:
        return self.geometry.a, self.geometry.b

    def verified(self) -> Matches | None:
        """The matches the verified pose explains (all of them when the pair has no inliers
        or the matches no keypoint indices; None without matches)."""
        m, inl = self.matches, self.geometry.inliers
        if m is None or inl is None or m.idx_a is None or m.idx_b is None:
            return m
        code = m.idx_a.astype(np.int64) * (1 << 32) + m.idx_b
        keep = inl[:, 0].astype(np.int64) * (1 << 32) + inl[:, 1]
        return m.subset(np.isin(code, keep))


@dataclass(frozen=True)
class MatchResult:
    """The pair stage's result: every evaluated pair ``(a, b)``, ``a < b``, in key order, and
    every image's features (whose keypoints the pairs' indices refer to)."""

    images: tuple[ImageFeatures, ...]
    pairs: Mapping[tuple[int, int], PairMatches]

    def pair(self, i: int, j: int) -> TwoViewGeometry:
        """The verified geometry of images ``i, j`` (either order; stored as min -> max)."""
        return self.pairs[(min(int(i), int(j)), max(int(i), int(j)))].geometry

    def verified_matches(self) -> dict[tuple[int, int], np.ndarray]:
        """``(a, b) -> (M, 2)`` keypoint index pairs that each pair's verified pose explains
        (edges, and pairs verified with too few matched boxes for an edge): the input of
        keypoint tracks."""
        return {k: p.geometry.inliers for k, p in self.pairs.items()
                if p.geometry.inliers is not None and p.geometry.inliers.size}


@dataclass(frozen=True)
class FrontendResult:
    """The front end's result: the view graph of all images (node ``i`` is image ``i``) with
    what it was built from.

    Attributes:
        records: the images (paths, keys, intrinsics, ground truth when known).
        matches: the pair stage's result (features and every evaluated pair).
        selection: which image pairs were matched.
        graph: the assembled view graph; ``stats``: its book-keeping.
        summary: the front end's counts and timings (:class:`FrontendSummary`, a copy; the
            image and pair counts of ``matches`` when None is given).
        seed: the front end's seed (RANSAC; bundle adjustment's sampling).
    """

    records: tuple[ImageRecord, ...]
    matches: MatchResult
    selection: PairSelection
    graph: ViewGraph
    stats: GraphStats
    summary: FrontendSummary | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        if self.summary is None:  # a result built by hand: count what it holds
            s = FrontendSummary(images=len(self.records),
                                boxes=any(len(f.boxes) for f in self.matches.images))
            for p in self.matches.pairs.values():
                s.pairs[p.geometry.status] += 1
                s.rotation_only += p.geometry.is_edge and p.geometry.rotation_only
            object.__setattr__(self, "summary", s)

    @property
    def images(self) -> tuple[ImageFeatures, ...]:
        return self.matches.images

    def pair(self, i: int, j: int) -> TwoViewGeometry:
        """The verified geometry of images ``i, j``."""
        return self.matches.pair(i, j)

    def keypoints(self) -> list[np.ndarray]:
        """Every image's ``(K_i, 2)`` keypoints."""
        return [f.keypoints for f in self.matches.images]

    def keypoint_colours(self) -> list[np.ndarray | None]:
        """Every image's ``(K_i, 3)`` uint8 RGB keypoint colours (``None`` where unknown)."""
        return [f.colours for f in self.matches.images]

    def intrinsics(self) -> np.ndarray:
        """``(N, 3, 3)`` float64: every image's ``K``."""
        return np.stack([r.K for r in self.records]).astype(np.float64)

    def distortion(self) -> list[np.ndarray | None]:
        return [r.dist for r in self.records]

    def verified_matches(self) -> dict[tuple[int, int], np.ndarray]:
        return self.matches.verified_matches()

    def rejected_pairs(self) -> list[dict[str, Any]]:
        """Every evaluated pair that is not an edge: image keys, status, reason and the
        verification's numbers (for the run's records)."""
        return [{"source": self.records[a].key, "target": self.records[b].key,
                 "status": p.geometry.status, "reason": p.geometry.reason,
                 **p.geometry.info}
                for (a, b), p in sorted(self.matches.pairs.items()) if not p.geometry.is_edge]


def assemble_frontend_result(records: Sequence[ImageRecord], matches: MatchResult,
                             selection: PairSelection, meta: Mapping[str, Any] | None = None,
                             summary: FrontendSummary | None = None,
                             seed: int = 0) -> FrontendResult:
    """The graph stage: the view graph of all ``records`` from the pair stage's ``matches``
    over the selected pairs (each one must be in ``matches``), ground truth when every image
    has a pose. ``summary``: the counts to carry along (copied)."""
    recs = tuple(dataclasses.replace(r) for r in records)
    n = len(recs)
    if len(matches.images) != n:
        raise ValueError(f"{n} images but features of {len(matches.images)}")
    w2c = None
    if all(r.c2w is not None for r in recs):
        w2c = np.linalg.inv(np.stack([r.c2w for r in recs]))
    meta = dict(meta or {})
    meta.setdefault("camera_ids", [r.key for r in recs])
    graph, stats = assemble_view_graph(
        list(range(n)), matches.pair, [f.boxes for f in matches.images],
        np.stack([r.K for r in recs]),
        np.array([r.size if r.size else f.size for r, f in zip(recs, matches.images,
                                                                 strict=True)],
                 dtype=np.float64),
        np.array([r.k1 for r in recs]), w2c, meta, selection.pairs)
    return FrontendResult(recs, matches, selection, graph, stats,
                          summary=None if summary is None else copy.deepcopy(summary),
                          seed=int(seed))

"""The front end over a set of images: ROI proposals and local features per image, keypoint
matching, box matching and both 5-point estimates per image pair, view graphs of any subset.

:class:`ImageFrontend` is lazy and caches: per-image work runs once (in ``workers`` threads:
OpenCV and torch release the GIL), pairs are evaluated on demand (all pairs for a photo folder,
a sampled few for a large 7-Scenes sequence). It exposes the same ``pair(u, v)`` as the
synthetic generator's ``SceneWorld``, so graphs come from one assembly
(:func:`~posernet.frontend.assembly.assemble_view_graph`).

What leaves it is typed data (:mod:`posernet.frontend.results`), stage by stage:
:meth:`ImageFrontend.extract` (per-image features), :meth:`ImageFrontend.select_pairs`,
:meth:`ImageFrontend.match` (per-pair matches and verified geometry) and
:meth:`ImageFrontend.view_graph` (the assembled view graph with all of the above); later stages
need nothing else from it.

Per-stage wall times and counts (images without proposals, pairs with too few keypoint
matches, unmatched pairs, failed 5-point estimates) are kept for the run's summary.
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time
from collections.abc import Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, is_dataclass, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

import cv2
import numpy as np
import torch
from tqdm.auto import tqdm

from ..graph import ViewGraph
from .assembly import GraphStats, PairResult, assemble_view_graph
from .boxmatch import BoxMatchRules, box_centres, keypoints_in_matched_boxes, match_boxes
from .cache import FrontendCache, file_digest
from .features import Features, Matches
from .images import ImageRecord, keypoint_colours, read_image
from .pairs import PairOptions, PairSelection, select_pairs
from .relpose import PoseOptions, five_point
from .results import (
    FrontendResult,
    FrontendSummary,
    ImageFeatures,
    MatchResult,
    PairMatches,
    TwoViewGeometry,
    assemble_frontend_result,
)
from .verify import (
    VerifyRules,
    epipolar_consistent,
    inlier_spread,
    keypoint_contrast,
    verify_two_view,
)

__all__ = ["FrontendSummary", "ImageFrontend", "pair_seed"]

log = logging.getLogger("posernet.frontend")


def pair_seed(seed: int, a: int, b: int) -> int:
    """A RANSAC seed for images ``a < b`` that does not depend on evaluation order."""
    h = hashlib.blake2b(f"{seed}:{a}:{b}".encode(), digest_size=4).digest()
    return int.from_bytes(h, "little") & 0x7FFFFFFF


@dataclass
class _ImageData:
    boxes: np.ndarray  # (B, 4) pixel xyxy
    scores: np.ndarray  # (B,)
    features: Any
    textured: np.ndarray  # (K,) bool: keypoint on a patch with contrast (not a flat region)
    colours: np.ndarray | None = None  # (K, 3) uint8 RGB under each keypoint


class ImageFrontend:
    """Proposals, features, matches and 5-point estimates for a list of :class:`ImageRecord`.

    Args:
        records: the images (intrinsics per image; ground truth optional).
        proposals: a callable ``(image, key) -> Proposals`` (:mod:`posernet.frontend.proposals`),
            or ``None``: no boxes (keypoints only; every pair needs ``edge_rule="verified"``).
        matcher: an object with ``extract(image)`` and ``match(a, b)``
            (:mod:`posernet.frontend.features`).
        rules: the box-matching rules (paper defaults, one-to-one).
        pose: 5-point + RANSAC options.
        verify: two-view verification rules (:mod:`posernet.frontend.verify`).
        estimate: which initial estimate an edge needs (``kp`` or ``bb``); the other is
            computed too and may be missing.
        edge_rule: ``"boxes"`` (the paper's: an edge needs ``rules.min_boxes`` matched box
            pairs) or ``"verified"`` (with ``estimate="kp"``, every pair whose two-view
            geometry is verified is an edge; its matched boxes, fewer or none, ride along, and
            PoserNet keeps the pose of an edge without any). The KP estimate is then fitted on
            every keypoint match of the pair, as the tracks use them; with ``"boxes"``, on the
            matches inside matched boxes (the paper's input), which on a few far-apart views
            can be a small subset that fits a pose 10-50 deg off.
        kp_top_pairs: with ``edge_rule="boxes"``, the KP estimate from the keypoints of the
            ``kp_top_pairs`` box pairs sharing the most matches (0: every matched box pair, the
            paper's rule).
        seed: RANSAC seed base (per pair: :func:`pair_seed`).
        workers: threads for the per-image and per-pair stages.
        keep_matches: keep every pair's keypoint matches (for pictures).
        cache: a folder for :class:`~posernet.frontend.cache.FrontendCache` (per-image and
            per-pair results, so a repeated or interrupted run resumes), or ``None``.
        max_image_size: keypoints are detected on a copy whose longer side is at most this
            many pixels (``None``: full size); their coordinates are mapped back to the image.
    """

    def __init__(
        self,
        records: Sequence[ImageRecord],
        proposals: Any,
        matcher: Any,
        rules: BoxMatchRules | None = None,
        pose: PoseOptions | None = None,
        verify: VerifyRules | None = None,
        estimate: str = "kp",
        edge_rule: str = "boxes",
        kp_top_pairs: int = 0,
        seed: int = 0,
        workers: int = 1,
        keep_matches: bool = True,
        cache: str | Path | None = None,
        max_image_size: int | None = None,
    ) -> None:
        if not records:
            raise ValueError("the front end needs at least one image")
        self.records = list(records)
        self.proposals = proposals
        self.matcher = matcher
        self.rules = rules or BoxMatchRules()
        self.pose = pose or PoseOptions()
        self.verify = verify or VerifyRules()
        if estimate not in ("kp", "bb"):
            raise ValueError(f"estimate must be 'kp' or 'bb', got {estimate!r}")
        self.estimate = estimate
        if edge_rule not in ("boxes", "verified"):
            raise ValueError(f"edge_rule must be 'boxes' or 'verified', got {edge_rule!r}")
        self.edge_rule = edge_rule
        if proposals is None and (edge_rule != "verified" or estimate != "kp"):
            raise ValueError("without proposals (no boxes) only estimate='kp' with "
                             "edge_rule='verified' makes edges")
        self.kp_top_pairs = int(kp_top_pairs)
        self.seed = int(seed)
        self.workers = max(1, int(workers))
        self.keep_matches = bool(keep_matches)
        self._images: dict[int, _ImageData] = {}
        self._released = False  # release_descriptors() was called
        self._pairs: dict[tuple[int, int], PairResult] = {}
        self.matches: dict[tuple[int, int], Any] = {}
        self.summary = FrontendSummary(images=len(self.records), boxes=proposals is not None)
        if max_image_size is not None and int(max_image_size) < 32:
            raise ValueError(f"max_image_size must be >= 32 px or None, got {max_image_size}")
        self.max_image_size = None if max_image_size is None else int(max_image_size)
        self._digest: dict[int, str] = {}
        self._fallback: bool | None = None  # the matcher's fallback runs (decided once)
        self._sparse = False  # a sparse set: any pair may get the fallback (fallback_on)
        self._orphan: np.ndarray | None = None  # (N,) images no pair ties (evaluate_pairs)
        self._held = False  # the fallback held back: the main matcher alone (hold_fallback)
        self._fallback_lock = threading.Lock()
        # one lock per image: an image gets its fallback features once, while other images'
        # are extracted beside it on the other workers
        self._augment_locks: dict[int, threading.Lock] = {}
        self._augment_locks_lock = threading.Lock()
        # per image: edges the main matcher verified firmly (None: not counted yet), and the
        # main matcher's attempts kept between the two passes of evaluate_pairs
        self._strong: np.ndarray | None = None
        self._first: dict[tuple[int, int], tuple[Matches, PairResult, FrontendSummary]] = {}
        # per (matcher, a, b): its matches and whether screened, kept where the intrinsics are
        # guessed, for a front end with_intrinsics makes (matching does not depend on them)
        self._matched: dict[tuple[str, int, int], tuple[Matches, bool]] = {}
        self._remember = all(r.intrinsics_source != "given" for r in self.records)
        self.cache = None if cache is None else FrontendCache(cache, self.fingerprint())

    def with_intrinsics(self, K: np.ndarray) -> ImageFrontend:
        """A fresh front end over the same images, with the same options and cache folder,
        whose images have the intrinsics ``K (N, 3, 3)`` (their ``intrinsics_source`` kept):
        its pairs are verified again (the cache's pair keys hold the intrinsics) on the
        matches this one made, which it remembers where the intrinsics were guessed (else
        they are matched again); the images' features come from this one (when not
        released) or the cache."""
        K = np.asarray(K, np.float64)
        if K.shape != (len(self.records), 3, 3) or not np.isfinite(K).all():
            raise ValueError(f"with_intrinsics: K must be finite ({len(self.records)}, 3, 3), "
                             f"got {K.shape}")
        records = [replace(r, K=K[i].copy()) for i, r in enumerate(self.records)]
        fresh = ImageFrontend(
            records, self.proposals, self.matcher, rules=self.rules, pose=self.pose,
            verify=self.verify, estimate=self.estimate, edge_rule=self.edge_rule,
            kp_top_pairs=self.kp_top_pairs, seed=self.seed, workers=self.workers,
            keep_matches=self.keep_matches,
            cache=None if self.cache is None else self.cache.root,
            max_image_size=self.max_image_size)
        if not self._released:
            fresh._images = dict(self._images)  # per-image work does not depend on K
            fresh._digest = dict(self._digest)
        fresh._matched = dict(self._matched)
        return fresh

    def _matched_once(self, kind: str, a: int, b: int, match: Any) -> tuple[Matches, bool]:
        """``match()`` (-> matches, screened) of pair ``a, b`` by matcher ``kind``, from the
        memo when an earlier front end (:meth:`with_intrinsics`) or this one made it."""
        key = (kind, a, b)
        hit = self._matched.get(key)
        if hit is None:
            hit = match()
            if self._remember:
                self._matched[key] = hit
        return hit

    @classmethod
    def from_evaluated(cls, records: Sequence[ImageRecord], features: Sequence[Features],
                       pairs: Iterable[PairResult], **kwargs: Any) -> ImageFrontend:
        """A front end over images whose keypoints were found and pairs evaluated elsewhere
        (matches imported from another tool, hand-made cases): nothing is read or matched
        again, and the later steps (:meth:`screen`, :meth:`view_graph`, :meth:`graph`,
        :meth:`rejected_pairs`) run on them. ``features``: one
        :class:`~posernet.frontend.features.Features` per record (keypoints only, no boxes);
        ``pairs``: evaluated pairs (``a < b``, inliers indexing those keypoints), each booked
        in the summary by its status. ``kwargs``: the constructor's options (keypoint edges:
        ``estimate="kp"``, ``edge_rule="verified"``)."""
        fe = cls(records, None, None, **{"edge_rule": "verified", **kwargs})
        if len(features) != len(fe.records):
            raise ValueError(f"from_evaluated: {len(features)} feature sets for "
                             f"{len(fe.records)} images")
        for i, f in enumerate(features):
            fe._images[i] = _ImageData(np.zeros((0, 4)), np.zeros(0), f,
                                       np.ones(len(f.uv), bool))
        n = len(fe.records)
        for p in pairs:
            if not 0 <= p.a < p.b < n:
                raise ValueError(f"from_evaluated: pair ({p.a}, {p.b}) is not two images "
                                 f"a < b of the {n}")
            if (p.a, p.b) in fe._pairs:
                raise ValueError(f"from_evaluated: pair ({p.a}, {p.b}) given twice")
            fe._pairs[(p.a, p.b)] = p
            fe.summary.pairs[p.status] += 1
            if p.is_edge and len(p.box_a) < fe.rules.min_boxes:
                fe.summary.pairs["edge_few_boxes"] += 1
        return fe

    def fingerprint(self) -> dict[str, Any]:
        """Every option that changes a front-end result (the cache's key)."""
        return {"proposals": None if self.proposals is None else _describe(self.proposals),
                "matcher": _describe(self.matcher),
                "rules": _describe(self.rules), "pose": _describe(self.pose),
                "verify": _describe(self.verify), "estimate": self.estimate,
                "edge_rule": self.edge_rule, "kp_top_pairs": self.kp_top_pairs,
                "kp_fit": self.kp_fit, "seed": self.seed, "max_image_size": self.max_image_size}

    @property
    def kp_fit(self) -> str:
        """Which matches the KP estimate of a pair with matched boxes is fitted on: ``"all"``
        (``edge_rule="verified"``) or ``"boxes"`` (the paper's, in matched boxes)."""
        return "all" if self.edge_rule == "verified" and self.estimate == "kp" else "boxes"

    # ------------------------------------------------------------------ images

    def _digest_of(self, i: int) -> str:
        if i not in self._digest:
            self._digest[i] = file_digest(self.records[i].path)
        return self._digest[i]

    def _process(self, i: int) -> tuple[int, _ImageData, dict[str, float]]:
        r = self.records[i]
        t0 = time.perf_counter()
        if self.cache is not None:
            try:
                hit = self.cache.load("images", self._digest_of(i))
            except OSError as exc:  # unreadable file: read_image below names it
                log.debug("no digest for %s: %s", r.path, exc)
                hit = None
            if hit is not None:
                data, size = _image_from_cache(*hit, device=getattr(self.matcher, "device",
                                                                     None))
                r.size = size
                return i, data, {"cached": time.perf_counter() - t0}
        img = read_image(r.path)
        t1 = time.perf_counter()
        h, w = img.shape[:2]
        if self.proposals is not None:
            props = self.proposals(img, r.key)
            boxes, scores = props.boxes, props.scores
        else:
            boxes, scores = np.zeros((0, 4)), np.zeros(0)
        t2 = time.perf_counter()
        feats = self._features(img)
        grey = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        contrast = keypoint_contrast(grey, feats.uv, self.verify.contrast_radius)
        t3 = time.perf_counter()
        r.size = (int(w), int(h))
        data = _ImageData(np.asarray(boxes, np.float64).reshape(-1, 4),
                          np.asarray(scores, np.float64).reshape(-1), feats,
                          contrast >= self.verify.min_contrast, keypoint_colours(img, feats.uv))
        if self.cache is not None:
            self.cache.save("images", self._digest_of(i), *_image_to_cache(data, r.size))
        return i, data, {"read": t1 - t0, "proposals": t2 - t1, "features": t3 - t2}

    def _features(self, img: np.ndarray) -> Features:
        """The matcher's features of ``img``, detected at the working resolution."""
        feats = self._scaled(img, self.matcher.extract)
        if feats is None:  # pragma: no cover - a main extractor always returns features
            raise RuntimeError(f"{self.matcher!r} returned no features")
        return feats

    def _scaled(self, img: np.ndarray, extract: Any) -> Features | None:
        """``extract(image)``'s features of ``img`` (None passes through), detected at the
        working resolution and mapped back to ``img``'s pixels."""
        h, w = img.shape[:2]
        if self.max_image_size is None or max(h, w) <= self.max_image_size:
            return extract(img)
        f = self.max_image_size / max(h, w)
        small = cv2.resize(img, (max(1, round(w * f)), max(1, round(h * f))),
                           interpolation=cv2.INTER_AREA)
        feats = extract(small)
        if feats is None:
            return None
        sx, sy = w / small.shape[1], h / small.shape[0]
        # pixel centres at integers: x_full + 0.5 = (x_small + 0.5) * scale
        uv = (feats.uv + 0.5) * np.array([sx, sy]) - 0.5
        return Features(uv, feats.desc, (w, h), feats.extra)

    def prepare(self, ids: Iterable[int] | None = None, progress: bool = True) -> None:
        """Read, propose and extract features for images ``ids`` (default: all), once each."""
        todo = [i for i in (range(len(self.records)) if ids is None else ids)
                if i not in self._images]
        if not todo:
            return
        bar = tqdm(total=len(todo), desc="images", unit="img", disable=not progress)
        if self.workers > 1 and len(todo) > 1:
            # OpenCV's own threads on top of the workers only oversubscribe the cores (SIFT
            # of 64 rendered frames on 2 workers, 2 cores: 38.4 -> 35.9 ms an image; the same
            # features, as its keypoint order is made canonical)
            threads = cv2.getNumThreads()
            cv2.setNumThreads(1)
            try:
                with ThreadPoolExecutor(self.workers) as pool:
                    results = pool.map(self._process, todo)
                    for i, data, secs in results:
                        self._store(i, data, secs)
                        bar.update(1)
            finally:
                cv2.setNumThreads(threads)
        else:
            for i in todo:
                self._store(*self._process(i))
                bar.update(1)
        bar.close()

    def _store(self, i: int, data: _ImageData, secs: dict[str, float]) -> None:
        if self._released:  # an image first needed after release_descriptors
            data = _without_descriptors(data)
        self._images[i] = data
        self.summary.seconds.update(secs)
        if "cached" in secs:
            self.summary.reused["images"] += 1
        self.summary.flat_keypoints += int((~data.textured).sum())
        if getattr(self.matcher, "is_weak_image", lambda f: False)(data.features):
            self.summary.fallback["images"] += 1
        if data.boxes.shape[0] == 0 and self.proposals is not None:
            self.summary.images_without_boxes += 1
            log.warning("image %s: no ROI proposal survived the filters; it cannot join a "
                        "graph", self.records[i].key)

    def image(self, i: int) -> _ImageData:
        if i not in self._images:
            self.prepare([i], progress=False)
        return self._images[i]

    def features(self, i: int) -> ImageFeatures:
        """The image stage's result for image ``i`` (computed once)."""
        d = self.image(i)
        return ImageFeatures(d.features.uv, tuple(d.features.size), d.boxes, d.colours)

    def extract(self, progress: bool = True) -> tuple[ImageFeatures, ...]:
        """The image stage on every image (:meth:`prepare`): their features, in image order."""
        self.prepare(progress=progress)
        return tuple(self.features(i) for i in range(len(self.records)))

    def select_pairs(self, options: PairOptions | None = None) -> PairSelection:
        """The image pairs to match (:func:`~posernet.frontend.pairs.select_pairs` on every
        image's descriptors, which stay inside the front end)."""
        self._check_descriptors("selecting pairs")
        return select_pairs([self.image(i).features for i in range(len(self.records))],
                            options)

    def boxes(self, i: int) -> np.ndarray:
        """Proposals of image ``i`` as pixel xyxy ``(B, 4)``."""
        return self.image(i).boxes

    # ------------------------------------------------------------------ pairs

    def pair(self, i: int, j: int) -> PairResult:
        """The evaluated pair of images ``i, j`` (stored once as ``min -> max``, cached)."""
        a, b = (int(i), int(j)) if i < j else (int(j), int(i))
        if a == b:
            raise ValueError(f"a pair needs two different images, got {a} twice")
        hit = self._pairs.get((a, b))
        if hit is None:
            self._check_descriptors(f"pair ({self.records[a].key}, {self.records[b].key})")
            hit = self._store_pair(*self._evaluate(a, b))
        return hit

    def release_descriptors(self) -> None:
        """Free every image's descriptors once its pairs are evaluated: the stages after
        matching use keypoints, boxes and matches only, and the descriptors are the image
        stage's largest part (about 45 MB at 256 images with SIFT). Evaluating a new pair or
        selecting pairs afterwards raises :class:`RuntimeError`; pairs already evaluated stay
        available."""
        for i, data in self._images.items():
            self._images[i] = _without_descriptors(data)
        self._released = True

    def _check_descriptors(self, what: str) -> None:
        if self._released:
            raise RuntimeError(f"{what}: this front end's descriptors were released "
                               "(release_descriptors) after its pairs were matched; make a "
                               "new ImageFrontend to match more pairs")

    def _store_pair(self, hit: PairResult, delta: FrontendSummary) -> PairResult:
        self._pairs[(hit.a, hit.b)] = hit
        delta.pairs[hit.status] += 1
        self.summary.merge(delta)
        return hit

    def _pair_key(self, a: int, b: int) -> str | None:
        if self.cache is None:
            return None
        ra, rb = self.records[a], self.records[b]
        return self.cache.pair_key(self._digest_of(a), self._digest_of(b), ra.K, rb.K, ra.dist,
                                   rb.dist)

    def _cached(self, a: int, b: int) -> tuple[PairResult, FrontendSummary] | None:
        """Pair ``a, b``'s result and counts from the cache, or None."""
        key = self._pair_key(a, b)
        if key is None:
            return None
        out = FrontendSummary()
        t0 = time.perf_counter()
        hit = self.cache.load("pairs", key)
        if hit is None or hit[1].get("fallback_on", False) != self.fallback_on():
            return None  # none, or evaluated in a set the fallback judged otherwise
        res, m = _pair_from_cache(*hit, a=a, b=b, summary=out)
        if res.info.get("matcher") == "fallback" and not (self._ensure_fallback(a)
                                                           and self._ensure_fallback(b)):
            return None  # its keypoints cannot be made again here
        if self.keep_matches and m is not None:
            self.matches[(a, b)] = m
        out.seconds["cached"] += time.perf_counter() - t0
        out.reused["pairs"] += 1
        return res, out

    def _evaluate(self, a: int, b: int) -> tuple[PairResult, FrontendSummary]:
        """One pair's result and its counts/seconds (kept apart so that pairs can be evaluated
        on worker threads and merged in order); from the cache when it has the pair."""
        hit = self._cached(a, b)
        if hit is not None:
            return hit
        out = FrontendSummary()
        res = self._evaluate_into(a, b, out)
        key = self._pair_key(a, b)
        if key is not None:
            self.cache.save("pairs", key, *_pair_to_cache(res, out, self.matches.get((a, b)),
                                                          self.fallback_on()))
        return res, out

    def _evaluate_into(self, a: int, b: int, summary: FrontendSummary) -> PairResult:
        """Match and verify pair ``a, b``; with a matcher that has a fallback
        (:class:`~posernet.frontend.features.FallbackMatcher`) a pair whose result it judges
        weak is matched and verified again with the fallback, whose edge the matcher then
        keeps or not."""
        memo = self._first.pop((a, b), None)
        m, res, first = memo if memo is not None else self._first_attempt(a, b)
        fm = self.matcher
        t0 = time.perf_counter()
        if (self._wants_fallback(a, b, len(m), res) and self._ensure_fallback(a)
                and self._ensure_fallback(b)):
            first.seconds["fallback"] += time.perf_counter() - t0
            second = FrontendSummary()
            screened = []
            # a matcher may screen its fallback (FallbackMatcher.match_fallback_screened)
            both = getattr(fm, "match_fallback_screened", None)

            def match(fa: Features, fb: Features) -> Matches:
                m, s = self._matched_once(
                    "fallback", a, b, lambda: (fm.match_fallback(fa, fb), False) if both is None
                    else both(fa, fb, screen=len(self.records) > 2))
                screened.append(s)
                return m

            m2, res2 = self._match_verify(a, b, match, second)
            first.seconds["fallback"] += sum(second.seconds.values())
            first.fallback["tried"] += 1
            first.fallback["screened"] += int(any(screened))
            first.fallback["alone"] += int(self._alone(a, b))
            keep = False
            if res2.is_edge:
                # its pose must explain SIFT's own matches: two matchers agreeing
                agree = self._agreement(m, res2, a, b)
                res2.info["fallback_agreement"] = round(agree, 4)
                keep = fm.keeps_fallback(res.info["main_inliers"], _edge_inliers(res2), agree,
                                         len(m), self._textured_pair(a, b), self._alone(a, b))
            if keep:
                second.seconds, second.fallback = first.seconds, first.fallback
                second.fallback["kept"] += 1
                res2.info.update(matcher="fallback", main_inliers=res.info["main_inliers"],
                                 main_spread=res.info["main_spread"])
                res2.inliers = self._with_main_tracks(m, res2, a, b)
                first, m, res = second, m2, res2
        summary.merge(first)
        if self.keep_matches:
            self.matches[(a, b)] = m
        return res

    def _first_attempt(self, a: int, b: int
                       ) -> tuple[Matches, PairResult, FrontendSummary]:
        """The main matcher's matches of pair ``a, b``, their verified result and its counts;
        with the fallback on, the result's ``info`` records the inliers and their spread
        (``main_inliers``, ``main_spread``) that decide about the fallback."""
        first = FrontendSummary()

        def match(fa: Features, fb: Features) -> Matches:
            return self._matched_once("main", a, b, lambda: (self.matcher.match(fa, fb),
                                                             False))[0]

        m, res = self._match_verify(a, b, match, first)
        if self.fallback_on():
            n_in = _edge_inliers(res)
            spread = self._spread(a, b, res.inliers) if n_in else None
            res.info.update(main_inliers=n_in,
                            main_spread=None if spread is None else round(spread, 4))
        return m, res, first

    def _is_strong(self, res: PairResult) -> bool:
        """Whether the main matcher verified pair ``res`` firmly (enough inliers, spread)."""
        n_in = res.info.get("main_inliers", 0)
        return n_in > 0 and not self.matcher.is_weak(n_in, res.info.get("main_spread"))

    def _wants_fallback(self, a: int, b: int, matches: int, res: PairResult) -> bool:
        """Whether pair ``a, b`` (``matches`` main matches, verified into ``res``) is matched
        again with the fallback: both images are weakly textured (any two in a sparse set),
        the matcher judges the
        result weak, and an image of the pair has fewer firm edges than the matcher's
        ``fallback_degree`` (counted over every pair by :meth:`evaluate_pairs`; a pair
        evaluated alone counts none)."""
        fm = self.matcher
        if not self.fallback_on():
            return False
        if not (self._sparse or (fm.is_weak_image(self.image(a).features)
                                 and fm.is_weak_image(self.image(b).features))):
            return False
        degree = 0 if self._strong is None else int(min(self._strong[a], self._strong[b]))
        return fm.wants_fallback(matches, res.info["main_inliers"], res.info["main_spread"],
                                 degree, self._textured_pair(a, b), self._alone(a, b))

    def _alone(self, a: int, b: int) -> bool:
        """Whether an image of pair ``a, b`` of a sparse set has no pair with the matcher's
        ``fallback_matches`` main matches (nor an edge): no other pair could tie it."""
        return self._orphan is not None and bool(self._orphan[a] or self._orphan[b])

    def _textured_pair(self, a: int, b: int) -> bool:
        """Whether neither image of pair ``a, b`` is weakly textured."""
        weak = self.matcher.is_weak_image
        return not (weak(self.image(a).features) or weak(self.image(b).features))

    def _ensure_fallback(self, i: int) -> bool:
        """Give image ``i`` the matcher's fallback features (appended to its own, once; the
        image's cache entry is written again); False when they cannot be made."""
        fm = self.matcher
        with self._augment_locks_lock:
            lock = self._augment_locks.setdefault(i, threading.Lock())
        with lock:
            data = self.image(i)
            if fm.has_fallback(data.features):
                return True
            r = self.records[i]
            img = read_image(r.path)
            g = self._scaled(img, fm.extract_fallback)
            if g is None:
                return False
            grey = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            contrast = keypoint_contrast(grey, g.uv, self.verify.contrast_radius)
            feats = fm.with_fallback(data.features, g)
            n = int(data.features.extra.get("primary", len(data.features)))
            textured = np.concatenate([data.textured[:n], contrast >= self.verify.min_contrast])
            new = _ImageData(data.boxes, data.scores, feats, textured,
                             keypoint_colours(img, feats.uv))
            self._images[i] = new
            if self.cache is not None:
                self.cache.save("images", self._digest_of(i), *_image_to_cache(new, r.size))
            return True

    def fallback_on(self) -> bool:
        """Whether the matcher's fallback runs: it has one, and at least its ``weak_share`` of
        all images (each prepared once to tell) are weakly textured, so that a textured set
        with a few plain frames stays with the main matcher, or the set is sparse (the
        matcher's ``sparse_images``) (one warning line when the
        fallback cannot run in a weak set). Decided once; False while held back
        (:meth:`hold_fallback`)."""
        if self._held:
            return False
        if self._fallback is None:
            fm = self.matcher
            if not hasattr(fm, "match_fallback"):
                self._fallback = False
                return False
            with self._fallback_lock:
                if self._fallback is None:
                    self.prepare(progress=False)
                    n = sum(bool(fm.is_weak_image(self.image(i).features))
                            for i in range(len(self.records)))
                    share = float(getattr(fm, "weak_share", 0.0))
                    self._sparse = bool(getattr(fm, "is_sparse_set", lambda n: False)(
                        len(self.records)))
                    weak = n > 0 and n >= share * len(self.records)
                    self._fallback = weak or self._sparse
                    if self._fallback and not getattr(fm, "installed", fm.available)():
                        self._fallback = self._sparse = False  # no fallback to run
                        if weak:  # a sparse textured set does well enough without
                            getattr(fm, "notice_unavailable", lambda: None)()
                    if self._sparse:
                        self.summary.fallback["sparse"] = 1
        return self._fallback

    def fallback_pending(self) -> bool:
        """Whether the matcher's fallback would run on this set (:meth:`fallback_on`) and the
        matcher asks for the main matcher's result first (its ``main_first`` share)."""
        held, self._held = self._held, False
        try:
            return self.fallback_on() and float(getattr(self.matcher, "main_first", 0)) > 0
        finally:
            self._held = held

    def hold_fallback(self, held: bool) -> None:
        """Hold the matcher's fallback back (pairs are matched by the main matcher alone) or
        let it run again. Pairs evaluated while held keep the main matcher's result until
        :meth:`forget_pairs`."""
        self._held = bool(held)

    def forget_pairs(self) -> None:
        """Drop every pair result and its counts (images and their features stay), so that
        the pairs are evaluated again, e.g. with the fallback after the main matcher alone."""
        self._pairs.clear()
        self._first.clear()
        self.matches.clear()
        self._strong = self._orphan = None
        s = self.summary
        s.pairs.clear()
        s.rejected.clear()
        s.rotation_only = 0
        s.reused.pop("pairs", None)
        for k in ("matching", "box_matching", "five_point", "fallback", "cached"):
            s.seconds.pop(k, None)

    def _agreement(self, m: Matches, res: PairResult, a: int, b: int) -> float:
        """Share of the matches ``m`` of pair ``a, b`` that the verified pose of ``res``
        explains (:meth:`_explained`)."""
        ok = self._explained(m, res, a, b)
        return float(ok.mean()) if ok.size else 0.0

    def _explained(self, m: Matches, res: PairResult, a: int, b: int) -> np.ndarray:
        """Which matches ``(M,)`` of ``m`` (pair ``a, b``) the verified pose of ``res``
        explains: epipolar distance, or the rotation's mapping for a rotation-only edge,
        within the tracks' threshold (none without a pose)."""
        pose = res.kp
        if len(m) == 0 or pose is None:
            return np.zeros(len(m), bool)
        ra, rb = self.records[a], self.records[b]
        R, t = (np.asarray(x, np.float64) for x in pose)
        thr = 2.0 * self.pose.kp_threshold
        if not res.rotation_only:
            return epipolar_consistent(m.uv_a, m.uv_b, R, t.ravel(), ra.K, rb.K, ra.dist,
                                       rb.dist, threshold=thr)
        x1 = cv2.undistortPoints(m.uv_a.reshape(-1, 1, 2), ra.K, ra.dist).reshape(-1, 2)
        h = np.c_[x1, np.ones(len(x1))] @ R.T
        with np.errstate(divide="ignore", invalid="ignore"):
            pred = h[:, :2] / h[:, 2:3] * np.diag(rb.K)[:2] + rb.K[:2, 2]
        und = cv2.undistortPoints(m.uv_b.reshape(-1, 1, 2), rb.K, rb.dist, P=rb.K)
        err = np.linalg.norm(pred - und.reshape(-1, 2), axis=1)
        return (h[:, 2] > 0) & (err < thr)

    def _with_main_tracks(self, m: Matches, res: PairResult, a: int, b: int
                          ) -> np.ndarray | None:
        """The track matches ``(I, 2)`` of a kept fallback edge ``res`` with the main matcher's
        matches ``m`` of the pair that its pose explains appended. The two kinds of keypoints
        never match each other, so without them a fallback edge's 3D points could never be
        seen in a camera tied to the pair by a main-matcher edge: alternating edges round a
        ring would leave every pair's distance unfixed (the self-check rejects such cameras)."""
        if res.inliers is None or res.rotation_only or m.idx_a is None or m.idx_b is None:
            return res.inliers  # a rotation-only edge's tracks are its fitted inliers alone
        ok = self._explained(m, res, a, b)
        if not ok.any():
            return res.inliers
        main = np.stack([m.idx_a[ok], m.idx_b[ok]], axis=1).astype(res.inliers.dtype)
        both = np.concatenate([res.inliers, main])
        _, first = np.unique(both, axis=0, return_index=True)  # a match both matchers found
        return both[np.sort(first)]

    def _spread(self, a: int, b: int, inliers: np.ndarray | None) -> float | None:
        """The smaller share of the two images the inliers' hull covers (None: no inliers)."""
        if inliers is None or len(inliers) < 3:
            return None
        out = []
        for i, col in ((a, 0), (b, 1)):
            f = self.image(i).features
            out.append(inlier_spread(f.uv[inliers[:, col]], f.size))
        return min(out)

    def _match_verify(self, a: int, b: int, match: Any, summary: FrontendSummary
                      ) -> tuple[Matches, PairResult]:
        """Matches of pair ``a, b`` by ``match(features_a, features_b)`` and their verified
        result (counts and seconds into ``summary``)."""
        A, B = self.image(a), self.image(b)
        ra, rb = self.records[a], self.records[b]
        sec = summary.seconds
        t0 = time.perf_counter()
        m = match(A.features, B.features)
        if m.idx_a is not None and m.idx_b is not None:
            m = m.subset(A.textured[m.idx_a] & B.textured[m.idx_b])
        t1 = time.perf_counter()
        sec["matching"] += t1 - t0
        return m, self._verify_pair(a, b, m, A, B, ra, rb, summary, t1)

    def _verify_pair(self, a: int, b: int, m: Matches, A: _ImageData, B: _ImageData,
                     ra: ImageRecord, rb: ImageRecord, summary: FrontendSummary,
                     t1: float) -> PairResult:
        """Box matching and two-view verification of matches ``m`` of pair ``a, b``."""
        sec = summary.seconds
        none = np.zeros(0, np.int64)
        rules = self.rules
        if m.uv_a.shape[0] < rules.min_keypoints:  # cannot match a single box pair
            summary.pairs["too_few_matches"] += 1
            return PairResult(a, b, none, none, np.zeros(0, bool), 0, 0, None, None, "unmatched",
                              reason="too_few_matches")
        ia, ib, _ = match_boxes(m.uv_a, m.uv_b, A.boxes, B.boxes, rules.min_keypoints,
                                rules.min_span, one_to_one=rules.one_to_one)
        t2 = time.perf_counter()
        sec["box_matching"] += t2 - t1
        wrong = np.zeros(ia.size, bool)
        q, s = self.pose, pair_seed(self.seed, a, b)
        common = {"prob": q.ransac_prob, "max_iters": q.max_iters, "seed": s, "method": q.method}
        geo = {"K2": rb.K, "dist1": ra.dist, "dist2": rb.dist}
        track_geo = {"K1": ra.K, **geo}
        boxes = ia.size >= rules.min_boxes
        if self.kp_fit == "all" or not boxes:
            # The geometry (and the tracks) from all the pair's matches: every verified pair
            # is an edge when keypoints make the edges (kp_fit "all"), with the box-centre
            # estimate riding along where boxes match; with the paper's box rule a pair with
            # too few matched boxes is no edge, but its verified matches still join the tracks.
            tv = verify_two_view(m.uv_a, m.uv_b, ra.K, rules=self.verify,
                                 threshold=q.kp_threshold, **geo, **common)
            bb = five_point(box_centres(A.boxes[ia]), box_centres(B.boxes[ib]), ra.K,
                            q.bb_threshold, **geo, **common) if boxes else None
            sec["five_point"] += time.perf_counter() - t2
            if boxes and bb is None:
                summary.rejected["bb:five_point"] += 1
            inliers = self._track_matches(m, tv, np.ones(len(m), bool), track_geo)
            if not tv.accepted:
                summary.rejected[f"kp:{tv.status}"] += 1
                return PairResult(a, b, ia, ib, wrong, 0, 0, None, bb, "unmatched",
                                  reason=tv.status, rotation_only=tv.rotation_only,
                                  inliers=inliers, info=tv.info)
            if self.kp_fit != "all":  # boxes may not be in use at all: say which rule failed
                return PairResult(a, b, ia, ib, wrong, 0, 0, None, None, "unmatched",
                                  reason="too_few_matched_boxes",
                                  rotation_only=tv.rotation_only, inliers=inliers,
                                  info=tv.info)
            summary.rotation_only += bool(tv.rotation_only)
            if not boxes:
                summary.pairs["edge_few_boxes"] += 1
            return PairResult(a, b, ia, ib, wrong, len(m), 0, tv.pose, bb, "edge",
                              rotation_only=tv.rotation_only, inliers=inliers, info=tv.info)
        inside = keypoints_in_matched_boxes(m.uv_a, m.uv_b, A.boxes, B.boxes, ia, ib,
                                            self.kp_top_pairs)
        p1, p2 = m.uv_a[inside], m.uv_b[inside]
        kp = verify_two_view(p1, p2, ra.K, rules=self.verify, threshold=q.kp_threshold,
                             **geo, **common)
        bb = five_point(box_centres(A.boxes[ia]), box_centres(B.boxes[ib]), ra.K,
                        q.bb_threshold, **geo, **common)
        sec["five_point"] += time.perf_counter() - t2
        if not kp.accepted:
            summary.rejected[f"kp:{kp.status}"] += 1
        if bb is None:
            summary.rejected["bb:five_point"] += 1
        need = kp.pose if self.estimate == "kp" else bb
        if need is None:
            status = f"{self.estimate}_failed"
            reason = kp.status if self.estimate == "kp" else "five_point"
            return PairResult(a, b, ia, ib, wrong, int(p1.shape[0]), 0, kp.pose, bb, status,
                              reason=reason, info=kp.info)
        summary.rotation_only += bool(kp.rotation_only)
        return PairResult(a, b, ia, ib, wrong, int(p1.shape[0]), 0, kp.pose, bb, "edge",
                          rotation_only=kp.rotation_only,
                          inliers=self._track_matches(m, kp, inside, track_geo), info=kp.info)

    def _track_matches(self, m: Any, tv: Any, fitted: np.ndarray,
                       geo: dict[str, Any]) -> np.ndarray | None:
        """Keypoint index pairs ``(I, 2)`` of the matches a verified two-view result ``tv``
        (fitted on the matches ``fitted``) explains, or ``None``: every match it explains, in
        boxes or not, feeds the tracks; a rotation-only pair has no depth to check, so only the
        matches it was fitted on and kept."""
        if not tv.accepted or m.idx_a is None or m.idx_b is None:
            return None
        if tv.rotation_only:
            keep = np.zeros(len(m), bool)
            keep[np.flatnonzero(fitted)[tv.inliers]] = True
        else:
            keep = epipolar_consistent(m.uv_a, m.uv_b, tv.R, tv.t, geo["K1"], geo["K2"],
                                       geo["dist1"], geo["dist2"],
                                       threshold=2.0 * self.pose.kp_threshold)
        return np.stack([m.idx_a[keep], m.idx_b[keep]], axis=1)

    def two_view(self, i: int, j: int) -> TwoViewGeometry:
        """The verified geometry of images ``i, j`` (evaluated once), as a frozen record."""
        return TwoViewGeometry.from_pair(self.pair(i, j))

    def match(self, pairs: Sequence[tuple[int, int]], progress: bool = True,
              screen: bool = True) -> MatchResult:
        """The pair stage: evaluate ``pairs`` (:meth:`evaluate_pairs`), then with ``screen``
        reject the edges among them that crowd their inliers or break triangles
        (:func:`~posernet.frontend.consistency.screen_edges`). Returns every evaluated pair's
        matches and geometry with every image's features (whose keypoints they index)."""
        self.evaluate_pairs(pairs, progress=progress)
        if screen:
            self.screen(pairs)
        return self.match_result()

    def screen(self, pairs: Sequence[tuple[int, int]],
               rules: VerifyRules | None = None) -> dict[str, int]:
        """Reject the edges among the evaluated ``pairs`` that crowd their inliers or break
        triangles (:func:`~posernet.frontend.consistency.screen_edges`; ``rules`` default to
        the front end's) and book each like any two-view rejection: it keeps its numbers,
        gets reason ``crowded`` / ``loop``, loses its matches from the keypoint tracks (its
        geometry is not trusted) and is counted as ``<estimate>:<reason>``. Returns the
        counts (``crowded``, ``loop``, ``triangles``)."""
        from .consistency import screen_edges

        keys = sorted({(min(int(a), int(b)), max(int(a), int(b))) for a, b in pairs if a != b})
        edges = [p for p in (self.pair(a, b) for a, b in keys) if p.is_edge]
        found = screen_edges(edges, lambda i: self.image(i).features.uv,
                             [r.size for r in self.records], self.estimate,
                             rules or self.verify)
        for p, reason in found.rejected:
            self._reject_edge(p, reason)
        return found.counts()

    def _reject_edge(self, p: PairResult, reason: str) -> None:
        """Turn edge ``p`` into a rejected pair and book it in the summary."""
        s = self.summary
        s.pairs["edge"] -= 1
        boxes = p.box_a.size >= self.rules.min_boxes
        if not boxes:  # an edge on fewer matched boxes than the paper's rule was counted apart
            s.pairs["edge_few_boxes"] -= 1
        p.status = f"{self.estimate}_failed" if boxes else "unmatched"
        s.pairs[p.status] += 1
        s.rejected[f"{self.estimate}:{reason}"] += 1
        if p.rotation_only:
            s.rotation_only -= 1
        p.reason = reason
        p.inliers = None

    def match_result(self) -> MatchResult:
        """Every pair evaluated so far and every image's features, as typed data."""
        self.prepare(progress=False)
        return MatchResult(
            images=tuple(self.features(i) for i in range(len(self.records))),
            pairs=MappingProxyType({k: PairMatches(TwoViewGeometry.from_pair(p),
                                                   self.matches.get(k))
                                    for k, p in sorted(self._pairs.items())}))

    def view_graph(self, selection: PairSelection, matches: MatchResult | None = None,
                   meta: dict[str, Any] | None = None) -> FrontendResult:
        """The graph stage: the view graph of every image over ``selection``'s pairs from the
        pair stage's ``matches`` (default: :meth:`match_result`), with the run's counts
        (:func:`~posernet.frontend.results.assemble_frontend_result`)."""
        if matches is None:
            matches = self.match_result()
        return assemble_frontend_result(self.records, matches, selection, meta,
                                        summary=self.summary, seed=self.seed)

    def verified_matches(self) -> dict[tuple[int, int], np.ndarray]:
        """Keypoint index pairs ``(M, 2)`` that each evaluated pair's verified pose explains
        (edges, and pairs with verified geometry but too few matched boxes for an edge), keyed
        by image pair ``(a, b)``, ``a < b`` (the input of keypoint tracks)."""
        return {k: p.inliers for k, p in self._pairs.items()
                if p.inliers is not None and p.inliers.size}

    def rejected_pairs(self) -> list[dict[str, Any]]:
        """Every evaluated pair that is not an edge: image keys, reason and verification
        numbers (for the run's summary)."""
        out = []
        for (a, b), p in sorted(self._pairs.items()):
            if not p.is_edge:
                out.append({"source": self.records[a].key, "target": self.records[b].key,
                            "status": p.status, "reason": p.reason, **p.info})
        return out

    def evaluate_pairs(self, pairs: Sequence[tuple[int, int]],
                       progress: bool = True) -> list[PairResult]:
        """Evaluate the given image pairs (with a progress bar; on ``workers`` threads, as
        matching and RANSAC release the GIL); cached ones are free. Results and counts do not
        depend on the number of workers (each pair has its own RANSAC seed)."""
        self.prepare({i for p in pairs for i in p}, progress=progress)
        keys = [(int(min(a, b)), int(max(a, b))) for a, b in pairs]
        todo = list(dict.fromkeys(k for k in keys if k not in self._pairs))
        evaluate = self._evaluate
        if self.fallback_on() and todo:
            # pass 1: the main matcher on every pair (or its cached result), to count each
            # image's firm edges; pass 2 then decides about the fallback pair by pair
            done = dict(self._map(lambda k: (k, self._cached(*k) or self._first_attempt(*k)),
                                  todo, progress, "pairs"))
            # each image's firm edges, and whether any pair ties it (an edge, or enough main
            # matches for the fallback's rules): over these first results and earlier pairs
            strong = np.zeros(len(self.records), np.int64)
            tied = np.zeros(len(self.records), bool)
            least = int(getattr(self.matcher, "fallback_matches", 0))
            firsts = [(k, r[1], len(r[0])) if len(r) == 3 else (k, r[0], r[0].n_kp)
                      for k, r in done.items()]
            for k, res, n in firsts + [(k, p, p.n_kp) for k, p in self._pairs.items()]:
                strong[list(k)] += int(self._is_strong(res))
                tied[list(k)] |= res.is_edge or n >= least
            self._strong = strong
            self._orphan = ~tied if self._sparse else None
            for k, r in done.items():
                if len(r) == 3:
                    self._first[k] = r  # type: ignore[assignment]

            def evaluate(a: int, b: int) -> tuple[PairResult, FrontendSummary]:
                r = done[(a, b)]
                return r if len(r) == 2 else self._evaluate(a, b)  # type: ignore[return-value]

        for res in self._map(lambda k: evaluate(*k), todo, progress,
                             "fallback" if evaluate is not self._evaluate else "pairs"):
            self._store_pair(*res)
        return [self.pair(a, b) for a, b in pairs]

    def _map(self, fn: Any, items: Sequence[Any], progress: bool, desc: str) -> list[Any]:
        """``fn`` over ``items`` in order, on ``workers`` threads, with a progress bar."""
        bar = tqdm(total=len(items), desc=desc, unit="pair", disable=not progress)
        out = []
        if self.workers > 1 and len(items) > 1:
            with ThreadPoolExecutor(self.workers) as pool:
                for r in pool.map(fn, items):
                    out.append(r)
                    bar.update(1)
        else:
            for k in items:
                out.append(fn(k))
                bar.update(1)
        bar.close()
        return out

    # ------------------------------------------------------------------ graphs

    def graph(self, ids: Sequence[int], meta: dict | None = None,
              pairs: Iterable[tuple[int, int]] | None = None) -> tuple[ViewGraph, GraphStats]:
        """The view graph of images ``ids`` (every pair evaluated, or only ``pairs``: image-id
        pairs, e.g. a :func:`~posernet.frontend.pairs.select_pairs` selection); ground truth
        when every image has a pose."""
        ids = list(ids)
        candidates = None
        if pairs is not None:
            node = {i: k for k, i in enumerate(ids)}
            candidates = [(node[a], node[b]) for a, b in pairs if a in node and b in node]
        recs = [self.records[i] for i in ids]
        self.prepare(ids, progress=False)
        w2c = None
        if all(r.c2w is not None for r in recs):
            w2c = np.linalg.inv(np.stack([r.c2w for r in recs]))
        meta = dict(meta or {})
        meta.setdefault("camera_ids", [r.key for r in recs])
        return assemble_view_graph(
            ids,
            self.pair,
            [self.boxes(i) for i in ids],
            np.stack([r.K for r in recs]),
            np.array([r.size for r in recs], dtype=np.float64),
            np.array([r.k1 for r in recs]),
            w2c,
            meta,
            candidates,
        )


def _edge_inliers(p: PairResult) -> int:
    """Inlier matches an edge gives the tracks (0: not an edge)."""
    return len(p.inliers) if p.is_edge and p.inliers is not None else 0


# ---------------------------------------------------------------------- cache records


def _describe(obj: Any) -> dict[str, Any]:
    """The settings of a front-end stage object, for the cache key: a dataclass's fields, else
    its plain public attributes (a file it reads is named by its content digest)."""
    if is_dataclass(obj) and not isinstance(obj, type):
        return {"type": type(obj).__name__, **asdict(obj)}
    out: dict[str, Any] = {"type": type(obj).__name__}
    for k, v in sorted(vars(obj).items()):
        if k.startswith("_"):
            continue
        if isinstance(v, (bool, int, float, str, type(None))):
            out[k] = v
        elif isinstance(v, (tuple, list)) and all(isinstance(x, (int, float, str)) for x in v):
            out[k] = list(v)
        elif isinstance(v, Path) and v.is_file():
            out[k] = file_digest(v)
        elif k == "device":
            out[k] = str(v)
    return out


def _without_descriptors(data: _ImageData) -> _ImageData:
    """``data`` with its features' descriptors dropped (keypoints and the rest kept)."""
    return replace(data, features=replace(data.features, desc=None))


def _image_to_cache(data: _ImageData, size: tuple[int, int] | None
                    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    f = data.features
    arrays = {"boxes": data.boxes, "scores": data.scores, "textured": data.textured,
              "uv": f.uv, "desc": _numpy(f.desc)}
    if data.colours is not None:
        arrays["colours"] = data.colours
    meta: dict[str, Any] = {"size": list(f.size), "image_size": list(size) if size else None,
                            "desc_torch": not isinstance(f.desc, np.ndarray), "extra": {},
                            "extra_arrays": {}}
    for k, v in f.extra.items():
        if isinstance(v, (np.ndarray, torch.Tensor)):
            arrays[f"x_{k}"] = _numpy(v)
            meta["extra_arrays"][k] = isinstance(v, torch.Tensor)
        else:
            meta["extra"][k] = v
    return arrays, meta


def _image_from_cache(arrays: dict[str, np.ndarray], meta: dict[str, Any],
                      device: Any = None) -> tuple[_ImageData, tuple[int, int] | None]:
    def restore(x: np.ndarray, as_torch: bool) -> Any:
        return torch.as_tensor(x, device=device) if as_torch else x

    extra = dict(meta["extra"])
    for k, as_torch in meta["extra_arrays"].items():
        extra[k] = restore(arrays[f"x_{k}"], as_torch)
    feats = Features(arrays["uv"], restore(arrays["desc"], meta["desc_torch"]),
                     tuple(meta["size"]), extra)
    size = tuple(meta["image_size"]) if meta["image_size"] else None
    return _ImageData(arrays["boxes"], arrays["scores"], feats, arrays["textured"],
                      arrays.get("colours")), size


def _numpy(x: Any) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def _pair_to_cache(p: PairResult, summary: FrontendSummary, m: Matches | None,
                   fallback_on: bool = False) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    arrays = {"box_a": p.box_a, "box_b": p.box_b, "wrong": p.wrong}
    for name in ("kp", "bb"):
        pose = getattr(p, name)
        if pose is not None:
            arrays[f"{name}_R"], arrays[f"{name}_t"] = pose
    if p.inliers is not None:
        arrays["inliers"] = p.inliers
    if m is not None:
        arrays.update(m_uv_a=m.uv_a, m_uv_b=m.uv_b, m_score=m.score)
        if m.idx_a is not None and m.idx_b is not None:
            arrays.update(m_idx_a=m.idx_a, m_idx_b=m.idx_b)
    meta = {"n_kp": p.n_kp, "n_kp_outliers": p.n_kp_outliers, "status": p.status,
            "reason": p.reason, "rotation_only": bool(p.rotation_only), "info": p.info,
            "pairs": dict(summary.pairs), "rejected": dict(summary.rejected),
            "rotation_only_count": summary.rotation_only, "fallback": dict(summary.fallback),
            "fallback_on": fallback_on}
    return arrays, meta


def _pair_from_cache(arrays: dict[str, np.ndarray], meta: dict[str, Any], a: int, b: int,
                     summary: FrontendSummary) -> tuple[PairResult, Matches | None]:
    def pose(name: str) -> tuple[np.ndarray, np.ndarray] | None:
        if f"{name}_R" not in arrays:
            return None
        return arrays[f"{name}_R"], arrays[f"{name}_t"]

    res = PairResult(a, b, arrays["box_a"], arrays["box_b"], arrays["wrong"],
                     int(meta["n_kp"]), int(meta["n_kp_outliers"]), pose("kp"), pose("bb"),
                     meta["status"], reason=meta["reason"],
                     rotation_only=bool(meta["rotation_only"]),
                     inliers=arrays.get("inliers"), info=meta["info"])
    summary.pairs.update(meta["pairs"])
    summary.rejected.update(meta["rejected"])
    summary.rotation_only += int(meta["rotation_only_count"])
    summary.fallback.update(meta.get("fallback", {}))
    m = None
    if "m_uv_a" in arrays:
        m = Matches(arrays["m_uv_a"], arrays["m_uv_b"], arrays["m_score"],
                    arrays.get("m_idx_a"), arrays.get("m_idx_b"))
    return res, m

"""Class-agnostic ROI proposals: the boxes that become a view graph's detections.

The paper runs OLN and keeps the 50 best-scoring boxes per image, dropping boxes larger than
25 % of the image. Three interchangeable sources, each a callable ``(image, key) -> Proposals``
built from plain keyword values (so ``hydra.utils.instantiate`` can make them):

* :class:`SelectiveSearch`: OpenCV contrib selective search on a downscaled copy, ranked by an
  objectness score (colour contrast x persistence, see the class).
* :class:`EdgeBoxes`: OpenCV contrib EdgeBoxes on a gradient edge map computed here (the
  structured-forest edge model is not shipped by any package).
* :class:`FileProposals`: boxes of any external detector (e.g. OLN) from a JSON file.

All three apply :func:`filter_proposals` (clip, minimum side, maximum area, top-k) and are
deterministic: the same image gives the same boxes in the same order. An image where nothing
survives the filters (a blank wall, a uniform image) gives an empty :class:`Proposals`, not an
error: callers count such images.

Measured on the synthetic scenes of ``tests/frontend/test_proposals.py`` (640x480; "easy": 8 scenes,
116 textured rectangles / ellipses on a low-contrast textured background; "hard": 16 scenes,
304 objects, a floor split and clutter) and on 18 frames of
:func:`posernet.data.render.render_sevenscenes` (chess, fire, office, seed 0; 368 ground-truth
boxes no larger than 25 % of the image): recall of the ground-truth boxes by the top 50 at
IoU 0.5 / 0.7, and CPU time per 640x480 image with one OpenCV thread (median; 2-core VM):

========================================  ==========  ==========  ==========  ======
source                                    easy        hard        rendered    ms
========================================  ==========  ==========  ==========  ======
SelectiveSearch() (single, resize 400)    0.97/0.91   0.93/0.80   0.83/0.66      93
SelectiveSearch(resize=320)               0.95/0.84   0.90/0.74   0.74/0.61      51
SelectiveSearch(resize=480)               0.98/0.95   0.91/0.82   0.82/0.67     146
SelectiveSearch("fast", resize=240)       0.98/0.93   0.93/0.87   0.69/0.55     175
SelectiveSearch("fast", resize=320)       0.99/0.93   0.93/0.84   0.74/0.62     313
EdgeBoxes() (resize 320)                  0.84/0.53   0.67/0.42   0.44/0.21      51
EdgeBoxes(resize=None)                    0.78/0.61   0.65/0.43   0.40/0.23     263
========================================  ==========  ==========  ==========  ======

For reference: OpenCV's own selective-search order (random, small fragments first) gives
0.5-0.6 at IoU 0.5 on the hard scenes at resize 400-480 (over 100 candidates), EdgeBoxes with
OpenCV's default parameters on lightly blurred gradient edges 0.3-0.4; every
single-strategy candidate at resize 400 (not only the top 50) covers 0.86 of the rendered
boxes, the misses being mostly objects under 48 px. Most of selective search's time is
OpenCV's own search; scoring adds about 10 ms.

Selective search in OpenCV returns its boxes in a *random* order (``rand() * level``, from the
C library's unseeded generator), so its order is never used: the boxes are put in a canonical
order first and scored by rules that do not depend on it.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..io import atomic_write_json
from ..options import Rule, check_options, option
from ..options import path as path_rule

__all__ = [
    "BOXES_FORMAT",
    "EdgeBoxes",
    "EdgeBoxesOptions",
    "FileProposals",
    "FileProposalsOptions",
    "FilterOptions",
    "ProposalError",
    "Proposals",
    "SelectiveSearch",
    "SelectiveSearchOptions",
    "box_iou",
    "box_persistence",
    "colour_contrast",
    "filter_proposals",
    "gradient_edges",
    "nms",
    "write_proposals_json",
]

BOXES_FORMAT = "posernet-boxes"
BOXES_VERSION = 1


@dataclass
class Proposals:
    """Boxes of one image, best first."""

    boxes: np.ndarray  # (B, 4) float64 pixel xyxy (x1 < x2, y1 < y2), by descending score
    scores: np.ndarray  # (B,) float64

    def __len__(self) -> int:
        return int(self.boxes.shape[0])

    @classmethod
    def empty(cls) -> Proposals:
        """No box: ``(0, 4)`` boxes and ``(0,)`` scores."""
        return cls(np.zeros((0, 4), np.float64), np.zeros(0, np.float64))


class ProposalError(ValueError):
    """A user-caused failure (bad image, bad or missing box file); the message names it. An
    option value out of range is a :class:`~posernet.options.ConfigValueError` (its field's
    rule, :class:`FilterOptions`, ...)."""


# ---------------------------------------------------------------------------- options


@dataclass(frozen=True)
class FilterOptions:
    """The box filter every source applies (:func:`filter_proposals`)."""

    top_k: int | None = option(50, ge=1, help="keep the best this many boxes per image "
                                              "(null: all)")
    max_area: float | None = option(0.25, gt=0, le=1, help="drop boxes over this share of the "
                                                           "image (null: no limit)")
    min_size: float = option(8.0, ge=0, help="drop boxes with a side under this many pixels")

    def __post_init__(self) -> None:
        check_options(self)


@dataclass(frozen=True)
class SelectiveSearchOptions(FilterOptions):
    """The options of :class:`SelectiveSearch` (see there)."""

    strategy: str = option("single", choices=("single", "fast", "quality"),
                           help="selective search strategy")
    resize: int | None = option(400, ge=32, help="longer side (px) of the copy searched "
                                                 "(null: full size)")
    base_k: int = option(150, help="graph-segmentation k (the first k for fast / quality)")
    inc_k: int = option(150, help="k step for fast / quality")
    sigma: float = option(0.8, help="graph-segmentation smoothing")
    nms_iou: float | None = option(0.6, help="NMS threshold on the scored boxes (null: none)")


@dataclass(frozen=True)
class EdgeBoxesOptions(FilterOptions):
    """The options of :class:`EdgeBoxes` (see there; the rest are OpenCV's parameters)."""

    resize: int | None = option(320, ge=32, help="longer side (px) of the working copy "
                                                 "(null: full size)")
    sigma: float = option(3.0, help="blur before the gradients (px of the working copy)")
    alpha: float = option(0.65)
    beta: float = option(0.45)
    eta: float = option(1.0)
    min_score: float = option(0.01)
    max_boxes: int = option(1000, help="boxes EdgeBoxes returns before the area filter")
    edge_min_mag: float = option(0.2)
    edge_merge_thr: float = option(0.5)
    cluster_min_mag: float = option(0.5)
    max_aspect_ratio: float = option(3.0)
    min_box_area: float = option(400.0, help="smallest box searched, in input pixels^2")
    gamma: float = option(2.0)
    kappa: float = option(1.5)


#: a box file: a name (a number is one too) or an ``os.PathLike``
BOX_FILE = Rule("a path", lambda v: isinstance(v, os.PathLike) or path_rule().ok(v))


@dataclass(frozen=True, kw_only=True)
class FileProposalsOptions(FilterOptions):
    """The options of :class:`FileProposals`: the box file and the filter."""

    #: a name or an ``os.PathLike`` (:data:`BOX_FILE`)
    path: str = option(rule=BOX_FILE, help="the JSON box file (layout in docs/formats.md)")


def _options(cls: type, args: dict[str, Any]) -> Any:
    """Options dataclass ``cls`` from a constructor's arguments (checked by its fields)."""
    return cls(**{k: args[k] for k in cls.__dataclass_fields__})


# ---------------------------------------------------------------------------- box utilities


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise IoU ``(N, M)`` of xyxy boxes ``a (N, 4)`` and ``b (M, 4)``."""
    a = np.asarray(a, np.float64).reshape(-1, 4)
    b = np.asarray(b, np.float64).reshape(-1, 4)
    iw = np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0])
    ih = np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1])
    inter = np.clip(iw, 0, None) * np.clip(ih, 0, None)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area_a[:, None] + area_b[None, :] - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)


def nms(boxes: np.ndarray, scores: np.ndarray, iou: float, max_keep: int | None = None
        ) -> np.ndarray:
    """Greedy non-maximum suppression: indices ``(K,)`` of the kept boxes, best first.

    A box is dropped when its IoU with a better kept box is above ``iou``; equal scores keep
    the input order (stable), so the result is deterministic.
    """
    order = np.argsort(-np.asarray(scores, np.float64), kind="stable")
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    keep: list[int] = []
    while order.size and (max_keep is None or len(keep) < max_keep):
        i = int(order[0])
        keep.append(i)
        rest = order[1:]
        order = rest[box_iou(boxes[i:i + 1], boxes[rest])[0] <= iou]
    return np.asarray(keep, dtype=np.int64)


def filter_proposals(
    boxes: Any,
    scores: Any,
    width: int,
    height: int,
    top_k: int | None = 50,
    max_area: float | None = 0.25,
    min_size: float = 8.0,
    nms_iou: float | None = None,
) -> Proposals:
    """The paper's box filter: clip, drop small and large boxes, optional NMS, keep the best.

    Args:
        boxes: ``(N, 4)`` pixel xyxy.
        scores: ``(N,)``; higher is better. Ties keep the input order.
        width, height: the image size in pixels (boxes are clipped to ``[0, width] x [0, height]``).
        top_k: keep at most this many boxes (``None``: all).
        max_area: drop boxes whose area (after clipping) is over this fraction of the image
            (``None``: no limit); the paper drops boxes over 25 %.
        min_size: drop boxes with a side under this many pixels (after clipping).
        nms_iou: if given, greedy NMS at this IoU before ``top_k``.

    Returns:
        :class:`Proposals` sorted by descending score; empty ``(0, 4)`` if nothing survives.
    """
    b = np.asarray(boxes, np.float64)
    s = np.asarray(scores, np.float64)
    if b.size == 0 and s.size == 0:
        return Proposals.empty()
    if b.ndim != 2 or b.shape[1] != 4:
        raise ProposalError(f"boxes must be (N, 4) xyxy, got shape {b.shape}")
    if s.shape != (b.shape[0],):
        raise ProposalError(f"scores must be ({b.shape[0]},) for {b.shape[0]} boxes, "
                            f"got shape {s.shape}")
    if not (np.isfinite(b).all() and np.isfinite(s).all()):
        raise ProposalError("boxes and scores must be finite (found NaN or inf)")
    if width <= 0 or height <= 0:
        raise ProposalError(f"image size must be positive, got {width}x{height}")
    b = b.copy()
    b[:, [0, 2]] = np.clip(b[:, [0, 2]], 0.0, float(width))
    b[:, [1, 3]] = np.clip(b[:, [1, 3]], 0.0, float(height))
    bw, bh = b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]
    ok = (bw >= max(min_size, 0.0)) & (bh >= max(min_size, 0.0)) & (bw > 0) & (bh > 0)
    if max_area is not None:
        ok &= bw * bh <= max_area * width * height
    b, s = b[ok], s[ok]
    if nms_iou is not None:
        order = nms(b, s, nms_iou, max_keep=top_k)
    else:
        order = np.argsort(-s, kind="stable")
        if top_k is not None:
            order = order[:top_k]
    return Proposals(np.ascontiguousarray(b[order]), np.ascontiguousarray(s[order]))


# ---------------------------------------------------------------------------- images


def _as_bgr(image: Any, key: str) -> np.ndarray:
    """The image as ``(H, W, 3)`` uint8 BGR (a gray ``(H, W)`` or ``(H, W, 1)`` is expanded)."""
    name = f"image {key!r}" if key else "image"
    if not isinstance(image, np.ndarray):
        raise ProposalError(f"{name}: expected a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise ProposalError(f"{name}: expected dtype uint8, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise ProposalError(f"{name}: expected shape (H, W, 3) BGR or (H, W) gray, "
                            f"got {image.shape}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise ProposalError(f"{name}: empty image, shape {image.shape}")
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return np.ascontiguousarray(image)


def _downscale(image: np.ndarray, resize: int | None) -> tuple[np.ndarray, np.ndarray]:
    """``(small, scale)``: the image shrunk so its longer side is ``resize`` px (never
    enlarged) and the xyxy factors ``(4,)`` taking its pixels to the original's (per axis:
    rounding makes them differ slightly)."""
    h, w = image.shape[:2]
    if resize is None or max(h, w) <= resize:
        return image, np.ones(4)
    f = resize / max(h, w)
    size = (max(1, round(w * f)), max(1, round(h * f)))
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    sx, sy = w / size[0], h / size[1]
    return small, np.array([sx, sy, sx, sy])


def _rects_to_xyxy(rects: np.ndarray) -> np.ndarray:
    """OpenCV ``(x, y, w, h)`` pixel rects ``(N, 4)`` -> continuous xyxy covering the pixels."""
    r = np.asarray(rects, np.float64).reshape(-1, 4)
    return np.stack([r[:, 0], r[:, 1], r[:, 0] + r[:, 2], r[:, 1] + r[:, 3]], axis=1)


# ---------------------------------------------------------------------------- selective search

_COLOUR_BINS = 8  # per Lab channel: 512-bin histograms (8 beat 4 and 6 in recall)


def _colour_index(small: np.ndarray) -> np.ndarray:
    """Quantised Lab colour ``(h, w)`` int64 in ``[0, _COLOUR_BINS**3)``."""
    lab = cv2.cvtColor(small, cv2.COLOR_BGR2Lab).astype(np.int64)
    q = lab * _COLOUR_BINS // 256
    return (q[..., 0] * _COLOUR_BINS + q[..., 1]) * _COLOUR_BINS + q[..., 2]


def colour_contrast(image: np.ndarray, boxes: np.ndarray, ring: float = 0.2) -> np.ndarray:
    """Chi-square distance ``(N,)`` in ``[0, 1]`` between the Lab colour histogram inside each
    xyxy box ``(N, 4)`` of ``image`` ``(h, w, 3)`` uint8 BGR and that of the ring around it (the
    box grown by ``ring`` x its size on every side, clipped to the image). 0 for a box
    without surround (it fills the image) or without pixels."""
    h, w = image.shape[:2]
    colour = _colour_index(image)
    n_bins = _COLOUR_BINS**3
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    ib = np.clip(np.round(boxes), 0, [w, h, w, h]).astype(np.int64)
    bw, bh = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
    ob = np.round(np.stack([boxes[:, 0] - ring * bw, boxes[:, 1] - ring * bh,
                            boxes[:, 2] + ring * bw, boxes[:, 3] + ring * bh], 1))
    ob = np.clip(ob, 0, [w, h, w, h]).astype(np.int64)
    out = np.zeros(len(boxes))
    for i, ((x1, y1, x2, y2), (u1, v1, u2, v2)) in enumerate(zip(ib, ob, strict=True)):
        if x2 <= x1 or y2 <= y1:
            continue
        inner = np.bincount(colour[y1:y2, x1:x2].ravel(), minlength=n_bins).astype(np.float64)
        outer = np.bincount(colour[v1:v2, u1:u2].ravel(), minlength=n_bins) - inner
        if outer.sum() <= 0:
            continue
        p, q = inner / inner.sum(), outer / outer.sum()
        den = p + q
        out[i] = 0.5 * np.sum(np.divide((p - q) ** 2, den, out=np.zeros_like(p), where=den > 0))
    return out


def box_persistence(boxes: np.ndarray, iou: float = 0.8) -> np.ndarray:
    """How many boxes of ``boxes (N, 4)`` overlap each one at IoU >= ``iou``, itself included:
    ``(N,)`` float64 >= 1."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    out = np.zeros(len(boxes))
    for lo in range(0, len(boxes), 512):  # chunks bound the (512, N) IoU block
        out[lo:lo + 512] = (box_iou(boxes[lo:lo + 512], boxes) >= iou).sum(1)
    return out


class SelectiveSearch:
    """Selective search (``cv2.ximgproc.segmentation``) ranked by an objectness score.

    The search runs on a copy whose longer side is ``resize`` px; boxes are mapped back to the
    input's pixels. Strategies: ``"single"`` (one colour space, one graph segmentation,
    ``switchToSingleStrategy(base_k, sigma)``: fastest), ``"fast"`` (2 colour spaces x 3
    ``k`` x 2 similarity strategies) and ``"quality"`` (5 colour spaces x 5 ``k`` x 4).

    Score: OpenCV orders its boxes by ``rand() * hierarchy level`` (C library generator:
    neither seeded by ``cv2.setRNGSeed`` nor reproducible), so that order is discarded and
    every box (after the size and area filters) gets an objectness score computed on the small
    copy, ``score = colour contrast x persistence``:

    * colour contrast (the CC cue of Alexe et al., "Measuring the objectness of image
      windows"): :func:`colour_contrast`, chi-square distance between the 512-bin Lab
      histogram inside the box and that of a ring around it (20 % of the box size wide);
    * persistence: :func:`box_persistence`, how many candidate boxes overlap this one at
      IoU >= 0.8 (itself included): a region that keeps its box over several merges (and, for
      fast / quality, over colour spaces and ``k``) is a stable object.

    Then NMS at ``nms_iou`` and the :func:`filter_proposals` filters. Measured alternatives:
    OpenCV's random order with ``srand`` seeded (recall 0.5-0.6 at resize 400 on the synthetic
    scenes: it ranks first-level fragments first), and superpixel straddling as a third factor
    (+1 to +3 points on the synthetic scenes, -8 points on rendered 7-Scenes-like frames whose
    textured objects over-segment). The unique box set that OpenCV returns does not depend on
    ``rand()``, the boxes are sorted before scoring and ties keep that order, so the result is
    deterministic (across threads too; no global OpenCV state is touched, so one instance may
    serve several threads).

    Args:
        top_k, max_area, min_size: see :func:`filter_proposals` (``min_size`` in input pixels).
        strategy: ``"single"``, ``"fast"`` or ``"quality"``.
        resize: longer side (px) of the copy the search runs on (``None``: full size).
        base_k: graph-segmentation ``k`` (the first ``k`` for fast / quality).
        inc_k: ``k`` step for fast / quality.
        sigma: graph-segmentation smoothing.
        nms_iou: NMS threshold on the scored boxes (``None``: none).
    """

    name = "selective_search"
    STRATEGIES = ("single", "fast", "quality")
    Options = SelectiveSearchOptions

    def __init__(
        self,
        top_k: int | None = 50,
        max_area: float | None = 0.25,
        min_size: float = 8.0,
        strategy: str = "single",
        resize: int | None = 400,
        base_k: int = 150,
        inc_k: int = 150,
        sigma: float = 0.8,
        nms_iou: float | None = 0.6,
    ) -> None:
        _options(SelectiveSearchOptions, locals())
        self.top_k = None if top_k is None else int(top_k)
        self.max_area = None if max_area is None else float(max_area)
        self.min_size = float(min_size)
        self.strategy = strategy
        self.resize = None if resize is None else int(resize)
        self.base_k = int(base_k)
        self.inc_k = int(inc_k)
        self.sigma = float(sigma)
        self.nms_iou = None if nms_iou is None else float(nms_iou)

    def __repr__(self) -> str:
        return (f"SelectiveSearch(strategy={self.strategy!r}, resize={self.resize}, "
                f"base_k={self.base_k}, top_k={self.top_k})")

    def candidates(self, image: np.ndarray, key: str = ""
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every unique box before filtering and scoring: ``(small, boxes, scale)``, the working
        copy, its xyxy boxes ``(N, 4)`` in lexicographic order and the factors ``(4,)`` taking
        them to ``image``'s pixels (``boxes * scale``)."""
        img = _as_bgr(image, key)
        small, scale = _downscale(img, self.resize)
        ss = cv2.ximgproc.segmentation.createSelectiveSearchSegmentation()
        ss.setBaseImage(small)
        if self.strategy == "single":
            ss.switchToSingleStrategy(self.base_k, self.sigma)
        elif self.strategy == "fast":
            ss.switchToSelectiveSearchFast(self.base_k, self.inc_k, self.sigma)
        else:
            ss.switchToSelectiveSearchQuality(self.base_k, self.inc_k, self.sigma)
        rects = ss.process()
        if rects is None or len(rects) == 0:
            return small, np.zeros((0, 4)), scale
        # canonical order: OpenCV's own is random (see the class docstring)
        return small, np.unique(_rects_to_xyxy(rects), axis=0), scale

    def __call__(self, image: np.ndarray, key: str = "") -> Proposals:
        """Proposals of ``image`` ``(H, W, 3)`` uint8 BGR or ``(H, W)`` gray, in its pixels."""
        small, boxes, scale = self.candidates(image, key)
        h, w = image.shape[:2]
        full = boxes * scale
        # drop what the filters would drop anyway before the per-box scoring loop
        bw, bh = full[:, 2] - full[:, 0], full[:, 3] - full[:, 1]
        ok = (bw >= self.min_size) & (bh >= self.min_size)
        if self.max_area is not None:
            ok &= bw * bh <= self.max_area * w * h
        if not ok.any():
            return Proposals.empty()
        scores = colour_contrast(small, boxes[ok]) * box_persistence(boxes[ok])
        return filter_proposals(full[ok], scores, w, h, self.top_k, self.max_area, self.min_size,
                                self.nms_iou)


# ---------------------------------------------------------------------------- edge boxes


def gradient_edges(image: np.ndarray, sigma: float = 3.0, scale: float | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Thin edges for EdgeBoxes without the structured-forest model.

    Lab colour structure tensor (Sobel gradients of the ``sigma``-blurred image, summed over
    channels and smoothed): magnitude ``sqrt(lambda_max)`` scaled to ``[0, 1]`` by ``scale``
    (``None``: the 99th percentile, but at least a 10-unit Lab step), orientation the
    dominant gradient direction (the edge normal, in ``[0, pi)``, which EdgeBoxes expects);
    then non-maximum suppression across the edge.

    Args:
        image: ``(H, W, 3)`` uint8 BGR.

    Returns:
        ``(edges, orientation)``, both ``(H, W)`` float32.
    """
    lab = cv2.cvtColor(image, cv2.COLOR_BGR2Lab).astype(np.float32)
    if sigma > 0:
        lab = cv2.GaussianBlur(lab, (0, 0), sigma)
    gx = cv2.Sobel(lab, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(lab, cv2.CV_32F, 0, 1, ksize=3)
    jxx, jxy, jyy = ((gx * gx).sum(2), (gx * gy).sum(2), (gy * gy).sum(2))
    # a light blur of the tensor: a stable orientation along the edge
    jxx, jxy, jyy = (cv2.GaussianBlur(j, (0, 0), 1.0) for j in (jxx, jxy, jyy))
    disc = np.sqrt((jxx - jyy) ** 2 + 4 * jxy**2)
    mag = np.sqrt(np.maximum(0.5 * (jxx + jyy + disc), 0))
    theta = np.mod(0.5 * np.arctan2(2 * jxy, jxx - jyy), np.pi).astype(np.float32)
    # a 3x3 Sobel answers 4 to a unit step: the floor keeps a flat, noisy image from having
    # its faint texture stretched to full-strength edges
    floor = 4.0 * 10.0
    ref = scale if scale is not None else max(float(np.percentile(mag, 99)), floor)
    e = np.clip(mag / ref, 0, 1).astype(np.float32)
    return _edge_nms(e, theta), theta


def _edge_nms(e: np.ndarray, theta: np.ndarray, m: float = 1.01, border: int = 5) -> np.ndarray:
    """Keep ``e`` where it is a maximum across the edge (along the normal ``theta``); fade
    edges within ``border`` px of the image border (as in the structured-forest code)."""
    h, w = e.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    c, s = np.cos(theta), np.sin(theta)
    keep = np.ones_like(e, dtype=bool)
    for d in (-1.0, 1.0):
        nb = cv2.remap(e, xs + d * c, ys + d * s, cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE)
        keep &= e * m >= nb
    out = np.where(keep, e, 0).astype(np.float32)
    b = min(border, h // 2, w // 2)
    for i in range(b):  # linear fade: 0 at the border, 1 at ``border`` px
        f = i / border
        out[i, :] *= f
        out[h - 1 - i, :] *= f
        out[:, i] *= f
        out[:, w - 1 - i] *= f
    return out


class EdgeBoxes:
    """EdgeBoxes (``cv2.ximgproc.createEdgeBoxes``) on :func:`gradient_edges`.

    Runs on a copy whose longer side is ``resize`` px; scores are EdgeBoxes' own (edge groups
    wholly inside the box minus those straddling it, normalised by box size). EdgeBoxes is
    deterministic. Gradient edges see texture as well as object outlines, so this source
    trails :class:`SelectiveSearch` in recall (module table); a strong blur (``sigma`` 3 px
    of the working copy) and a looser NMS (``beta`` 0.45 instead of OpenCV's 0.75: more
    distinct boxes in the top 50) doubled its recall at IoU 0.5 on the synthetic scenes.

    Args:
        top_k, max_area, min_size: see :func:`filter_proposals` (``min_size`` in input pixels).
        resize: longer side (px) of the working copy (``None``: full size; slower and no
            better measured).
        sigma: blur before the gradients (px of the working copy).
        alpha, beta, eta, min_score, edge_min_mag, edge_merge_thr, cluster_min_mag,
        max_aspect_ratio, gamma, kappa: EdgeBoxes parameters (OpenCV's defaults but
            ``beta`` 0.45 and ``edge_min_mag`` 0.2, tuned for recall at IoU 0.5).
        max_boxes: boxes EdgeBoxes returns before the area filter (enough to leave ``top_k``).
        min_box_area: smallest box EdgeBoxes searches, in input pixels^2.
    """

    name = "edge_boxes"
    Options = EdgeBoxesOptions

    def __init__(
        self,
        top_k: int | None = 50,
        max_area: float | None = 0.25,
        min_size: float = 8.0,
        resize: int | None = 320,
        sigma: float = 3.0,
        alpha: float = 0.65,
        beta: float = 0.45,
        eta: float = 1.0,
        min_score: float = 0.01,
        max_boxes: int = 1000,
        edge_min_mag: float = 0.2,
        edge_merge_thr: float = 0.5,
        cluster_min_mag: float = 0.5,
        max_aspect_ratio: float = 3.0,
        min_box_area: float = 400.0,
        gamma: float = 2.0,
        kappa: float = 1.5,
    ) -> None:
        _options(EdgeBoxesOptions, locals())
        self.top_k = None if top_k is None else int(top_k)
        self.max_area = None if max_area is None else float(max_area)
        self.min_size = float(min_size)
        self.resize = None if resize is None else int(resize)
        self.sigma = float(sigma)
        self.params = dict(alpha=float(alpha), beta=float(beta), eta=float(eta),
                           minScore=float(min_score), maxBoxes=int(max_boxes),
                           edgeMinMag=float(edge_min_mag), edgeMergeThr=float(edge_merge_thr),
                           clusterMinMag=float(cluster_min_mag),
                           maxAspectRatio=float(max_aspect_ratio), gamma=float(gamma),
                           kappa=float(kappa))
        self.min_box_area = float(min_box_area)

    def __repr__(self) -> str:
        return f"EdgeBoxes(resize={self.resize}, sigma={self.sigma}, top_k={self.top_k})"

    def __call__(self, image: np.ndarray, key: str = "") -> Proposals:
        """Proposals of ``image`` ``(H, W, 3)`` uint8 BGR or ``(H, W)`` gray, in its pixels."""
        img = _as_bgr(image, key)
        h, w = img.shape[:2]
        small, scale = _downscale(img, self.resize)
        if min(small.shape[:2]) < 8:  # EdgeBoxes needs a few pixels of margin
            return Proposals.empty()
        edges, theta = gradient_edges(small, self.sigma)
        min_area = max(self.min_box_area / (scale[0] * scale[1]), 1.0)  # in working pixels
        eb = cv2.ximgproc.createEdgeBoxes(**self.params, minBoxArea=min_area)
        rects, scores = eb.getBoundingBoxes(edges, theta)
        if rects is None or len(rects) == 0:
            return Proposals.empty()
        boxes = _rects_to_xyxy(rects) * scale
        return filter_proposals(boxes, np.asarray(scores, np.float64).reshape(-1), w, h,
                                self.top_k, self.max_area, self.min_size)


# ---------------------------------------------------------------------------- box files


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in pairs:
        if k in out:
            raise ValueError(f"duplicate key {k!r}")
        out[k] = v
    return out


class FileProposals:
    """Boxes from any external detector (e.g. the paper's OLN), read from a JSON file::

        {"format": "posernet-boxes", "version": 1,
         "images": {"<key>": {"boxes": [[x1, y1, x2, y2], ...], "scores": [...optional...]}}}

    ``<key>`` is the image's path relative to the image folder (e.g.
    ``"seq-01/frame-000000.color.png"``) or its bare file name; lookup tries the key as given
    (``\\`` read as ``/``), then the bare file name. Bare names are ambiguous when several
    folders hold the same name (7-Scenes sequences do): use relative paths there. Missing
    scores mean the listed order is the ranking (scores ``1 - i / n``). The file is read and
    validated when the object is made; the usual filters apply per image. Extra keys (per
    file or per image, e.g. labels) are ignored.
    """

    name = "file"
    Options = FileProposalsOptions

    def __init__(self, path: str | os.PathLike[str], top_k: int | None = 50,
                 max_area: float | None = 0.25, min_size: float = 8.0) -> None:
        _options(FileProposalsOptions, locals())
        self.path = Path(path if isinstance(path, str | os.PathLike) else str(path))
        self.top_k = None if top_k is None else int(top_k)
        self.max_area = None if max_area is None else float(max_area)
        self.min_size = float(min_size)
        self.entries = self._load(self.path)

    def __repr__(self) -> str:
        return f"FileProposals({str(self.path)!r}, {len(self.entries)} images)"

    @staticmethod
    def _load(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        if not path.is_file():
            raise ProposalError(f"box file not found: {path}")
        try:
            with open(path, encoding="utf-8") as fh:
                doc = json.load(fh, object_pairs_hook=_no_duplicates)
        except (json.JSONDecodeError, UnicodeDecodeError, ValueError) as exc:
            raise ProposalError(f"{path}: not valid JSON ({exc})") from exc
        if not isinstance(doc, dict) or doc.get("format") != BOXES_FORMAT:
            got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
            raise ProposalError(f"{path}: 'format' must be {BOXES_FORMAT!r}, got {got!r}")
        if doc.get("version") != BOXES_VERSION:
            raise ProposalError(f"{path}: unsupported version {doc.get('version')!r} "
                                f"(this reader knows {BOXES_VERSION})")
        images = doc.get("images")
        if not isinstance(images, dict):
            raise ProposalError(f"{path}: 'images' must be an object of image key -> entry")
        return {str(k).replace("\\", "/"): FileProposals._entry(path, k, v)
                for k, v in images.items()}

    @staticmethod
    def _entry(path: Path, key: str, entry: Any) -> tuple[np.ndarray, np.ndarray]:
        where = f"{path} [{key}]"
        if not isinstance(entry, dict) or not isinstance(entry.get("boxes"), list):
            raise ProposalError(f"{where}: an entry must be an object with a 'boxes' list")
        boxes = entry["boxes"]
        for i, b in enumerate(boxes):
            if not (isinstance(b, list) and len(b) == 4 and all(_is_number(v) for v in b)
                    and all(math.isfinite(v) for v in b)):
                raise ProposalError(f"{where}: box {i} must be 4 finite numbers "
                                    f"[x1, y1, x2, y2], got {b!r}")
            if not (b[2] > b[0] and b[3] > b[1]):
                raise ProposalError(f"{where}: box {i} {b!r} needs x2 > x1 and y2 > y1")
        arr = np.asarray(boxes, np.float64).reshape(-1, 4)
        scores = entry.get("scores")
        if scores is None:
            n = len(boxes)
            return arr, 1.0 - np.arange(n, dtype=np.float64) / max(n, 1)
        if not isinstance(scores, list) or len(scores) != len(boxes):
            got = len(scores) if isinstance(scores, list) else type(scores).__name__
            raise ProposalError(f"{where}: 'scores' must be a list of {len(boxes)} numbers "
                                f"(one per box), got {got}")
        for i, v in enumerate(scores):
            if not (_is_number(v) and math.isfinite(v)):
                raise ProposalError(f"{where}: score {i} must be a finite number, got {v!r}")
        return arr, np.asarray(scores, np.float64).reshape(-1)

    def lookup(self, key: str) -> tuple[np.ndarray, np.ndarray]:
        """Raw ``(boxes (N, 4), scores (N,))`` of image ``key`` (as given, then bare name)."""
        k = str(key).replace("\\", "/")
        hit = self.entries.get(k)
        if hit is None:
            hit = self.entries.get(k.rsplit("/", 1)[-1])
        if hit is None:
            raise ProposalError(f"image {key!r} is not in box file {self.path} (looked up as "
                                f"{k!r} and {k.rsplit('/', 1)[-1]!r}; "
                                f"{len(self.entries)} images there)")
        return hit

    def __call__(self, image: np.ndarray, key: str) -> Proposals:
        """The file's boxes for ``key``, filtered for ``image``'s size (``(H, W[, 3])``)."""
        img = _as_bgr(image, key)
        boxes, scores = self.lookup(key)
        h, w = img.shape[:2]
        return filter_proposals(boxes, scores, w, h, self.top_k, self.max_area, self.min_size)


def write_proposals_json(path: str | os.PathLike[str],
                         proposals: Mapping[str, Proposals | np.ndarray]) -> Path:
    """Write ``{key: Proposals or (N, 4) boxes}`` in :class:`FileProposals`' format."""
    images: dict[str, Any] = {}
    for key, p in proposals.items():
        if isinstance(p, Proposals):
            images[str(key)] = {"boxes": np.asarray(p.boxes, np.float64).tolist(),
                                "scores": np.asarray(p.scores, np.float64).tolist()}
        else:
            images[str(key)] = {"boxes": np.asarray(p, np.float64).reshape(-1, 4).tolist()}
    return atomic_write_json(path, {"format": BOXES_FORMAT, "version": BOXES_VERSION,
                                    "images": images})

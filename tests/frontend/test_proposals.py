"""ROI proposal sources (posernet.frontend.proposals) on synthetic images with known boxes."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest

from posernet.frontend.proposals import (
    EdgeBoxes,
    FileProposals,
    ProposalError,
    Proposals,
    SelectiveSearch,
    box_iou,
    filter_proposals,
    nms,
    write_proposals_json,
)
from posernet.options import ConfigValueError

# ---------------------------------------------------------------------------- synthetic scenes


def _pattern(rng: np.random.Generator, h: int, w: int, kind: int) -> np.ndarray:
    """``(h, w)`` float32 texture of unit amplitude: blurred noise (0), stripes (1), checker (2)."""
    if kind == 0:
        n = cv2.GaussianBlur(rng.normal(0, 1, (h, w, 1)).astype(np.float32), (0, 0), 1.5)
        return n / (n.std() + 1e-6)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    if kind == 1:
        th, period = rng.uniform(0, np.pi), rng.uniform(6, 14)
        return np.sin(2 * np.pi * (xx * np.cos(th) + yy * np.sin(th)) / period)
    period = int(rng.integers(6, 14))
    return 0.8 * ((((xx // period) + (yy // period)) % 2) * 2 - 1)


def synthetic_scene(seed: int, n_objects: int = 15, hard: bool = False, width: int = 640,
                    height: int = 480) -> tuple[np.ndarray, np.ndarray]:
    """A ``(H, W, 3)`` uint8 BGR image of textured, slightly rotated rectangles and ellipses
    of distinct hues on a low-contrast noise background, and the ground-truth xyxy boxes
    ``(M, 4)`` of their visible pixels (objects with >= 400 visible px). ``hard`` adds a
    floor split, stronger background texture and small clutter blobs (not objects)."""
    rng = np.random.default_rng(seed)
    bg = rng.uniform(90, 160, 3).astype(np.float32)
    img = bg + (16.0 if hard else 8.0) * _pattern(rng, height, width, 0)[..., None]
    if hard:
        floor = rng.uniform(60, 180, 3).astype(np.float32)
        floor = floor + 16.0 * _pattern(rng, height, width, 0)[..., None]
        y0 = int(height * rng.uniform(0.5, 0.7))
        img[y0:] = floor[y0:]
        for _ in range(6):
            x, y = rng.integers(0, width), rng.integers(0, height)
            col = img[min(y, height - 1), min(x, width - 1)] + rng.normal(0, 25, 3)
            cv2.circle(img, (int(x), int(y)), int(rng.integers(3, 12)), col.tolist(), -1)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    img += (0.03 * (xx - width / 2) + 0.02 * (yy - height / 2))[..., None]  # soft shading
    labels = np.zeros((height, width), np.int32)
    hues = (np.arange(n_objects) * 180 / n_objects + rng.uniform(0, 12)) % 180
    rng.shuffle(hues)
    for i in range(n_objects):
        hsv = np.uint8([[[hues[i], rng.uniform(120, 255), rng.uniform(90, 240)]]])
        colour = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0].astype(np.float32)
        kind, amp = int(rng.integers(0, 3)), rng.uniform(6, 18)
        pattern = _pattern(rng, height, width, kind)
        mask = np.zeros((height, width), np.uint8)
        cx, cy = rng.uniform(40, width - 40), rng.uniform(40, height - 40)
        a, b = rng.uniform(14, 80), rng.uniform(14, 70)
        angle = rng.uniform(-15, 15)
        if rng.random() < 0.5:
            pts = cv2.boxPoints(((cx, cy), (2 * a, 2 * b), angle)).astype(np.int32)
            cv2.fillPoly(mask, [pts], 255)
        else:
            cv2.ellipse(mask, ((cx, cy), (2 * a, 2 * b), angle), 255, -1)
        m = mask > 0
        img[m] = colour + np.float32(amp) * pattern[m][:, None]
        labels[m] = i + 1
    boxes = []
    for i in range(1, n_objects + 1):
        ys, xs = np.nonzero(labels == i)
        if len(xs) >= 400:
            boxes.append([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1])
    return np.clip(img, 0, 255).astype(np.uint8), np.asarray(boxes, np.float64)


def recall(gt: np.ndarray, boxes: np.ndarray, iou: float = 0.5) -> float:
    """Fraction of ground-truth boxes matched by some proposal at IoU >= ``iou``."""
    if len(boxes) == 0:
        return 0.0
    return float((box_iou(gt, boxes).max(1) >= iou).mean())


@pytest.fixture(scope="module")
def scenes() -> list[tuple[np.ndarray, np.ndarray]]:
    # two easy (15 objects) and two hard (20 objects, clutter) scenes
    return [synthetic_scene(0), synthetic_scene(1),
            synthetic_scene(100, n_objects=20, hard=True),
            synthetic_scene(101, n_objects=20, hard=True)]


def _mean_recall(source, scenes) -> float:
    return float(np.mean([recall(gt, source(img, f"scene-{i}.png").boxes)
                          for i, (img, gt) in enumerate(scenes)]))


def _check_proposals(p: Proposals, w: int, h: int, top_k: int = 50) -> None:
    assert p.boxes.dtype == np.float64 and p.scores.dtype == np.float64
    assert p.boxes.shape == (len(p), 4) and p.scores.shape == (len(p),)
    assert len(p) <= top_k
    b = p.boxes
    assert np.all(b[:, 0] < b[:, 2]) and np.all(b[:, 1] < b[:, 3])
    assert np.all(b >= 0) and np.all(b[:, [0, 2]] <= w) and np.all(b[:, [1, 3]] <= h)
    assert np.all((b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1]) <= 0.25 * w * h)
    assert np.all(np.diff(p.scores) <= 0)  # best first


# ---------------------------------------------------------------------------- filter_proposals


def test_filter_clips_and_drops_small_and_large_boxes():
    boxes = [
        [-10, -5, 50, 40],  # clipped to [0, 0, 50, 40]
        [10, 10, 15, 60],  # 5 px wide: too small
        [0, 0, 60, 60],  # 3600 px > 25 % of 100 x 100
        [90, 90, 130, 120],  # clipped to 10 x 10: kept
        [200, 200, 220, 220],  # outside: nothing left after clipping
    ]
    p = filter_proposals(boxes, [0.5, 0.9, 0.8, 0.7, 0.95], width=100, height=100)
    np.testing.assert_array_equal(p.boxes, [[90, 90, 100, 100], [0, 0, 50, 40]])
    np.testing.assert_array_equal(p.scores, [0.7, 0.5])
    assert len(filter_proposals(boxes, [1] * 5, 100, 100, max_area=None)) == 3
    assert len(filter_proposals(boxes, [1] * 5, 100, 100, min_size=0)) == 3


def test_filter_orders_by_score_keeps_top_k_and_ties_stable():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 400, (30, 2))
    boxes = np.hstack([xy, xy + rng.uniform(10, 60, (30, 2))])
    scores = rng.permutation(30).astype(float) // 3  # ties in threes
    p = filter_proposals(boxes, scores, 500, 500, top_k=7)
    order = np.argsort(-scores, kind="stable")[:7]
    np.testing.assert_array_equal(p.boxes, boxes[order])
    np.testing.assert_array_equal(p.scores, scores[order])
    assert len(filter_proposals(boxes, scores, 500, 500, top_k=None)) == 30


def test_filter_nms_drops_overlaps():
    boxes = [[0, 0, 100, 100], [2, 2, 100, 100], [50, 50, 150, 150], [300, 0, 340, 40]]
    p = filter_proposals(boxes, [0.9, 0.8, 0.7, 0.6], 400, 400, max_area=None, nms_iou=0.5)
    np.testing.assert_array_equal(p.scores, [0.9, 0.7, 0.6])
    np.testing.assert_array_equal(nms(np.asarray(boxes, float), [1, 1, 1, 1], 0.5), [0, 2, 3])


def test_filter_empty_and_bad_input():
    for boxes, scores in (([], []), (np.zeros((0, 4)), np.zeros(0))):
        p = filter_proposals(boxes, scores, 10, 10)
        assert p.boxes.shape == (0, 4) and p.scores.shape == (0,)
    p = filter_proposals([[0, 0, 2, 2]], [1.0], 10, 10)  # all filtered out
    assert p.boxes.shape == (0, 4) and len(p) == 0
    with pytest.raises(ProposalError, match=r"\(N, 4\)"):
        filter_proposals([[0, 0, 1]], [1.0], 10, 10)
    with pytest.raises(ProposalError, match="scores must be"):
        filter_proposals([[0, 0, 5, 5]], [1.0, 2.0], 10, 10)
    with pytest.raises(ProposalError, match="finite"):
        filter_proposals([[0, 0, np.nan, 5]], [1.0], 10, 10)


def test_box_iou():
    a = np.array([[0, 0, 10, 10], [0, 0, 0, 0]], float)
    b = np.array([[5, 0, 15, 10], [0, 0, 10, 10], [20, 20, 30, 30]], float)
    np.testing.assert_allclose(box_iou(a, b), [[1 / 3, 1, 0], [0, 0, 0]])


# ---------------------------------------------------------------------------- image sources


def test_selective_search_recovers_objects(scenes):
    ss = SelectiveSearch()
    for img, _ in scenes[:1]:
        _check_proposals(ss(img), 640, 480)
    # measured 0.97 (0.95-1.0 per scene); 50 random boxes score about 0.06
    assert _mean_recall(ss, scenes) >= 0.8


def test_selective_search_fast_strategy(scenes):
    ss = SelectiveSearch(strategy="fast", resize=240, top_k=50)
    p = ss(scenes[2][0])
    _check_proposals(p, 640, 480)
    assert recall(scenes[2][1], p.boxes) >= 0.75  # measured 0.95


def test_edge_boxes_recovers_objects(scenes):
    eb = EdgeBoxes()
    _check_proposals(eb(scenes[0][0]), 640, 480)
    assert _mean_recall(eb, scenes) >= 0.5  # measured 0.70 (0.63-0.80 per scene)


@pytest.mark.parametrize("make", [SelectiveSearch, EdgeBoxes], ids=["ss", "eb"])
def test_sources_are_deterministic(make, scenes):
    img = scenes[3][0]
    a = make()(img)
    b = make()(img.copy())
    np.testing.assert_array_equal(a.boxes, b.boxes)
    np.testing.assert_array_equal(a.scores, b.scores)
    src = make()  # one instance shared by threads, as the front end does
    with ThreadPoolExecutor(2) as pool:
        for c in pool.map(src, [img, img]):
            np.testing.assert_array_equal(a.boxes, c.boxes)


@pytest.mark.parametrize("make", [SelectiveSearch, EdgeBoxes], ids=["ss", "eb"])
def test_uniform_and_tiny_images_give_empty_proposals(make):
    src = make()
    for img in (np.full((480, 640, 3), 90, np.uint8), np.zeros((240, 320), np.uint8),
                np.full((3, 5, 3), 200, np.uint8)):
        p = src(img, "blank.png")
        assert p.boxes.shape == (0, 4) and p.scores.shape == (0,)


def test_gray_image_is_accepted(scenes):
    img = cv2.cvtColor(scenes[0][0], cv2.COLOR_BGR2GRAY)
    src = SelectiveSearch(top_k=10)
    a = src(img)
    np.testing.assert_array_equal(a.boxes, src(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)).boxes)
    assert 0 < len(a) <= 10


@pytest.mark.parametrize("make", [SelectiveSearch, EdgeBoxes], ids=["ss", "eb"])
def test_bad_images_are_refused(make):
    src = make()
    with pytest.raises(ProposalError, match=r"'a\.png'.*uint8.*float32"):
        src(np.zeros((20, 20, 3), np.float32), "a.png")
    with pytest.raises(ProposalError, match=r"'b\.png'.*shape"):
        src(np.zeros((20, 20, 4), np.uint8), "b.png")
    with pytest.raises(ProposalError, match=r"'c\.png'.*empty"):
        src(np.zeros((0, 20, 3), np.uint8), "c.png")
    with pytest.raises(ProposalError, match="numpy array"):
        src([[1, 2], [3, 4]], "d.png")


def test_bad_settings_are_refused():
    # each option's rule is declared on its field (SelectiveSearchOptions, ...)
    with pytest.raises(ConfigValueError, match="^SelectiveSearchOptions.strategy: 'best' is not "
                                               "one of single, fast, quality$"):
        SelectiveSearch(strategy="best")
    with pytest.raises(ConfigValueError, match=r"^EdgeBoxesOptions.max_area: 1.5 is not a number "
                                               r"in \(0, 1\] or null$"):
        EdgeBoxes(max_area=1.5)
    with pytest.raises(ConfigValueError, match="^SelectiveSearchOptions.top_k: 0 is not"):
        SelectiveSearch(top_k=0)
    with pytest.raises(ConfigValueError, match="^EdgeBoxesOptions.resize: 8 is not an integer "
                                               ">= 32 or null$"):
        EdgeBoxes(resize=8)
    with pytest.raises(ConfigValueError, match="^FileProposalsOptions.path: '' is not a path$"):
        FileProposals("")


def test_hydra_instantiate(tmp_path):
    from hydra.utils import instantiate

    ss = instantiate({"_target_": "posernet.frontend.proposals.SelectiveSearch", "top_k": 20,
                      "max_area": 0.25, "min_size": 8, "strategy": "single", "resize": 320})
    assert isinstance(ss, SelectiveSearch) and ss.top_k == 20 and ss.resize == 320
    eb = instantiate({"_target_": "posernet.frontend.proposals.EdgeBoxes", "resize": None})
    assert isinstance(eb, EdgeBoxes) and eb.resize is None
    path = write_proposals_json(tmp_path / "b.json", {"x.png": np.array([[0, 0, 20, 20]])})
    fp = instantiate({"_target_": "posernet.frontend.proposals.FileProposals",
                      "path": str(path), "top_k": 5})
    assert isinstance(fp, FileProposals) and len(fp(np.zeros((40, 40), np.uint8), "x.png")) == 1
    # the shipped configs build too
    from omegaconf import OmegaConf

    from posernet.cli import CONFIG_DIR

    for name in ("selective_search", "edge_boxes"):
        src = instantiate(OmegaConf.load(Path(CONFIG_DIR) / "proposals" / f"{name}.yaml"))
        assert src.name == name


# ---------------------------------------------------------------------------- box files


def _write(path: Path, doc) -> Path:
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc), encoding="utf-8")
    return path


def _doc(images) -> dict:
    return {"format": "posernet-boxes", "version": 1, "images": images}


def test_file_proposals_round_trip(tmp_path):
    img = np.zeros((480, 640, 3), np.uint8)
    props = Proposals(np.array([[10, 10, 60, 80], [100, 100, 200, 150.5]]), np.array([0.9, 0.4]))
    path = write_proposals_json(tmp_path / "boxes.json", {
        "seq-01/frame-000000.color.png": props,
        "frame-000007.color.png": np.array([[0, 0, 30, 30], [5, 5, 500, 400], [40, 40, 90, 90]]),
    })
    fp = FileProposals(path)
    p = fp(img, "seq-01/frame-000000.color.png")
    np.testing.assert_array_equal(p.boxes, props.boxes)
    np.testing.assert_array_equal(p.scores, props.scores)
    # a bare-name entry answers for any folder; without scores the listed order is the
    # ranking; the 25 % filter drops the big box
    q = fp(img, "seq-02/frame-000007.color.png")
    np.testing.assert_array_equal(q.boxes, [[0, 0, 30, 30], [40, 40, 90, 90]])
    assert q.scores[0] > q.scores[1]
    assert len(FileProposals(path, top_k=1)(img, "seq-02\\frame-000007.color.png")) == 1


def test_file_proposals_filters_and_empty_entry(tmp_path):
    path = _write(tmp_path / "b.json", _doc({
        "a.png": {"boxes": [[-5, -5, 20, 20], [0, 0, 3, 3]], "scores": [1, 2], "labels": [1, 2]},
        "empty.png": {"boxes": []},
    }))
    fp = FileProposals(path)
    p = fp(np.zeros((100, 100), np.uint8), "a.png")
    np.testing.assert_array_equal(p.boxes, [[0, 0, 20, 20]])
    e = fp(np.zeros((100, 100), np.uint8), "empty.png")
    assert e.boxes.shape == (0, 4) and e.scores.shape == (0,)


@pytest.mark.parametrize(
    ("content", "match"),
    [
        ("{not json", r"b\.json: not valid JSON"),
        ('{"format": "posernet-boxes", "version": 1, "images": {"a": {"boxes": []}, '
         '"a": {"boxes": []}}}', r"duplicate key 'a'"),
        ({"format": "coco", "version": 1, "images": {}}, r"'format' must be 'posernet-boxes'"),
        ([1, 2], r"'format' must be"),
        ({"format": "posernet-boxes", "version": 2, "images": {}}, "unsupported version 2"),
        ({"format": "posernet-boxes", "version": 1, "images": []}, "'images' must be"),
        (_doc({"a.png": [[0, 0, 1, 1]]}), r"\[a\.png\]: an entry must be an object"),
        (_doc({"a.png": {"boxes": [[0, 0, 10]]}}), r"\[a\.png\]: box 0 must be 4 finite"),
        (_doc({"a.png": {"boxes": [[0, 0, 5, 5], [0, 0, "1", 4]]}}), "box 1 must be 4 finite"),
        (_doc({"a.png": {"boxes": [[True, 0, 5, 5]]}}), "box 0 must be 4 finite"),
        (_doc({"a.png": {"boxes": [[10, 0, 5, 5]]}}), r"box 0 .* needs x2 > x1 and y2 > y1"),
        (_doc({"a.png": {"boxes": [[0, 5, 5, 5]]}}), "needs x2 > x1 and y2 > y1"),
        (_doc({"a.png": {"boxes": [[0, 0, 5, 5]], "scores": [1, 2]}}),
         r"'scores' must be a list of 1 numbers .* got 2"),
        (_doc({"a.png": {"boxes": [[0, 0, 5, 5]], "scores": 1.0}}), "'scores' must be a list"),
    ],
)
def test_file_proposals_bad_files(tmp_path, content, match):
    path = _write(tmp_path / "b.json", content)
    with pytest.raises(ProposalError, match=match):
        FileProposals(path)


def test_file_proposals_nan(tmp_path):
    # Python's json reads the NaN token; the loader must still refuse it
    path = _write(tmp_path / "b.json", '{"format": "posernet-boxes", "version": 1, "images": '
                  '{"a.png": {"boxes": [[0, 0, 5, 5], [0, NaN, 5, 5]]}}}')
    with pytest.raises(ProposalError, match=r"b\.json \[a\.png\]: box 1 must be 4 finite"):
        FileProposals(path)
    path = _write(tmp_path / "c.json", '{"format": "posernet-boxes", "version": 1, "images": '
                  '{"a.png": {"boxes": [[0, 0, 5, 5]], "scores": [NaN]}}}')
    with pytest.raises(ProposalError, match="score 0 must be a finite number"):
        FileProposals(path)


def test_file_proposals_missing_file_and_key(tmp_path):
    with pytest.raises(ProposalError, match=r"box file not found: .*nope\.json"):
        FileProposals(tmp_path / "nope.json")
    path = write_proposals_json(tmp_path / "b.json", {"seq-01/a.png": np.array([[0, 0, 9, 9]])})
    fp = FileProposals(path)
    with pytest.raises(ProposalError, match=r"image 'seq-02/a\.png' is not in box file .*b\.json"):
        fp(np.zeros((20, 20), np.uint8), "seq-02/a.png")
    with pytest.raises(ProposalError, match=r"'seq-01/a\.png'.*uint8"):
        fp(np.zeros((20, 20), np.float64), "seq-01/a.png")

"""Pictures of an image pair for a person to look at, written as PNG (atomically).

* :func:`draw_matches`: the two images side by side (at one height, dimmed), keypoint matches as
  thin coloured lines and boxes as rectangles, matched box pairs thick in one colour each and
  numbered, with a header line of counts.

OpenCV raster drawing of the front end's :class:`~posernet.frontend.features.Matches`; the
matplotlib figures (error curves, cameras) are in :mod:`posernet.plots`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .frontend.features import MatcherError, Matches, check_image, positive_int
from .io import atomic_path

__all__ = ["draw_matches"]

# distinct, saturated BGR colours for matched box pairs (Tableau 10 + extras)
_PAIR_COLOURS = [
    (180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148),
    (75, 86, 140), (194, 119, 227), (34, 189, 188), (207, 190, 23), (0, 215, 255),
    (255, 0, 255), (0, 255, 0),
]  # fmt: skip


def _pair_colour(k: int) -> tuple[int, int, int]:
    if k < len(_PAIR_COLOURS):
        return _PAIR_COLOURS[k]
    hsv = np.uint8([[[int(k * 0.618034 * 180) % 180, 230, 255]]])  # golden-ratio hues
    return tuple(int(c) for c in cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0])


def _check_boxes(boxes: Any, what: str) -> np.ndarray:
    if boxes is None:
        return np.zeros((0, 4))
    b = np.asarray(boxes, dtype=np.float64)
    if b.size == 0:
        return np.zeros((0, 4))
    if b.ndim != 2 or b.shape[1] != 4:
        raise MatcherError(f"{what} must have shape (B, 4) (x1, y1, x2, y2), got {b.shape}")
    return b


def _label(img: np.ndarray, text: str, org: tuple[int, int], colour: tuple[int, ...]) -> None:
    """Text on a filled box of ``colour`` whose top-left corner is ``org`` (kept inside)."""
    font, fs, th = cv2.FONT_HERSHEY_SIMPLEX, 0.6, 2
    (tw, tht), base = cv2.getTextSize(text, font, fs, th)
    x = int(np.clip(org[0], 0, max(img.shape[1] - tw - 4, 0)))
    y = int(np.clip(org[1], 0, max(img.shape[0] - tht - base - 4, 0)))
    cv2.rectangle(img, (x, y), (x + tw + 4, y + tht + base + 4), colour, -1)
    lum = 0.114 * colour[0] + 0.587 * colour[1] + 0.299 * colour[2]
    ink = (0, 0, 0) if lum > 140 else (255, 255, 255)
    cv2.putText(img, text, (x + 2, y + tht + 2), font, fs, ink, th, cv2.LINE_AA)


def draw_matches(
    image_a: np.ndarray,
    image_b: np.ndarray,
    matches: Matches,
    path: str | os.PathLike[str],
    boxes_a: np.ndarray | None = None,
    boxes_b: np.ndarray | None = None,
    box_pairs: np.ndarray | None = None,
    max_lines: int = 200,
    title: str = "",
) -> Path:
    """Draw two images side by side with keypoint matches and (matched) boxes; write a PNG.

    Args:
        image_a, image_b: (H, W, 3) BGR or (H, W) uint8 images.
        matches: their correspondences; at most ``max_lines`` of them (a fixed random subset) are
            drawn as thin lines.
        path: output PNG, written atomically.
        boxes_a, boxes_b: (B, 4) xyxy pixel boxes, drawn as thin grey rectangles.
        box_pairs: (P, 2) indices into boxes_a / boxes_b: pair k is drawn thick in the same
            distinct colour in both images and labelled ``k``.
        title: text in the header line (followed by the counts).
    Returns:
        ``Path(path)``.
    """
    imgs = []
    for what, im in (("image_a", image_a), ("image_b", image_b)):
        im = check_image(im, what)
        imgs.append(cv2.cvtColor(im, cv2.COLOR_GRAY2BGR) if im.ndim == 2 else im)
    ba, bb = _check_boxes(boxes_a, "boxes_a"), _check_boxes(boxes_b, "boxes_b")
    pairs = np.zeros((0, 2), np.int64) if box_pairs is None else np.asarray(box_pairs)
    pairs = pairs.reshape(-1, 2).astype(np.int64) if pairs.size else np.zeros((0, 2), np.int64)
    if len(pairs) and (
        pairs.min() < 0 or pairs[:, 0].max() >= len(ba) or pairs[:, 1].max() >= len(bb)
    ):
        raise MatcherError(
            f"box_pairs index out of range ({len(ba)} boxes in a, {len(bb)} in b): {pairs.tolist()}"
        )
    max_lines = positive_int(max_lines, "max_lines", minimum=0)

    # both images at one height (at most 720 px): a small image beside a big one is shown as
    # large as its partner, not as a thumbnail; each keeps its own scale for the drawing
    target = min(720, max(im.shape[0] for im in imgs))
    scales = [target / im.shape[0] for im in imgs]
    imgs = [im if s == 1.0 else cv2.resize(im, None, fx=s, fy=s, interpolation=(
        cv2.INTER_AREA if s < 1.0 else cv2.INTER_LINEAR)) for im, s in zip(imgs, scales,
                                                                            strict=True)]
    scale_a, scale_b = scales
    (ha, wa), (hb, wb) = imgs[0].shape[:2], imgs[1].shape[:2]
    gap, head = 8, 30
    canvas = np.full((head + max(ha, hb), wa + gap + wb, 3), 32, np.uint8)
    # half-desaturated, dimmed photos: the coloured lines and boxes stand out on busy images
    for im, x0, h in ((imgs[0], 0, ha), (imgs[1], wa + gap, hb)):
        grey = cv2.cvtColor(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)
        muted = 0.7 * (0.5 * im.astype(np.float32) + 0.5 * grey.astype(np.float32))
        canvas[head : head + h, x0 : x0 + im.shape[1]] = muted.astype(np.uint8)
    off_a, off_b = np.array([0.0, head]), np.array([wa + gap, head])

    n = len(matches)
    sel = np.arange(n)
    if n > max_lines:
        sel = np.sort(np.random.default_rng(0).choice(n, size=max_lines, replace=False))
    overlay = canvas.copy()
    for j, i in enumerate(sel):
        hue = np.uint8([[[int(j * 0.618034 * 180) % 180, 200, 255]]])
        c = tuple(int(v) for v in cv2.cvtColor(hue, cv2.COLOR_HSV2BGR)[0, 0])
        pa = tuple(np.round(matches.uv_a[i] * scale_a + off_a).astype(int))
        pb = tuple(np.round(matches.uv_b[i] * scale_b + off_b).astype(int))
        cv2.line(overlay, pa, pb, c, 1, cv2.LINE_AA)
        cv2.circle(overlay, pa, 2, c, -1, cv2.LINE_AA)
        cv2.circle(overlay, pb, 2, c, -1, cv2.LINE_AA)
    canvas = cv2.addWeighted(overlay, 0.65, canvas, 0.35, 0.0)

    def rect(box: np.ndarray, off: np.ndarray, colour: tuple[int, ...], thick: int,
             scale: float) -> tuple:
        p1 = tuple(np.round(box[:2] * scale + off).astype(int))
        p2 = tuple(np.round(box[2:] * scale + off).astype(int))
        if thick > 1:  # dark rim: a matched box reads against lines and texture alike
            cv2.rectangle(canvas, p1, p2, (0, 0, 0), thick + 2, cv2.LINE_AA)
        cv2.rectangle(canvas, p1, p2, colour, thick, cv2.LINE_AA)
        return p1

    for boxes, off, sc in ((ba, off_a, scale_a), (bb, off_b, scale_b)):
        for box in boxes:
            rect(box, off, (200, 200, 200), 1, sc)
    for k, (i, j) in enumerate(pairs):
        c = _pair_colour(k)
        for box, off, sc in ((ba[i], off_a, scale_a), (bb[j], off_b, scale_b)):
            p1 = rect(box, off, c, 3, sc)
            _label(canvas, str(k), (p1[0], p1[1]), c)

    shown = f"{len(sel)} drawn" if len(sel) < n else "all drawn"
    text = f"{n} matches ({shown})" + (f", {len(pairs)} box pairs" if len(pairs) else "")
    text = f"{title}  |  {text}" if title else text
    cv2.putText(canvas, text, (8, 21), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1,
                cv2.LINE_AA)  # fmt: skip
    ok, buf = cv2.imencode(".png", canvas)
    if not ok:  # pragma: no cover - cv2 encodes any uint8 BGR image
        raise RuntimeError("cv2.imencode failed")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())
    return Path(path)

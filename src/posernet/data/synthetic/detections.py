"""Objectness detector (OLN-like) on a simulated view: noisy, incomplete, with spurious boxes.

From the projected box of each visible cuboid the detector misses some objects, returns parts of
others, jitters every box edge, adds false positives, keeps the ``max_boxes`` best-scoring boxes
and drops boxes larger than ``max_area`` of the image (paper, supplementary).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import DetectorOptions
from .visibility import View

__all__ = ["Detections", "detect"]

_FULL_VIEW = 0.85  # above this visible fraction the whole projected box is the object's box


@dataclass
class Detections:
    """Boxes of one image, best score first.

    ``boxes (B, 4)`` pixel ``(x1, y1, x2, y2)`` as reported; ``true_boxes (B, 4)`` the noise-free
    box of the object (or the box itself for a false positive); ``obj (B,)`` cuboid index, -1 for
    false positives; ``part (B,)`` whether the box covers only part of its object.
    """

    boxes: np.ndarray
    true_boxes: np.ndarray
    obj: np.ndarray
    part: np.ndarray
    score: np.ndarray


def detect(
    view: View, opts: DetectorOptions, width: int, height: int, rng: np.random.Generator
) -> Detections:
    """Simulate the detector on ``view``; every random draw comes from ``rng``."""
    O = view.obj_box.shape[0]
    vis = np.nan_to_num(view.obj_visible, nan=0.0)
    # The box of what is visible: the full projection, or for occluded objects the extent of
    # their visible surface (never larger than the projection).
    full = vis >= _FULL_VIEW
    box = np.where(full[:, None], view.obj_box, view.obj_vis_box)
    box = np.concatenate(
        (np.maximum(box[:, :2], view.obj_box[:, :2]), np.minimum(box[:, 2:], view.obj_box[:, 2:])),
        axis=1,
    )
    wh = box[:, 2:] - box[:, :2]
    seen = (
        view.obj_valid
        & (vis >= opts.min_visible)
        & (vis > 0)
        & (wh.min(1) >= max(opts.min_box_px, 1.0))
    )
    # Draw every random number for every object (fixed count) so the stream does not depend on
    # which objects are visible, then use what applies.
    u_miss = rng.random(O)
    u_part = rng.random(O)
    part_size = rng.uniform(0.45, 0.85, size=(O, 2))
    part_pos = rng.random((O, 2))
    jitter = rng.normal(0.0, opts.box_jitter, size=(O, 4))
    score = rng.uniform(0.5, 1.0, size=O) * (0.5 + 0.5 * vis)

    # small objects are missed more often (objectness drops with size)
    small = np.clip(1.0 - wh.min(1) / (4.0 * max(opts.min_box_px, 1.0)), 0.0, 1.0)
    keep = seen & (u_miss >= opts.miss_rate + (1 - opts.miss_rate) * 0.5 * small)
    is_part = keep & (u_part < opts.part_rate)
    sub_wh = wh * np.where(is_part[:, None], part_size, 1.0)
    sub_lo = box[:, :2] + (wh - sub_wh) * np.where(is_part[:, None], part_pos, 0.0)
    det = np.concatenate((sub_lo, sub_lo + sub_wh), axis=1)
    side = np.concatenate((sub_wh, sub_wh), axis=1)
    det = det + jitter * side

    # false positives: boxes on texture, background, object groups (log-uniform size)
    n_fp = int(rng.poisson(opts.false_positives))
    fp_wh = np.exp(rng.uniform(np.log(20), np.log(0.45 * min(width, height)), size=(n_fp, 2)))
    fp_c = rng.uniform([0, 0], [width, height], size=(n_fp, 2))
    fp = np.concatenate((fp_c - fp_wh / 2, fp_c + fp_wh / 2), axis=1)
    fp_score = rng.uniform(0.05, 0.7, size=n_fp)

    boxes = np.concatenate((det[keep], fp))
    true_boxes = np.concatenate((box[keep], fp))
    obj = np.concatenate((np.nonzero(keep)[0], np.full(n_fp, -1, np.int64)))
    part = np.concatenate((is_part[keep], np.zeros(n_fp, bool)))
    scores = np.concatenate((score[keep], fp_score))

    # clip to the image; drop degenerate boxes and boxes over max_area of the image
    boxes = np.stack(
        (
            np.clip(boxes[:, 0], 0, width),
            np.clip(boxes[:, 1], 0, height),
            np.clip(boxes[:, 2], 0, width),
            np.clip(boxes[:, 3], 0, height),
        ),
        1,
    )
    bw, bh = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
    ok = (bw >= 2.0) & (bh >= 2.0) & (bw * bh <= opts.max_area * width * height)
    order = np.argsort(-scores[ok], kind="stable")[: opts.max_boxes]
    idx = np.nonzero(ok)[0][order]
    return Detections(
        boxes=boxes[idx],
        true_boxes=true_boxes[idx],
        obj=obj[idx],
        part=part[idx],
        score=scores[idx],
    )

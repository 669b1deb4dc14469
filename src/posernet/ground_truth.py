"""Recovered cameras held against ground-truth poses, on plain camera-to-world matrices.

:func:`align_cameras` moves cameras (and 3D points) onto the ground truth by the similarity of
the camera centres, the frame in which the interactive view shows both;
:func:`trajectory_table` is the evo-style trajectory-error table (APE / RPE after a
similarity alignment) that ``posernet-reconstruct`` writes as ``trajectory_errors.md``.
Positions from images are known up to a similarity, so both align by one first.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["GroundTruthAlignment", "align_cameras", "trajectory_table"]


@dataclass(frozen=True)
class GroundTruthAlignment:
    """Cameras (and points) moved onto the ground truth by the similarity
    ``x -> scale * R @ x + t`` of their centres.

    Attributes:
        cameras: ``{name: (4, 4) camera-to-world}`` in the ground truth's frame.
        points: ``(P, 3)`` points moved likewise, or None.
        scale, R ``(3, 3)``, t ``(3,)``: the similarity.
    """

    cameras: dict[str, np.ndarray]
    points: np.ndarray | None
    scale: float
    R: np.ndarray
    t: np.ndarray


def align_cameras(cameras: Mapping[str, np.ndarray], ground_truth: Mapping[str, np.ndarray],
                  points: np.ndarray | None = None) -> GroundTruthAlignment | None:
    """``cameras`` (``{name: (4, 4) camera-to-world}``, any array-like) and ``points (P, 3)``
    moved onto ``ground_truth`` (same form, same names) by the Umeyama similarity of the
    camera centres; None when a camera has no ground truth or there are fewer than 3 (the
    similarity is not determined)."""
    from .geometry import umeyama_alignment

    names = list(cameras)
    if len(names) < 3 or any(ground_truth.get(n) is None for n in names):
        return None
    est_c = np.stack([np.asarray(cameras[n])[:3, 3] for n in names])
    gt_c = np.stack([np.asarray(ground_truth[n])[:3, 3] for n in names])
    s, R, t = (x.numpy() for x in umeyama_alignment(torch.as_tensor(est_c),
                                                    torch.as_tensor(gt_c)))
    S = np.eye(4)
    S[:3, :3], S[:3, 3] = R, t
    out = {}
    for n in names:
        m = np.array(cameras[n], np.float64)
        m[:3, 3] *= s
        out[n] = S @ m
    moved = None if points is None else s * points @ R.T + t
    return GroundTruthAlignment(out, moved, float(s), R, t)


def trajectory_table(cameras: Mapping[str, np.ndarray],
                     ground_truth: Mapping[str, np.ndarray]) -> str | None:
    """The evo-style APE / RPE table (markdown) of ``cameras`` (``{name: (4, 4)
    camera-to-world}``, one component) against ``ground_truth`` (same form), the cameras in
    name order (the trajectory's order for frame-numbered images); None with fewer than 3
    cameras."""
    from .metrics import trajectory_errors

    names = sorted(cameras)
    if len(names) < 3:
        return None
    est = torch.as_tensor(np.stack([np.asarray(cameras[n]) for n in names]))
    ref = torch.as_tensor(np.stack([np.asarray(ground_truth[n]) for n in names]))
    err = trajectory_errors(est, ref)
    rows = [("APE translation (GT units)", err["ape_translation"]),
            ("RPE translation (GT units)", err["rpe_translation"]),
            ("RPE rotation (deg)", err["rpe_rotation_deg"])]
    lines = [f"**Trajectory errors (evo style, Sim(3)-aligned; largest component, {len(names)} "
             f"cameras in name order; scale {err['scale']['sim3']:.4g})**", "",
             "| error | rmse | mean | median | std | min | max |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    lines += [f"| {name} | " + " | ".join(f"{v[k]:.4f}" for k in
                                          ("rmse", "mean", "median", "std", "min", "max")) + " |"
              for name, v in rows]
    return "\n".join(lines) + "\n"

"""Error metrics in the paper's format (Sec. 4): per-edge errors, per-graph means, threshold tables.

The paper's tables are per graph: each graph's error is the mean over its edges (relative poses)
or cameras (absolute poses); a table row gives the percentage of graphs whose error is below each
threshold, and the median over graphs (``eta``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from .geometry import rotation_error_deg, translation_direction_error_deg

__all__ = [
    "ANGLE_THRESHOLDS_DEG",
    "METRE_THRESHOLDS",
    "ThresholdRow",
    "per_graph_mean",
    "relative_pose_errors",
    "threshold_row",
]

ANGLE_THRESHOLDS_DEG: tuple[float, ...] = (3.0, 5.0, 10.0, 30.0, 45.0)
METRE_THRESHOLDS: tuple[float, ...] = (0.05, 0.1, 0.25, 0.5, 0.75)


def relative_pose_errors(edge_pose: Tensor, edge_pose_gt: Tensor) -> tuple[Tensor, Tensor]:
    """Per-edge rotation error and translation-direction error in degrees.

    Shapes: ``edge_pose, edge_pose_gt (E, 7)`` -> two ``(E,)`` tensors. Translations are compared
    as directions (the 5-point algorithm gives unit vectors, the ground truth is metric).
    """
    if edge_pose.shape != edge_pose_gt.shape or edge_pose.shape[-1] != 7:
        raise ValueError(
            f"edge poses must both be (E, 7); got {tuple(edge_pose.shape)} and "
            f"{tuple(edge_pose_gt.shape)}"
        )
    rot = rotation_error_deg(edge_pose[..., :4], edge_pose_gt[..., :4])
    tdir = translation_direction_error_deg(edge_pose[..., 4:], edge_pose_gt[..., 4:])
    return rot, tdir


def per_graph_mean(values: Tensor, batch: Tensor, num_graphs: int) -> Tensor:
    """Mean of ``values (K,)`` per graph given ``batch (K,)``; graphs with no entry give NaN.

    NaN (not 0) marks a graph that has nothing to measure so it can be excluded explicitly.
    """
    if values.ndim != 1 or batch.shape != values.shape:
        raise ValueError(
            f"values and batch must be 1-D of equal length, got {tuple(values.shape)} and "
            f"{tuple(batch.shape)}"
        )
    sums = torch.zeros(num_graphs, dtype=values.dtype, device=values.device)
    sums.index_add_(0, batch, values)
    cnt = torch.bincount(batch, minlength=num_graphs).to(values.dtype)
    return torch.where(cnt > 0, sums / cnt.clamp_min(1), torch.full_like(sums, float("nan")))


@dataclass(frozen=True)
class ThresholdRow:
    """Percentages of graphs under each threshold plus the median over graphs."""

    thresholds: tuple[float, ...]
    percent_below: tuple[float, ...]
    median: float
    count: int

    def as_dict(self, prefix: str = "") -> dict[str, float]:
        out = {f"{prefix}<{t:g}": p for t, p in zip(self.thresholds, self.percent_below,
                                                     strict=True)}
        out[f"{prefix}median"] = self.median
        return out


def threshold_row(per_graph: Tensor | Sequence[float],
                  thresholds: Sequence[float] = ANGLE_THRESHOLDS_DEG) -> ThresholdRow:
    """Summarise per-graph errors like the paper: % of graphs below each threshold, median.

    NaN entries (graphs with nothing measured) are excluded and not counted.
    """
    x = torch.as_tensor(per_graph, dtype=torch.float64).flatten()
    x = x[~torch.isnan(x)]
    n = int(x.numel())
    if n == 0:
        return ThresholdRow(tuple(thresholds), tuple(float("nan") for _ in thresholds),
                            float("nan"), 0)
    pct = tuple(float((x < t).double().mean() * 100.0) for t in thresholds)
    # The median of an even count is the mean of the two middle values (numpy convention).
    median = float(x.quantile(0.5))
    return ThresholdRow(tuple(float(t) for t in thresholds), pct, median, n)

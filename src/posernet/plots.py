"""Figures a person would rather look at than read, saved as PNG (atomically).

* :func:`plot_sorted_errors`: the supplementary's per-graph error curves — graphs sorted by the
  refined error, each curve smoothed with a rolling mean over ``window`` graphs.
* :func:`plot_cameras`: camera centres and viewing directions in 3D (ground truth vs estimates),
  after aligning the estimates to the ground truth.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure  # object API: no pyplot state, no display needed
from torch import Tensor

from .geometry import invert_se3
from .io import atomic_path

__all__ = ["plot_cameras", "plot_sorted_errors", "rolling_mean"]

_COLOURS = {"ground truth": "#1f9bd7", "initial": "#d62728", "refined": "#2ca02c",
            "initial+ba": "#9467bd", "refined+ba": "#ff7f0e"}
#: what a stage's poses are, in words a photo user reads (legend of :func:`plot_cameras`)
STAGE_LABELS = {"initial": "motion averaging", "refined": "PoserNet + motion averaging",
                "initial+ba": "motion averaging + bundle adjustment",
                "refined+ba": "PoserNet + averaging + bundle adjustment"}


def rolling_mean(x: np.ndarray, window: int) -> np.ndarray:
    """Centred rolling mean with a shrinking window at the ends (same length as ``x``)."""
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return x
    w = max(1, min(int(window), x.size))
    c = np.concatenate(([0.0], np.cumsum(x)))
    lo = np.clip(np.arange(x.size) - w // 2, 0, x.size)
    hi = np.clip(lo + w, 0, x.size)
    lo = np.clip(hi - w, 0, x.size)
    return (c[hi] - c[lo]) / (hi - lo)


def _save(fig: Figure, path: str | os.PathLike[str]) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120, bbox_inches="tight")
    return Path(path)


def plot_sorted_errors(
    path: str | os.PathLike[str],
    panels: Mapping[str, Mapping[str, Sequence[float] | Tensor]],
    sort_by: str = "refined",
    window: int = 50,
    ylabels: Mapping[str, str] | None = None,
    title: str | None = None,
) -> Path:
    """Per-graph error curves, one panel per metric, sorted by ``sort_by`` and smoothed.

    Args:
        path: output PNG.
        panels: ``{panel title: {curve label: per-graph errors}}``, e.g.
            ``{"rotation": {"initial": [...], "refined": [...]}}``; all curves of a panel have
            one value per graph (NaN graphs are dropped from every curve of the panel).
        sort_by: curve label whose order sorts the graphs (the paper sorts by the refined one).
        window: rolling-mean window in graphs (the paper uses 50).
        ylabels: y-axis label per panel (default ``"error (deg)"``).
    """
    if not panels:
        raise ValueError("plot_sorted_errors: no panels given")
    fig = Figure(figsize=(8, 3.2 * len(panels)))
    axes = fig.subplots(len(panels), 1, squeeze=False)
    for ax, (name, curves) in zip(axes[:, 0], panels.items(), strict=True):
        arrays = {k: np.asarray(torch.as_tensor(v, dtype=torch.float64)) for k, v in curves.items()}
        if sort_by not in arrays:
            raise ValueError(f"plot_sorted_errors: panel {name!r} has no curve {sort_by!r}")
        lengths = {a.shape for a in arrays.values()}
        if len(lengths) != 1:
            raise ValueError(f"plot_sorted_errors: curves of panel {name!r} differ in length")
        ok = np.all([np.isfinite(a) for a in arrays.values()], axis=0)
        order = np.argsort(arrays[sort_by][ok], kind="stable")
        for label, a in arrays.items():
            y = rolling_mean(a[ok][order], window)
            ax.plot(np.arange(y.size), y, label=label, color=_COLOURS.get(label), lw=1.6)
        ax.set_title(name)
        ax.set_xlabel(f"graph (sorted by {sort_by} error; rolling mean over {window})")
        ax.set_ylabel((ylabels or {}).get(name, "error (deg)"))
        ax.grid(alpha=0.3)
        ax.legend()
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


def plot_cameras(
    path: str | os.PathLike[str],
    poses: Mapping[str, Tensor],
    title: str | None = None,
    axis_length: float | None = None,
    links: str | None = None,
    units: str = "m",
) -> Path:
    """Camera centres and optical axes in 3D for one graph.

    Args:
        path: output PNG.
        poses: ``{label: world-to-camera poses (N, 4, 4)}``, e.g. ground truth, initial and
            refined after motion averaging, already aligned to the ground-truth frame; stage
            names (``initial``, ``initial+ba``, ...) are shown as :data:`STAGE_LABELS`.
        axis_length: length of the drawn optical axis (default: 15% of the scene extent).
        links: a key of ``poses`` whose cameras are each joined to their ``"ground truth"``
            camera by a thin line (the error made visible).
        units: axis unit: ``"m"`` (aligned to metric ground truth) or e.g. ``"scale-free"``.
    """
    if not poses:
        raise ValueError("plot_cameras: no poses given")
    fig = Figure(figsize=(6, 5.5))
    ax = fig.add_subplot(projection="3d")
    centres_all = []
    for T in poses.values():
        c2w = invert_se3(T.detach().double().cpu())
        centres_all.append(c2w[:, :3, 3])
    extent = float(torch.cat(centres_all).std(dim=0).norm()) or 1.0
    length = axis_length or 0.3 * extent
    for (label, T), centres in zip(poses.items(), centres_all, strict=True):
        c2w = invert_se3(T.detach().double().cpu())
        axis = c2w[:, :3, 2] * length  # camera z axis (optical axis) in the world
        colour = _COLOURS.get(label)
        c, a = centres.numpy(), axis.numpy()
        ax.scatter(c[:, 0], c[:, 1], c[:, 2], color=colour, label=STAGE_LABELS.get(label, label),
                   s=18)
        ax.quiver(c[:, 0], c[:, 1], c[:, 2], a[:, 0], a[:, 1], a[:, 2], color=colour,
                  linewidth=1.0, arrow_length_ratio=0.2)
    if links is not None and links in poses and "ground truth" in poses:
        keys = list(poses)
        est = centres_all[keys.index(links)].numpy()
        gt = centres_all[keys.index("ground truth")].numpy()
        for k, (p, q) in enumerate(zip(est, gt, strict=True)):
            ax.plot([p[0], q[0]], [p[1], q[1]], [p[2], q[2]], color="0.45", lw=0.8,
                    label="estimate to ground truth" if k == 0 else None)
    # equal scales on the three axes: a trajectory must not look stretched
    pts = torch.cat(centres_all).numpy()
    mid = 0.5 * (pts.max(0) + pts.min(0))
    half = 0.5 * float((pts.max(0) - pts.min(0)).max()) + length
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel(f"x ({units})")
    ax.set_ylabel(f"y ({units})")
    ax.set_zlabel(f"z ({units})")
    ax.legend(loc="upper left", fontsize=7)
    if title:
        ax.set_title(title)
    return _save(fig, path)

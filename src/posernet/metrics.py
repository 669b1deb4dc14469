"""Error metrics in the paper's format (Sec. 4): per-edge errors, per-graph means, threshold tables.

This module holds the one implementation of the paper's tables: :func:`relative_errors_per_graph`
/ :func:`absolute_errors_per_graph` (per-graph errors from estimated poses, ground truth and the
batch structure) and :func:`relative_rows` / :func:`absolute_rows` (their threshold rows).

The paper's tables are per graph: each graph's error is the mean over its edges (relative poses)
or cameras (absolute poses); a table row gives the percentage of graphs whose error is below each
threshold, and the median over graphs (``eta``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from .geometry import (
    proper_rotation_from_cov,
    rotation_angle,
    rotation_error_deg,
    translation_direction_error_deg,
    umeyama_alignment,
)
from .scatter import scatter_count

__all__ = [
    "ABSOLUTE_KEYS",
    "ALIGNMENTS",
    "ANGLE_THRESHOLDS_DEG",
    "METRE_THRESHOLDS",
    "RELATIVE_KEYS",
    "ROTATION_GAUGES",
    "ThresholdRow",
    "absolute_errors_per_graph",
    "absolute_pose_errors",
    "absolute_pose_errors_per_camera",
    "absolute_rows",
    "align_to_ground_truth",
    "per_graph_mean",
    "relative_errors_per_graph",
    "relative_pose_errors",
    "relative_rows",
    "skipped_per_graph",
    "threshold_row",
    "trajectory_errors",
    "translation_direction_error_deg",
    "unplaced_per_graph",
]

ANGLE_THRESHOLDS_DEG: tuple[float, ...] = (3.0, 5.0, 10.0, 30.0, 45.0)
METRE_THRESHOLDS: tuple[float, ...] = (0.05, 0.1, 0.25, 0.5, 0.75)


def relative_pose_errors(edge_pose: Tensor, edge_pose_gt: Tensor) -> tuple[Tensor, Tensor]:
    """Per-edge rotation error and translation-direction error in degrees.

    Shapes: ``edge_pose, edge_pose_gt (E, 7)`` -> two ``(E,)`` tensors. Translations are compared
    as directions (the 5-point algorithm gives unit vectors, the ground truth is metric). An edge
    whose estimated or true translation has (near) zero length has no direction: its
    translation error is NaN, never 0 (likewise the rotation error of a zero quaternion).
    :func:`per_graph_mean` skips NaN edges; :func:`skipped_per_graph` counts them.
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
    """Mean of ``values (K,)`` per graph given ``batch (K,)``, skipping NaN entries.

    A graph with no (non-NaN) entry gives NaN, not 0, so it can be excluded explicitly
    (:func:`threshold_row` does). Count what was skipped with :func:`skipped_per_graph`.
    """
    if values.ndim != 1 or batch.shape != values.shape:
        raise ValueError(
            f"values and batch must be 1-D of equal length, got {tuple(values.shape)} and "
            f"{tuple(batch.shape)}"
        )
    keep = ~torch.isnan(values)
    values, batch = values[keep], batch[keep]
    sums = torch.zeros(num_graphs, dtype=values.dtype, device=values.device)
    sums.index_add_(0, batch, values)
    cnt = scatter_count(batch, num_graphs).to(values.dtype)
    return torch.where(cnt > 0, sums / cnt.clamp_min(1), torch.full_like(sums, float("nan")))


def skipped_per_graph(values: Tensor, batch: Tensor, num_graphs: int) -> Tensor:
    """Number of NaN entries of ``values (K,)`` per graph (``batch (K,)``), ``[B]`` long:
    what :func:`per_graph_mean` left out."""
    return scatter_count(batch[torch.isnan(values)], num_graphs)


@dataclass(frozen=True)
class ThresholdRow:
    """Percentages of graphs under each threshold plus the median over graphs.

    ``count`` is the number of graphs measured; ``skipped`` the number of items (edges or
    cameras) that had no measurable error and were left out of the per-graph means.
    """

    thresholds: tuple[float, ...]
    percent_below: tuple[float, ...]
    median: float
    count: int
    skipped: int = 0

    def as_dict(self, prefix: str = "") -> dict[str, float]:
        out = {f"{prefix}<{t:g}": p for t, p in zip(self.thresholds, self.percent_below,
                                                     strict=True)}
        out[f"{prefix}median"] = self.median
        return out


def threshold_row(per_graph: Tensor | Sequence[float],
                  thresholds: Sequence[float] = ANGLE_THRESHOLDS_DEG,
                  skipped: int = 0) -> ThresholdRow:
    """Summarise per-graph errors like the paper: % of graphs below each threshold, median.

    NaN entries (graphs with nothing measured) are excluded and not counted. ``skipped`` is
    recorded as is: the number of edges/cameras left out of the per-graph means.
    """
    x = torch.as_tensor(per_graph, dtype=torch.float64).flatten()
    x = x[~torch.isnan(x)]
    n = int(x.numel())
    if n == 0:
        return ThresholdRow(tuple(thresholds), tuple(float("nan") for _ in thresholds),
                            float("nan"), 0, int(skipped))
    pct = tuple(float((x < t).double().mean() * 100.0) for t in thresholds)
    # The median of an even count is the mean of the two middle values (numpy convention).
    median = float(x.quantile(0.5))
    return ThresholdRow(tuple(float(t) for t in thresholds), pct, median, n, int(skipped))


# --------------------------------------------------------------------------- absolute poses
#
# Absolute poses have a gauge freedom (a global rigid or similarity transform), so the estimate
# is aligned to the ground truth before measuring: Umeyama on the
# camera centres (similarity when the scale is unknown, rigid when it is metric), then
#   rotation error of camera i = angle(R_gt_i^T Q R_est_i) on camera-to-world rotations,
#   position error of camera i = | s Q c_est_i + t - c_gt_i |.

ALIGNMENTS: tuple[str, ...] = ("similarity", "rigid")
# Which rotation aligns estimated to true rotations for the rotation error: the one of the
# similarity on camera centres, or the chordal mean of R_gt R_est^T.
ROTATION_GAUGES: tuple[str, ...] = ("centres", "rotations")


def _group_layout(group: Tensor, num_groups: int) -> tuple[Tensor, Tensor, int]:
    """Padded layout of ``K`` items in ``num_groups`` groups: ``(row [K], col [K], width)``."""
    count = scatter_count(group, num_groups)
    order = torch.argsort(group, stable=True)
    start = torch.cumsum(count, 0) - count
    col = torch.empty_like(group)
    col[order] = torch.arange(group.numel(), device=group.device) - start[group[order]]
    return group, col, int(count.max()) if count.numel() else 0


def absolute_pose_errors_per_camera(
    pose_est: Tensor,
    pose_gt: Tensor,
    group: Tensor,
    num_groups: int,
    alignment: str = "similarity",
    valid: Tensor | None = None,
    degenerate_tol: float = 1e-9,
    rotation_gauge: str = "rotations",
) -> tuple[Tensor, Tensor]:
    """Per-camera rotation error (deg) and position error (m) after aligning each group.

    ``pose_est, pose_gt [N, 4, 4]`` world-to-camera; ``group [N]`` the alignment group of each
    camera (its graph, or its connected component), ``0..num_groups-1``; ``valid [N]`` cameras
    to use (others get NaN and take no part in the alignment). Each group is aligned on its
    camera centres (Umeyama; ``alignment`` ``"similarity"`` or ``"rigid"``). When the centres
    cannot fix the rotation (fewer than 3 cameras, or collinear ones: second singular value of
    the covariance below ``degenerate_tol`` times the first), the rotation is taken from the
    cameras' rotations (chordal mean of ``R_gt_c2w R_est_c2w^T``) and scale and offset from the
    centres given it. Batched: one padded ``[G, K, 3]`` problem, no loop over groups.
    """
    Re, Rg, ce, cg, s, Q, t, Q_err = _align_groups(pose_est, pose_gt, group, num_groups,
                                                   alignment, valid, degenerate_tol,
                                                   rotation_gauge)
    rot = torch.rad2deg(rotation_angle(Rg.mT @ Q_err @ Re))
    pos = (s * (Q @ ce[..., None]).squeeze(-1) + t - cg).norm(dim=-1)
    if valid is None:
        return rot, pos
    nan = torch.full_like(rot, float("nan"))
    return torch.where(valid, rot, nan), torch.where(valid, pos, nan)


def _align_groups(pose_est: Tensor, pose_gt: Tensor, group: Tensor, num_groups: int,
                  alignment: str, valid: Tensor | None, degenerate_tol: float,
                  rotation_gauge: str) -> tuple[Tensor, ...]:
    """The per-camera alignment of :func:`absolute_pose_errors_per_camera`.

    Returns camera-to-world rotations ``Re, Rg [N, 3, 3]``, centres ``ce, cg [N, 3]`` and, per
    camera (its group's), the centres' transform ``s [N, 1], Q [N, 3, 3], t [N, 3]`` and the
    rotation ``Q_err [N, 3, 3]`` that aligns orientations (``Q`` for the "centres" gauge).
    """
    if alignment not in ALIGNMENTS:
        raise ValueError(f"alignment={alignment!r}; choose one of {list(ALIGNMENTS)}")
    if rotation_gauge not in ROTATION_GAUGES:
        raise ValueError(f"rotation_gauge={rotation_gauge!r}; choose one of "
                         f"{list(ROTATION_GAUGES)}")
    if pose_est.shape != pose_gt.shape or pose_est.ndim != 3 or pose_est.shape[-2:] != (4, 4):
        raise ValueError(f"pose_est and pose_gt must both be [N, 4, 4], got "
                         f"{tuple(pose_est.shape)} and {tuple(pose_gt.shape)}")
    N = pose_est.shape[0]
    if group.shape != (N,):
        raise ValueError(f"group must be [N] = [{N}], got {tuple(group.shape)}")
    dt = torch.float64
    est, gt = pose_est.to(dt), pose_gt.to(dt)
    for name, p in (("pose_est", est), ("pose_gt", gt)):
        if not bool(torch.isfinite(p).all()):
            raise ValueError(f"{name} has a NaN/inf value")
    if valid is None:
        valid = torch.ones(N, dtype=torch.bool, device=est.device)
    # Camera-to-world rotations and camera centres c = -R^T t.
    Re, Rg = est[:, :3, :3].mT, gt[:, :3, :3].mT
    ce = (Re @ -est[:, :3, 3:]).squeeze(-1)
    cg = (Rg @ -gt[:, :3, 3:]).squeeze(-1)
    row, col, width = _group_layout(group, num_groups)
    G = num_groups
    P_e = torch.zeros(G, max(width, 1), 3, dtype=dt, device=est.device)
    P_g = torch.zeros_like(P_e)
    msk = torch.zeros(G, max(width, 1), dtype=torch.bool, device=est.device)
    P_e[row, col], P_g[row, col], msk[row, col] = ce, cg, valid
    s, Q, t = umeyama_alignment(P_e, P_g, with_scale=alignment == "similarity", mask=msk)
    # Degenerate centre configurations: rotation from the rotations instead.
    cnt = msk.sum(1)
    w = msk.to(dt)[..., None]
    mu_e = (w * P_e).sum(1) / cnt.clamp_min(1)[:, None]
    mu_g = (w * P_g).sum(1) / cnt.clamp_min(1)[:, None]
    xe, xg = (P_e - mu_e[:, None]) * w, (P_g - mu_g[:, None]) * w
    sv = torch.linalg.svdvals(xg.mT @ xe)
    degenerate = (cnt < 3) | (sv[:, 1] <= degenerate_tol * sv[:, 0].clamp_min(1e-300))
    Q_rot = None
    if bool(degenerate.any()) or rotation_gauge == "rotations":
        M = torch.zeros(G, 3, 3, dtype=dt, device=est.device)
        M.index_add_(0, group[valid], (Rg @ Re.mT)[valid])
        Qr, _, _ = proper_rotation_from_cov(M)
        Q_rot = Qr
        var_e = (xe * xe).sum((1, 2))
        if alignment == "similarity":
            sr = torch.where(var_e > 1e-300,
                             (xg * (xe @ Qr.mT)).sum((1, 2)) / var_e.clamp_min(1e-300),
                             torch.ones_like(var_e))
        else:
            sr = torch.ones_like(var_e)
        tr = mu_g - sr[:, None] * (Qr @ mu_e[..., None]).squeeze(-1)
        s = torch.where(degenerate, sr, s)
        Q = torch.where(degenerate[:, None, None], Qr, Q)
        t = torch.where(degenerate[:, None], tr, t)
    Qn = Q[group]
    # "rotations": the rotation error uses the rotation that best aligns the rotations
    # themselves, so bad positions (e.g. from unit-norm translations) do not leak into it.
    Q_err = Q_rot[group] if rotation_gauge == "rotations" else Qn
    return Re, Rg, ce, cg, s[group, None], Qn, t[group], Q_err


def align_to_ground_truth(pose_est: Tensor, pose_gt: Tensor, rotation_gauge: str = "rotations",
                          alignment: str = "similarity") -> Tensor:
    """``pose_est`` moved into the ground-truth frame as :func:`absolute_pose_errors` sees it.

    ``pose_est, pose_gt [N, 4, 4]`` world-to-camera poses of one graph, aligned exactly as
    :func:`absolute_pose_errors_per_camera` aligns a group (same code): camera centres by the
    Umeyama transform of the centres (``alignment``: ``similarity`` or ``rigid``), orientations
    by the rotation that best aligns the rotations (``rotation_gauge="rotations"``, the
    metrics' default) or by the centres' rotation (``"centres"``). The rotation and position
    errors of the result against ``pose_gt`` are those the metrics report, so a plot of it shows
    what the tables measure. Returns ``[N, 4, 4]`` world-to-camera (float64).
    """
    from .geometry import invert_se3, make_se3

    group = torch.zeros(pose_est.shape[0], dtype=torch.long, device=pose_est.device)
    Re, _, ce, _, s, Q, t, Q_err = _align_groups(pose_est, pose_gt, group, 1, alignment, None,
                                                 1e-9, rotation_gauge)
    centres = s * (Q @ ce[..., None]).squeeze(-1) + t
    return invert_se3(make_se3(Q_err @ Re, centres))


def absolute_pose_errors(
    pose_est: Tensor,
    pose_gt: Tensor,
    node_batch: Tensor,
    num_graphs: int,
    alignment: str = "similarity",
    component: Tensor | None = None,
    valid: Tensor | None = None,
    rotation_gauge: str = "rotations",
) -> tuple[Tensor, Tensor]:
    """Per-graph mean rotation error (deg) and camera position error (m), ``[B]`` each.

    ``rotation_gauge="rotations"`` (default) measures rotations after aligning them by the
    rotations themselves (chordal mean of ``R_gt R_est^T``), positions after the similarity on
    the centres; ``"centres"`` uses the centres' alignment for both, which lets bad positions
    (e.g. from unit-norm relative translations) inflate the rotation error.

    Each graph is aligned to its ground truth (see :func:`absolute_pose_errors_per_camera`);
    with ``component [N]`` (global component ids, e.g. ``SyncResult.component``) each connected
    component is aligned on its own. Cameras outside ``valid`` are left out of alignment and
    means; a graph with no valid camera gives NaN (excluded by :func:`threshold_row`).
    """
    if component is not None:
        _, grp = torch.unique(component, return_inverse=True)
        ng = int(grp.max()) + 1 if grp.numel() else 0
    else:
        grp, ng = node_batch, num_graphs
    rot, pos = absolute_pose_errors_per_camera(pose_est, pose_gt, grp, ng, alignment, valid,
                                               rotation_gauge=rotation_gauge)
    keep = ~torch.isnan(rot)
    return (per_graph_mean(rot[keep], node_batch[keep], num_graphs),
            per_graph_mean(pos[keep], node_batch[keep], num_graphs))


# --------------------------------------------------------------------------- the paper's tables
#
# The one path from (estimated poses, ground truth, batch structure) to per-graph errors and
# threshold rows. ``evaluation.evaluate_result`` (refine, eval, demo, reconstruct, the
# experiment runner) and the
# Lightning module's per-graph errors all call these; nothing else builds a table row from
# errors.

RELATIVE_KEYS: tuple[str, ...] = ("rot", "tdir")
ABSOLUTE_KEYS: tuple[str, ...] = ("rot", "trans")


def relative_errors_per_graph(edge_pose: Tensor, edge_pose_gt: Tensor, edge_batch: Tensor,
                              num_graphs: int) -> dict[str, Tensor]:
    """Per-graph mean relative errors (degrees) and what each mean left out.

    ``edge_pose, edge_pose_gt [E, 7]``, ``edge_batch [E]`` -> ``{"rot", "tdir"}`` ``[B]``
    per-graph means (NaN for a graph with no measurable edge) and ``{"rot_skipped",
    "tdir_skipped"}`` ``[B]`` the edges per graph without a measurable error.
    """
    rot, tdir = relative_pose_errors(edge_pose, edge_pose_gt)
    return {"rot": per_graph_mean(rot, edge_batch, num_graphs),
            "tdir": per_graph_mean(tdir, edge_batch, num_graphs),
            "rot_skipped": skipped_per_graph(rot, edge_batch, num_graphs),
            "tdir_skipped": skipped_per_graph(tdir, edge_batch, num_graphs)}


def relative_rows(per_graph: dict[str, Tensor | Sequence[float]],
                  thresholds: Sequence[float] = ANGLE_THRESHOLDS_DEG) -> dict[str, ThresholdRow]:
    """``{"rot", "tdir"}`` threshold rows of per-graph relative errors.

    ``per_graph`` as from :func:`relative_errors_per_graph` (optionally concatenated over
    batches); the ``*_skipped`` counts, when present, are recorded in the rows.
    """
    out = {}
    for key in RELATIVE_KEYS:
        skipped = per_graph.get(f"{key}_skipped")
        out[key] = threshold_row(per_graph[key], thresholds,
                                 skipped=0 if skipped is None else int(torch.as_tensor(
                                     skipped).sum()))
    return out


def unplaced_per_graph(solved: Tensor, node_batch: Tensor, num_graphs: int) -> Tensor:
    """Cameras per graph that motion averaging could not place (``solved`` False), ``[B]``."""
    out = torch.zeros(num_graphs, dtype=torch.long, device=solved.device)
    out.index_add_(0, node_batch.to(solved.device), (~solved.bool()).long())
    return out


def absolute_errors_per_graph(pose_est: Tensor, pose_gt: Tensor, node_batch: Tensor,
                              num_graphs: int, alignment: str = "similarity",
                              component: Tensor | None = None, solved: Tensor | None = None,
                              rotation_gauge: str = "rotations") -> dict[str, Tensor]:
    """Per-graph mean absolute errors after alignment (:func:`absolute_pose_errors`).

    Returns ``{"rot": [B] degrees, "trans": [B] metres}`` (means over the ``solved`` cameras;
    NaN for a graph with none) and ``"unplaced"`` ``[B]`` (:func:`unplaced_per_graph`).
    """
    rot, pos = absolute_pose_errors(pose_est, pose_gt, node_batch, num_graphs,
                                    alignment=alignment, component=component, valid=solved,
                                    rotation_gauge=rotation_gauge)
    if solved is None:
        solved = torch.ones(node_batch.shape, dtype=torch.bool, device=node_batch.device)
    return {"rot": rot, "trans": pos,
            "unplaced": unplaced_per_graph(solved, node_batch, num_graphs)}


def absolute_rows(per_graph: dict[str, Tensor | Sequence[float]]) -> dict[str, ThresholdRow]:
    """``{"rot", "trans"}`` threshold rows (degrees, metres) of per-graph absolute errors."""
    return {"rot": threshold_row(per_graph["rot"], ANGLE_THRESHOLDS_DEG),
            "trans": threshold_row(per_graph["trans"], METRE_THRESHOLDS)}


def trajectory_errors(est_c2w: Tensor, gt_c2w: Tensor) -> dict[str, dict[str, float]]:
    """evo-style APE and RPE of one trajectory, after a similarity alignment (``evo_ape -as``).

    ``est_c2w, gt_c2w [N, 4, 4]`` camera-to-world poses of the same cameras in trajectory
    order (N >= 3). The estimate is mapped onto the ground truth by the Umeyama similarity of
    the camera centres. APE: the translation error of every camera (ground-truth units). RPE:
    between consecutive cameras, the translation (units) and rotation (degrees) of
    ``inv(gt_i^-1 gt_j) (est_i^-1 est_j)``. Each as ``rmse, mean, median, std, min, max``.
    """
    if est_c2w.shape != gt_c2w.shape or est_c2w.ndim != 3 or est_c2w.shape[1:] != (4, 4):
        raise ValueError(f"est and gt must both be [N, 4, 4], got {tuple(est_c2w.shape)} and "
                         f"{tuple(gt_c2w.shape)}")
    if est_c2w.shape[0] < 3:
        raise ValueError("a trajectory needs at least 3 poses")
    est, gt = est_c2w.double(), gt_c2w.double()
    s, R, t = umeyama_alignment(est[:, :3, 3], gt[:, :3, 3])
    aligned = est.clone()
    aligned[:, :3, :3] = R @ est[:, :3, :3]
    aligned[:, :3, 3] = s * est[:, :3, 3] @ R.T + t
    ape = (aligned[:, :3, 3] - gt[:, :3, 3]).norm(dim=1)

    def rel(T: Tensor) -> Tensor:
        return torch.linalg.inv(T[:-1]) @ T[1:]

    d = torch.linalg.inv(rel(gt)) @ rel(aligned)
    rpe_t = d[:, :3, 3].norm(dim=1)
    cos = ((d[:, 0, 0] + d[:, 1, 1] + d[:, 2, 2] - 1) / 2).clamp(-1.0, 1.0)
    rpe_r = torch.rad2deg(torch.arccos(cos))

    def stats(x: Tensor) -> dict[str, float]:
        return {"rmse": float(x.pow(2).mean().sqrt()), "mean": float(x.mean()),
                "median": float(x.median()), "std": float(x.std(unbiased=False)),
                "min": float(x.min()), "max": float(x.max())}

    return {"ape_translation": stats(ape), "rpe_translation": stats(rpe_t),
            "rpe_rotation_deg": stats(rpe_r), "scale": {"sim3": float(s)}}

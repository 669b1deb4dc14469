"""The whole job on view graphs: refine relative poses with PoserNet, average them into absolute
poses, and (when ground truth is present) measure both in the paper's per-graph format.

Used by ``posernet-refine``, ``posernet-demo`` and the experiment runner; usable directly::

    model = PoserNet.from_checkpoint(path)
    result = refine_graphs(model, graphs, backend=get_backend("eig_se3"))
    tables = evaluate_result(result)
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from tqdm.auto import tqdm

from .graph import GraphBatch, GraphValidationError, ViewGraph, load_graphs
from .metrics import (
    ANGLE_THRESHOLDS_DEG,
    METRE_THRESHOLDS,
    absolute_pose_errors,
    per_graph_mean,
    relative_pose_errors,
    threshold_row,
)

__all__ = [
    "RefineResult",
    "evaluate_result",
    "load_input_graphs",
    "refine_graphs",
]

STAGES = ("initial", "refined")


def load_input_graphs(path: str | os.PathLike[str], split: str = "test",
                      estimate: str | None = "kp", strict: bool = True) -> list[ViewGraph]:
    """Graphs from a posernet ``.pt`` file, a folder of them, or an authors'-format ``.json``.

    ``estimate`` picks the initial poses to refine (``kp``/``bb``/...; ``None`` keeps the
    stored ``edge_pose``). ``split`` and ``strict`` apply to JSON input.
    """
    path = Path(path)
    if path.suffix.lower() == ".json":
        from .data.posernet_json import load_posernet_json

        return load_posernet_json(path, split=split, estimate=estimate or "feature_5pt",
                                  strict=strict)
    if path.is_dir():
        files = sorted(path.rglob("*.pt"))
        if not files:
            raise FileNotFoundError(f"no graph files (*.pt) under {path}")
    elif path.is_file():
        files = [path]
    else:
        raise FileNotFoundError(f"input graph file not found: {path}")
    graphs: list[ViewGraph] = []
    for f in files:
        for g in load_graphs(f):
            if estimate is not None:
                if estimate not in g.estimates:
                    raise GraphValidationError(
                        f"{f}: graph {g.name!r} has no initial estimate {estimate!r} "
                        f"(available: {sorted(g.estimates)}); use estimate=null for its "
                        "stored edge_pose")
                g = g.with_estimate(estimate)
            graphs.append(g)
    if not graphs:
        raise GraphValidationError(f"{path}: no graphs")
    return graphs


@dataclass
class RefineResult:
    """Per-graph outputs of :func:`refine_graphs` (lists aligned with ``graphs``).

    ``edge_pose[stage][g] [E_g, 7]`` relative poses for stage ``initial``/``refined``;
    ``absolute[stage][g] [N_g, 4, 4]`` world-to-camera poses after motion averaging (empty
    without a backend); ``solved``/``component`` per camera from the backend.
    """

    graphs: list[ViewGraph]
    edge_pose: dict[str, list[Tensor]]
    absolute: dict[str, list[Tensor]] = field(default_factory=dict)
    solved: dict[str, list[Tensor]] = field(default_factory=dict)
    component: dict[str, list[Tensor]] = field(default_factory=dict)
    backend: dict[str, Any] | None = None


def _split(t: Tensor, ptr: Tensor) -> list[Tensor]:
    return list(torch.split(t.detach().cpu(), torch.diff(ptr).tolist()))


@torch.inference_mode()
def refine_graphs(
    model: torch.nn.Module | None,
    graphs: Sequence[ViewGraph],
    backend: Any | None = None,
    batch_size: int = 64,
    device: str | torch.device = "cpu",
    progress: bool = True,
) -> RefineResult:
    """Refine every graph's ``edge_pose`` with ``model`` and average initial and refined poses.

    Args:
        model: a :class:`posernet.nn.PoserNet` (or any module mapping a batch to ``[E, 7]``);
            ``None`` skips refinement (the refined stage is then absent).
        graphs: input graphs; their ``edge_pose`` is the initial estimate.
        backend: a :mod:`posernet.sync` backend, or ``None`` for relative poses only.
        batch_size: graphs per forward pass / per batched motion-averaging solve.
        device: where to run (``"cuda"`` when available and wanted; never assumed).
    """
    graphs = list(graphs)
    if not graphs:
        raise ValueError("refine_graphs: no graphs given")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    stages = STAGES if model is not None else STAGES[:1]
    out = RefineResult(graphs=graphs, edge_pose={s: [] for s in stages})
    if backend is not None:
        out.backend = backend.describe()
        for d in (out.absolute, out.solved, out.component):
            d.update({s: [] for s in stages})
    if model is not None:
        model = model.to(device).eval()
    bar = tqdm(total=len(graphs), desc="refine", unit="graph", disable=not progress)
    for i in range(0, len(graphs), batch_size):
        chunk = graphs[i:i + batch_size]
        batch = GraphBatch.from_graphs(chunk).to(device)
        poses = {"initial": batch.edge_pose}
        if model is not None:
            poses["refined"] = model(batch).to(batch.edge_pose.dtype)
        for s, p in poses.items():
            out.edge_pose[s] += _split(p, batch.edge_ptr)
            if backend is not None:
                res = backend.solve_with_info(batch, p)
                out.absolute[s] += _split(res.poses, batch.ptr)
                out.solved[s] += _split(res.solved, batch.ptr)
                out.component[s] += _split(res.component, batch.ptr)
        bar.update(len(chunk))
    bar.close()
    return out


def _global_components(per_graph: Sequence[Tensor]) -> Tensor:
    """Renumber each graph's component ids 0..k-1 and offset them so no two graphs share one."""
    out, offset = [], 0
    for c in per_graph:
        local = torch.unique(c, return_inverse=True)[1] if c.numel() else c
        out.append(local + offset)
        offset += int(local.max()) + 1 if c.numel() else 0
    return torch.cat(out)


def evaluate_result(result: RefineResult, rotation_gauge: str = "rotations") -> dict[str, Any]:
    """Per-graph errors and threshold rows for every stage present (needs ground truth).

    Returns ``{"relative": {stage: {"rot": ThresholdRow, "tdir": ThresholdRow}},
    "absolute": {stage: {"rot": ..., "trans": ...}}, "per_graph": {...}, "alignment": str}``.
    ``rotation_gauge`` (``centres`` or ``rotations``) picks how absolute rotations are aligned
    (:func:`posernet.metrics.absolute_pose_errors`).
    Relative errors need ``edge_pose_gt``; absolute ones ``pose_gt`` and a backend. Graphs
    without the needed ground truth raise a :class:`GraphValidationError` naming the graph.
    """
    graphs = result.graphs
    missing = [g.name for g in graphs if g.edge_pose_gt is None]
    if missing:
        raise GraphValidationError(f"graph {missing[0]!r} has no ground truth (edge_pose_gt); "
                                   "cannot measure errors")
    batch = GraphBatch.from_graphs([g.to("cpu") for g in graphs])
    B = batch.num_graphs
    out: dict[str, Any] = {"relative": {}, "absolute": {}, "per_graph": {}}
    for s, poses in result.edge_pose.items():
        rot, tdir = relative_pose_errors(torch.cat(poses).to(batch.edge_pose_gt.dtype),
                                         batch.edge_pose_gt)
        r, t = per_graph_mean(rot, batch.edge_batch, B), per_graph_mean(tdir, batch.edge_batch, B)
        out["per_graph"][f"rel_rot_{s}"], out["per_graph"][f"rel_tdir_{s}"] = r, t
        out["relative"][s] = {"rot": threshold_row(r, ANGLE_THRESHOLDS_DEG),
                              "tdir": threshold_row(t, ANGLE_THRESHOLDS_DEG)}
    if result.absolute and batch.pose_gt is not None:
        metric = bool(result.backend and result.backend.get("scale") in ("given", "oracle"))
        out["alignment"] = "rigid" if metric else "similarity"
        out["rotation_gauge"] = rotation_gauge
        for s, poses in result.absolute.items():
            comp = _global_components(result.component[s])
            rot, pos = absolute_pose_errors(
                torch.cat(poses).double(), batch.pose_gt.double(), batch.node_batch, B,
                alignment=out["alignment"], component=comp, valid=torch.cat(result.solved[s]),
                rotation_gauge=rotation_gauge)
            out["per_graph"][f"abs_rot_{s}"], out["per_graph"][f"abs_pos_{s}"] = rot, pos
            out["absolute"][s] = {"rot": threshold_row(rot, ANGLE_THRESHOLDS_DEG),
                                  "trans": threshold_row(pos, METRE_THRESHOLDS)}
    return out


def _pose_record(T: Tensor) -> dict[str, Any]:
    from .geometry import matrix_to_pose_vec

    p = matrix_to_pose_vec(T.double())
    return {"q_wxyz": p[:4].tolist(), "t": p[4:].tolist(), "matrix": T.double().tolist()}


def result_to_json(result: RefineResult, info: dict[str, Any] | None = None) -> dict[str, Any]:
    """JSON-ready record of a :class:`RefineResult` (format ``posernet-refined``, version 1).

    Per graph: ``edges`` (``source``/``target`` camera ids and, per stage, the relative pose of
    ``source -> target`` as ``q_wxyz``, ``t`` and the 4x4 ``matrix`` mapping source-camera points
    into the target camera) and ``cameras`` (per stage, the world-to-camera pose after motion
    averaging, its camera-to-world inverse, ``solved`` and ``component``).
    """
    from .geometry import invert_se3, pose_vec_to_matrix

    graphs_out = []
    for k, g in enumerate(result.graphs):
        ids = g.meta.get("camera_ids")
        if not (isinstance(ids, list) and len(ids) == g.num_nodes):
            ids = [str(i) for i in range(g.num_nodes)]
        mats = {s: pose_vec_to_matrix(p[k].double()) for s, p in result.edge_pose.items()}
        edges = []
        for e, (i, j) in enumerate(g.edge_index.T.tolist()):
            rec: dict[str, Any] = {"source": str(ids[i]), "target": str(ids[j])}
            rec.update({s: _pose_record(m[e]) for s, m in mats.items()})
            edges.append(rec)
        cams: dict[str, Any] = {}
        for n, cid in enumerate(ids):
            cam: dict[str, Any] = {}
            for s, poses in result.absolute.items():
                T = poses[k][n].double()
                cam[s] = {"world_to_camera": T.tolist(),
                          "camera_to_world": invert_se3(T).tolist(),
                          "q_wxyz": _pose_record(T)["q_wxyz"], "t": T[:3, 3].tolist(),
                          "solved": bool(result.solved[s][k][n]),
                          "component": int(result.component[s][k][n])}
            cams[str(cid)] = cam
        graphs_out.append({"name": g.name, "scene": g.meta.get("scene"), "edges": edges,
                           "cameras": cams})
    return {"format": "posernet-refined", "version": 1, **(info or {}),
            "backend": result.backend, "graphs": graphs_out}


def result_tables(evaluation: dict[str, Any], label: str = "KP",
                  backend: dict[str, Any] | None = None, title: str = "") -> dict[str, Any]:
    """Paper-style :class:`~posernet.report.ResultTable`\\ s from :func:`evaluate_result`.

    ``relative`` (Table 1 layout: initial vs PoserNet) and, with motion averaging,
    ``absolute`` (Table 3 layout), whose note states the scale policy and alignment.
    """
    from .report import ABSOLUTE_GROUPS, ResultTable, TableRow

    names = {"initial": "Initial", "refined": "PoserNet"}
    tables: dict[str, Any] = {
        "relative": ResultTable(
            rows=[TableRow((label, names[s]), cells) for s, cells in
                  evaluation["relative"].items()],
            title=f"Relative poses{title}")}
    if evaluation.get("absolute"):
        bname = (backend or {}).get("backend", "sync")
        stage = {"initial": bname, "refined": f"{bname} + PoserNet"}
        gauge = ("rotations aligned by the rotations" if evaluation.get("rotation_gauge") ==
                 "rotations" else "rotations aligned with the centres")
        note = (f"Scale: {(backend or {}).get('scale_label', 'unknown')}; alignment: "
                f"{evaluation.get('alignment')} (Umeyama on camera centres) per connected "
                f"component; {gauge}")
        tables["absolute"] = ResultTable(
            rows=[TableRow((label, stage[s]), cells) for s, cells in
                  evaluation["absolute"].items()],
            groups=ABSOLUTE_GROUPS, title=f"Absolute poses after motion averaging{title}",
            note=note)
    return tables

"""Refine relative poses with PoserNet and average them into absolute poses, graph by graph
in batches (:func:`refine_graphs`), and the JSON record of the result (:func:`result_to_json`).

Used by ``posernet-refine``, ``-eval``, ``-demo``, ``-reconstruct`` and the experiments::

    model, guard = load_refiner(path)
    result = refine_graphs(model, graphs, backend=get_backend("eig_se3"))
    evaluation = evaluate_result(result)        # posernet.evaluation
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor
from tqdm.auto import tqdm

from .graph import GraphBatch, ViewGraph
from .guard import graph_made_worse, keep_input_mask

__all__ = ["CONFIDENCE_KEYS", "STAGES", "RefineResult", "keep_input", "refine_graphs",
           "result_to_json"]

STAGES = ("initial", "refined")


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
    #: per graph ``[E_g, 4]`` predicted errors in degrees (``CONFIDENCE_NAMES`` order), when
    #: the model has a confidence head; ``gate`` ``[E_g, 2]`` (rotation, direction) when it
    #: has a gate
    confidence: list[Tensor] = field(default_factory=list)
    gate: list[Tensor] = field(default_factory=list)
    #: per graph ``[E_g, 2]`` (rotation, direction): where ``guard=True`` kept the input
    kept_input: list[Tensor] = field(default_factory=list)


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
    guard: bool = False,
    weighted: bool = False,
    edge_weight: Sequence[Tensor] | None = None,
) -> RefineResult:
    """Refine every graph's ``edge_pose`` with ``model`` and average initial and refined poses.

    Args:
        model: a :class:`posernet.nn.PoserNet` (or any module mapping a batch to ``[E, 7]``);
            ``None`` skips refinement (the refined stage is then absent).
        graphs: input graphs; their ``edge_pose`` is the initial estimate.
        backend: a :mod:`posernet.sync` backend, or ``None`` for relative poses only.
        batch_size: graphs per forward pass / per batched motion-averaging solve.
        device: where to run (``"cuda"`` when available and wanted; never assumed).
        guard: keep the input rotation / direction on edges where the model's confidence head
            predicts a smaller error for the input than for its output
            (:func:`posernet.guard.keep_input_mask`), and every input pose of a graph whose
            refined poses are less cycle-consistent than its input
            (:func:`posernet.guard.graph_made_worse`); needs a confidence head.
        weighted: start motion averaging's IRLS from the confidence head's weights
            (``1 / sigma^2`` of the stage's predicted errors) instead of uniform ones.
        edge_weight: per graph ``[E_g, 2]`` (rotation, translation) weights that every stage's
            motion averaging multiplies in, e.g. a translation weight 0 on an edge without a
            usable direction (:mod:`posernet.sync.weighted`).
    """
    graphs = list(graphs)
    if not graphs:
        raise ValueError("refine_graphs: no graphs given")
    if edge_weight is not None and len(edge_weight) != len(graphs):
        raise ValueError(f"refine_graphs: edge_weight has {len(edge_weight)} entries for "
                         f"{len(graphs)} graphs")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    stages = STAGES if model is not None else STAGES[:1]
    out = RefineResult(graphs=graphs, edge_pose={s: [] for s in stages})
    if backend is not None:
        out.backend = backend.describe()
        # the averaging of *every* stage, the input's too, is then weighted by the model
        out.backend["confidence_weights"] = bool(weighted and model is not None
                                                 and getattr(model, "confidence", False))
        for d in (out.absolute, out.solved, out.component):
            d.update({s: [] for s in stages})
    adaptive = model is not None and bool(getattr(model, "adaptive", False))
    has_conf = adaptive and bool(getattr(model, "confidence", False))
    if (guard or weighted) and not has_conf:
        what = "guard=true" if guard else "confidence weights"
        raise ValueError(f"{what} needs a checkpoint with a confidence head "
                         "(net.confidence=true, e.g. model=adaptive)")
    if model is not None:
        model = model.to(device).eval()
    bar = tqdm(total=len(graphs), desc="refine", unit="graph", disable=not progress)
    for i in range(0, len(graphs), batch_size):
        chunk = graphs[i:i + batch_size]
        batch = GraphBatch.from_graphs(chunk).to(device)
        poses = {"initial": batch.edge_pose}
        weights: dict[str, Tensor | None] = {"initial": None, "refined": None}
        if adaptive:
            ex = model(batch, return_extras=True)
            refined = ex.pose.to(batch.edge_pose.dtype)
            if ex.gate is not None:
                out.gate += _split(ex.gate, batch.edge_ptr)
            if ex.sigma is not None:
                sigma = ex.sigma.to(batch.edge_pose.dtype)
                sig_out = sigma[:, :2]
                if guard:
                    keep = keep_input_mask(sigma)
                    # a graph the refinement made less cycle-consistent keeps its input
                    # whole: the confidence head is no judge on inputs unlike its training
                    worse = graph_made_worse(batch, batch.edge_pose, refined)
                    keep = keep | worse[batch.edge_batch][:, None]
                    refined = keep_input(batch.edge_pose, refined, keep)
                    sig_out = torch.where(keep, sigma[:, 2:], sigma[:, :2])
                    out.kept_input += _split(keep, batch.edge_ptr)
                out.confidence += _split(torch.rad2deg(sigma), batch.edge_ptr)
                if weighted:
                    weights = {"initial": sigma[:, 2:].pow(-2), "refined": sig_out.pow(-2)}
            poses["refined"] = refined
        elif model is not None:
            poses["refined"] = model(batch).to(batch.edge_pose.dtype)
        if edge_weight is not None:
            base = torch.cat([torch.as_tensor(w, dtype=batch.edge_pose.dtype).reshape(-1, 2)
                              for w in edge_weight[i:i + batch_size]]).to(device)
            weights = {s: base if w is None else w * base for s, w in weights.items()}
        for s, p in poses.items():
            out.edge_pose[s] += _split(p, batch.edge_ptr)
            if backend is not None:
                res = (backend.solve_with_info(batch, p, edge_weight=weights[s])
                       if weights[s] is not None else backend.solve_with_info(batch, p))
                out.absolute[s] += _split(res.poses, batch.ptr)
                out.solved[s] += _split(res.solved, batch.ptr)
                out.component[s] += _split(res.component, batch.ptr)
        bar.update(len(chunk))
    bar.close()
    return out


def keep_input(edge_pose: Tensor, refined: Tensor, keep: Tensor) -> Tensor:
    """``refined [E, 7]`` with the input rotation (``keep[:, 0]``) and the input direction
    (``keep[:, 1]``) put back where ``keep [E, 2]`` says so (unit quaternion and direction)."""
    from .geometry import quaternion_canonical, quaternion_normalize

    q_in = quaternion_canonical(quaternion_normalize(edge_pose[:, :4]))
    t_in = torch.nn.functional.normalize(edge_pose[:, 4:], dim=-1, eps=1e-12)
    q = torch.where(keep[:, :1], q_in, refined[:, :4])
    t = torch.where(keep[:, 1:], t_in, refined[:, 4:])
    return torch.cat((q, t), dim=-1)


#: keys of an edge's ``confidence`` record in refined.json (degrees): the predicted error of
#: the refined rotation / direction and of the input rotation / direction
CONFIDENCE_KEYS = ("rot_err_deg", "tdir_err_deg", "input_rot_err_deg", "input_tdir_err_deg")


def result_to_json(result: RefineResult, info: dict[str, Any] | None = None) -> dict[str, Any]:
    """JSON-ready record of a :class:`RefineResult` (format ``posernet-refined``, version 1).

    With an adaptive checkpoint every edge also has ``confidence`` (the model's predicted
    errors in degrees, :data:`CONFIDENCE_KEYS`), ``gate`` (0 = input kept, 1 = prediction) and,
    with ``guard=true``, ``kept_input`` (``rotation`` / ``direction`` booleans).

    Per graph: ``edges`` (``source``/``target`` camera ids and, per stage, the relative pose of
    ``source -> target`` as ``q_wxyz``, ``t`` and the 4x4 ``matrix`` mapping source-camera points
    into the target camera), ``cameras`` (per stage, the world-to-camera pose after motion
    averaging, its camera-to-world inverse, ``q_wxyz``, ``t``, ``solved`` and ``component``) and
    ``cameras_placed`` (per stage). A camera the backend could not place (``solved: false``)
    has ``null`` poses and component: no pose is invented (as in ``posernet-poses``). The top
    level ``cameras_placed`` gives ``{stage: {"placed": k, "cameras": n}}`` over all graphs.
    """
    from .geometry import pose_vec_to_matrix
    from .records import camera_record, pose_records

    graphs_out = []
    totals = {s: {"placed": 0, "cameras": 0} for s in result.absolute}
    for k, g in enumerate(result.graphs):
        ids = g.meta.get("camera_ids")
        if not (isinstance(ids, list) and len(ids) == g.num_nodes):
            ids = [str(i) for i in range(g.num_nodes)]
        mats = {s: pose_records(pose_vec_to_matrix(p[k].double()))
                for s, p in result.edge_pose.items()}
        edges = []
        conf = result.confidence[k].double().tolist() if result.confidence else None
        gate = result.gate[k].double().tolist() if result.gate else None
        kept = result.kept_input[k].tolist() if result.kept_input else None
        for e, (i, j) in enumerate(g.edge_index.T.tolist()):
            rec: dict[str, Any] = {"source": str(ids[i]), "target": str(ids[j])}
            rec.update({s: m[e] for s, m in mats.items()})
            if conf is not None:  # the model's predicted errors (degrees)
                rec["confidence"] = dict(zip(CONFIDENCE_KEYS, conf[e], strict=True))
            if gate is not None:  # 0: the input kept, 1: the network's prediction
                rec["gate"] = {"rotation": gate[e][0], "direction": gate[e][1]}
            if kept is not None:
                rec["kept_input"] = {"rotation": kept[e][0], "direction": kept[e][1]}
            edges.append(rec)
        cams: dict[str, Any] = {}
        placed = {s: 0 for s in result.absolute}
        for n, cid in enumerate(ids):
            cam: dict[str, Any] = {}
            for s, poses in result.absolute.items():
                solved = bool(result.solved[s][k][n])
                cam[s] = camera_record(poses[k][n] if solved else None,
                                       result.component[s][k][n])
                placed[s] += solved
            cams[str(cid)] = cam
        for s, c in placed.items():
            totals[s]["placed"] += c
            totals[s]["cameras"] += g.num_nodes
        rec_g: dict[str, Any] = {"name": g.name, "scene": g.meta.get("scene"), "edges": edges,
                                 "cameras": cams}
        if placed:
            rec_g["cameras_placed"] = placed
        graphs_out.append(rec_g)
    out: dict[str, Any] = {"format": "posernet-refined", "version": 1, **(info or {}),
                           "backend": result.backend}
    if totals:
        out["cameras_placed"] = totals
    out["graphs"] = graphs_out
    return out

"""The whole job on view graphs: refine relative poses with PoserNet, average them into absolute
poses, and (when ground truth is present) measure both in the paper's per-graph format.

Used by ``posernet-refine``, ``posernet-demo`` and the experiment runner; usable directly::

    model = PoserNet.from_checkpoint(path)
    result = refine_graphs(model, graphs, backend=get_backend("eig_se3"))
    tables = evaluate_result(result)
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from tqdm.auto import tqdm

from .graph import GraphBatch, GraphValidationError, ViewGraph, load_graphs
from .guard import graph_made_worse, keep_input_mask
from .metrics import (
    absolute_errors_per_graph,
    absolute_rows,
    relative_errors_per_graph,
    relative_rows,
    unplaced_per_graph,
)

__all__ = [
    "RefineResult",
    "evaluate_result",
    "load_input_graphs",
    "refine_graphs",
]

STAGES = ("initial", "refined")


def load_input_graphs(path: str | os.PathLike[str], split: str = "test",
                      estimate: str | None = "kp", strict: bool = True, size: str = "small",
                      log: Callable[[str], None] | None = None) -> list[ViewGraph]:
    """Graphs from a posernet ``.pt`` file, a folder of them, a dataset root or an authors' JSON.

    * ``.json``: the ``split`` list of an authors'-format file (``strict`` applies).
    * a dataset root made by ``posernet-make-data`` (it has ``manifest.json``): the graphs of
      ``split`` (``train``/``val``/``test``) and ``size`` (``small``, ``large`` or ``all``);
      the choice is reported through ``log``.
    * any other folder: every ``.pt`` under it, which must all belong to one split (by each
      graph's ``meta["split"]``, else by a ``train``/``val``/``test`` folder in its path):
      a folder mixing splits without a manifest is refused, naming the folder.
    * a ``.pt`` file: its graphs.

    ``estimate`` picks the initial poses to refine (``kp``/``bb``/...; ``None`` keeps the
    stored ``edge_pose``). Ground truth is optional everywhere. ``log`` (e.g. ``print``)
    receives one line saying what was selected from a dataset root.
    """
    path = Path(path)
    if path.suffix.lower() == ".json":
        from .data.posernet_json import load_posernet_json

        return load_posernet_json(path, split=split, estimate=estimate or "feature_5pt",
                                  strict=strict)
    if path.is_dir():
        if (path / "manifest.json").is_file():
            loaded = _load_dataset_root(path, split, size, log)
        else:
            files = sorted(path.rglob("*.pt"))
            if not files:
                raise FileNotFoundError(f"no graph files (*.pt) under {path}")
            loaded = [(f, load_graphs(f)) for f in files]
            _refuse_mixed_splits(path, loaded)
    elif path.is_file():
        loaded = [(path, load_graphs(path))]
    else:
        raise FileNotFoundError(f"input graph file not found: {path}")
    graphs: list[ViewGraph] = []
    for f, file_graphs in loaded:
        for g in file_graphs:
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


def _load_dataset_root(root: Path, split: str, size: str,
                       log: Callable[[str], None] | None) -> list[tuple[Path, list[ViewGraph]]]:
    """``(file, graphs)`` of one split and size (or all sizes) of a posernet-make-data root."""
    from .data.store import SIZES, SPLITS, DatasetError, available_scenes, read_manifest

    if split not in SPLITS:
        raise DatasetError(f"{root}: is a dataset root; split must be one of {list(SPLITS)}, "
                           f"got {split!r}")
    if size != "all" and size not in SIZES:
        raise DatasetError(f"{root}: is a dataset root; size must be one of "
                           f"{[*SIZES, 'all']}, got {size!r}")
    read_manifest(root)
    sizes = list(SIZES) if size == "all" else [size]
    loaded: list[tuple[Path, list[ViewGraph]]] = []
    counts: dict[str, int] = {}
    for sz in sizes:
        for scene in available_scenes(root, sz, split):
            f = root / sz / split / f"{scene}.pt"
            if not f.is_file():
                raise DatasetError(f"{f}: listed in the manifest but missing")
            loaded.append((f, load_graphs(f)))
            counts[sz] = counts.get(sz, 0) + len(loaded[-1][1])
    if not loaded:
        raise DatasetError(f"{root}: the dataset has no {'/'.join(sizes)} {split} graphs "
                           "(choose another split= or size=)")
    if log is not None:
        what = ", ".join(f"{n} {sz}" for sz, n in counts.items())
        log(f"{root}: dataset root; using split={split} size={size}: {what} {split} graphs "
            f"from {len(loaded)} file(s)")
    return loaded


def _refuse_mixed_splits(folder: Path, loaded: Sequence[tuple[Path, list[ViewGraph]]]) -> None:
    """Raise when the ``.pt`` files under ``folder`` (no manifest) hold more than one split."""
    from .data.store import SPLITS

    by_split: dict[str, list[Path]] = {}
    for f, graphs in loaded:
        named = {str(g.meta["split"]) for g in graphs if g.meta.get("split")}
        if not named:  # no split in the graphs: take it from the folders below ``folder``
            named = {p for p in f.relative_to(folder).parts[:-1] if p in SPLITS}
        for sp in named:
            by_split.setdefault(sp, []).append(f)
    if len(by_split) > 1:
        desc = "; ".join(f"{sp}: {len(fs)} file(s), e.g. {fs[0].relative_to(folder)}"
                         for sp, fs in sorted(by_split.items()))
        raise GraphValidationError(
            f"{folder}: its .pt files mix splits ({desc}) and it has no manifest.json; point "
            "input= at one split's folder (e.g. <dataset>/small/test) or at a dataset root made "
            "by posernet-make-data (then split= and size= choose)")


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


def _global_components(per_graph: Sequence[Tensor]) -> Tensor:
    """Renumber each graph's component ids 0..k-1 and offset them so no two graphs share one."""
    out, offset = [], 0
    for c in per_graph:
        local = torch.unique(c, return_inverse=True)[1] if c.numel() else c
        out.append(local + offset)
        offset += int(local.max()) + 1 if c.numel() else 0
    return torch.cat(out)


def evaluate_result(result: RefineResult, rotation_gauge: str = "rotations") -> dict[str, Any]:
    """Per-graph errors and threshold rows for every stage present, where ground truth exists.

    Returns ``{"relative": {stage: {"rot": ThresholdRow, "tdir": ThresholdRow}},
    "absolute": {stage: {"rot": ..., "trans": ...}}, "per_graph": {...}, "alignment": str,
    "placed": {stage: {...}}, "graphs": B, "graphs_without_gt": {"relative": n, "absolute": n}}``.
    ``rotation_gauge`` (``centres`` or ``rotations``) picks how absolute rotations are aligned
    (:func:`posernet.metrics.absolute_pose_errors`).

    What is not measurable is skipped and counted, never scored:

    * Relative errors need ``edge_pose_gt``; a graph without it gets NaN per-graph errors (left
      out of the rows) and is counted in ``graphs_without_gt["relative"]``. An edge whose
      estimated or true translation has zero length has no direction: it is left out of its
      graph's mean and counted (``ThresholdRow.skipped``, ``per_graph["rel_tdir_skipped_*"]``).
    * Absolute errors need ``pose_gt`` and a backend; graphs without ``pose_gt`` are counted in
      ``graphs_without_gt["absolute"]``. A camera the backend could not place (``solved``
      False: no edge, or an unsolvable component) has no pose: it takes no part in the
      alignment, a graph's error is the mean over its *placed* cameras, and the unplaced ones
      are counted per graph (``per_graph["abs_unplaced_*"]``) and per stage (``placed``:
      ``cameras``, ``placed``, ``graphs_with_unplaced``, ``graphs_with_none_placed``; a graph
      with no camera placed has NaN errors and is left out of the rows).

    Raises :class:`GraphValidationError` when no graph has any ground truth to measure.
    """
    graphs = result.graphs
    B = len(graphs)
    rel_idx = [k for k, g in enumerate(graphs) if g.edge_pose_gt is not None]
    abs_idx = [k for k, g in enumerate(graphs) if g.pose_gt is not None]
    if not rel_idx and not (result.absolute and abs_idx):
        raise GraphValidationError(
            f"none of the {B} graph(s) has ground truth (edge_pose_gt"
            f"{' or pose_gt' if result.absolute else ''}), e.g. {graphs[0].name!r}; "
            "cannot measure errors")
    out: dict[str, Any] = {"relative": {}, "absolute": {}, "per_graph": {}, "graphs": B,
                           "graphs_without_gt": {"relative": B - len(rel_idx),
                                                 "absolute": B - len(abs_idx)}}
    nan = torch.full((B,), float("nan"), dtype=torch.float64)
    if rel_idx:
        sel = torch.tensor(rel_idx)
        gt = torch.cat([graphs[k].edge_pose_gt.cpu() for k in rel_idx])
        eb = sel.repeat_interleave(torch.tensor([graphs[k].num_edges for k in rel_idx]))
        for s, poses in result.edge_pose.items():
            est = torch.cat([poses[k] for k in rel_idx]).to(gt.dtype)
            rel = relative_errors_per_graph(est, gt, eb, B)
            for key, v in rel.items():  # rel_rot_*, rel_tdir_*, rel_rot_skipped_*, ...
                out["per_graph"][f"rel_{key}_{s}"] = v
            out["relative"][s] = relative_rows(rel)
    if result.absolute and abs_idx:
        metric = bool(result.backend and result.backend.get("scale") in ("given", "oracle"))
        out["alignment"] = "rigid" if metric else "similarity"
        out["rotation_gauge"] = rotation_gauge
        out["placed"] = {}
        sel = torch.tensor(abs_idx)
        n_nodes = torch.tensor([graphs[k].num_nodes for k in abs_idx])
        nb = sel.repeat_interleave(n_nodes)
        gt = torch.cat([graphs[k].pose_gt.cpu() for k in abs_idx]).double()
        all_nb = torch.arange(B).repeat_interleave(torch.tensor([g.num_nodes for g in graphs]))
        for s, poses in result.absolute.items():
            solved = [result.solved[s][k].bool() for k in range(B)]
            comp = _global_components([result.component[s][k] for k in abs_idx])
            abs_err = absolute_errors_per_graph(
                torch.cat([poses[k] for k in abs_idx]).double(), gt, nb, B,
                alignment=out["alignment"], component=comp,
                solved=torch.cat([solved[k] for k in abs_idx]), rotation_gauge=rotation_gauge)
            # Unplaced cameras are counted in every graph, with ground truth or not.
            unplaced = unplaced_per_graph(torch.cat(solved), all_nb, B)
            out["per_graph"][f"abs_rot_{s}"] = abs_err["rot"]
            out["per_graph"][f"abs_pos_{s}"] = abs_err["trans"]
            out["per_graph"][f"abs_unplaced_{s}"] = unplaced
            placed_k = n_nodes - unplaced[sel]
            out["placed"][s] = {"cameras": int(n_nodes.sum()), "placed": int(placed_k.sum()),
                                "graphs_with_unplaced": int((placed_k < n_nodes).sum()),
                                "graphs_with_none_placed": int((placed_k == 0).sum())}
            out["absolute"][s] = absolute_rows(abs_err)
    for s in result.edge_pose:  # keep the per-graph keys present, NaN where not measured
        for key in ("rel_rot", "rel_tdir"):
            out["per_graph"].setdefault(f"{key}_{s}", nan.clone())
    return out


def _pose_record(T: Tensor) -> dict[str, Any]:
    from .geometry import matrix_to_pose_vec

    p = matrix_to_pose_vec(T.double())
    return {"q_wxyz": p[:4].tolist(), "t": p[4:].tolist(), "matrix": T.double().tolist()}


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
    from .geometry import invert_se3, pose_vec_to_matrix

    graphs_out = []
    totals = {s: {"placed": 0, "cameras": 0} for s in result.absolute}
    for k, g in enumerate(result.graphs):
        ids = g.meta.get("camera_ids")
        if not (isinstance(ids, list) and len(ids) == g.num_nodes):
            ids = [str(i) for i in range(g.num_nodes)]
        mats = {s: pose_vec_to_matrix(p[k].double()) for s, p in result.edge_pose.items()}
        edges = []
        conf = result.confidence[k].double().tolist() if result.confidence else None
        gate = result.gate[k].double().tolist() if result.gate else None
        kept = result.kept_input[k].tolist() if result.kept_input else None
        for e, (i, j) in enumerate(g.edge_index.T.tolist()):
            rec: dict[str, Any] = {"source": str(ids[i]), "target": str(ids[j])}
            rec.update({s: _pose_record(m[e]) for s, m in mats.items()})
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
                if not bool(result.solved[s][k][n]):
                    cam[s] = {"world_to_camera": None, "camera_to_world": None,
                              "q_wxyz": None, "t": None, "solved": False, "component": None}
                    continue
                T = poses[k][n].double()
                cam[s] = {"world_to_camera": T.tolist(),
                          "camera_to_world": invert_se3(T).tolist(),
                          "q_wxyz": _pose_record(T)["q_wxyz"], "t": T[:3, 3].tolist(),
                          "solved": True,
                          "component": int(result.component[s][k][n])}
                placed[s] += 1
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


def result_tables(evaluation: dict[str, Any], label: str = "KP",
                  backend: dict[str, Any] | None = None, title: str = "") -> dict[str, Any]:
    """Paper-style :class:`~posernet.report.ResultTable`\\ s from :func:`evaluate_result`.

    ``relative`` (Table 1 layout: initial vs PoserNet) and, with motion averaging,
    ``absolute`` (Table 3 layout), whose note states the scale policy and alignment and whose
    rows count the cameras placed (``Cameras placed: k of n``; errors are over placed cameras).
    Graphs without ground truth and edges without a measurable error are counted in the notes.
    """
    from .report import ABSOLUTE_GROUPS, ResultTable, TableRow

    names = {"initial": "Initial", "refined": "PoserNet"}
    B = evaluation.get("graphs")
    missing = evaluation.get("graphs_without_gt", {})

    def unscored(kind: str, what: str) -> str | None:
        n = int(missing.get(kind, 0))
        return (f"{n} of {B} graph(s) have no ground-truth {what} and are not scored."
                if n else None)

    tables: dict[str, Any] = {}
    if evaluation.get("relative"):
        tables["relative"] = ResultTable(
            rows=[TableRow((label, names[s]), cells) for s, cells in
                  evaluation["relative"].items()],
            title=f"Relative poses{title}", note=unscored("relative", "relative poses"))
    if evaluation.get("absolute"):
        bname = (backend or {}).get("backend", "sync")
        base = {"initial": bname, "refined": f"{bname} + PoserNet"}
        if (backend or {}).get("confidence_weights"):
            base["initial"] = f"{bname} (weighted by PoserNet's confidence)"

        def stage_name(s: str) -> str:  # "<stage>+ba": bundle adjustment after averaging
            head, _, tail = s.partition("+")
            return base.get(head, head) + (" + BA" if tail == "ba" else "")

        gauge = ("rotations aligned by the rotations" if evaluation.get("rotation_gauge") ==
                 "rotations" else "rotations aligned with the centres")
        note = (f"Scale: {(backend or {}).get('scale_label', 'unknown')}; alignment: "
                f"{evaluation.get('alignment')} (Umeyama on camera centres) per connected "
                f"component; {gauge}")
        extra = unscored("absolute", "camera poses")
        if extra:
            note += "\n" + extra
        placed = evaluation.get("placed", {})

        def count(s: str) -> tuple[int, int] | None:
            p = placed.get(s)
            return (int(p["placed"]), int(p["cameras"])) if p else None

        tables["absolute"] = ResultTable(
            rows=[TableRow((label, stage_name(s)), cells, placed=count(s)) for s, cells in
                  evaluation["absolute"].items()],
            groups=ABSOLUTE_GROUPS, title=f"Absolute poses after motion averaging{title}",
            note=note)
    return tables

"""From photos to absolute camera poses: the front end builds one view graph of all images,
PoserNet refines its edges (optional), motion averaging places the cameras.

Used by ``posernet-reconstruct``; usable directly::

    records = records_for_images("photos/", "585,585,320,240")
    fe = ImageFrontend(records, SelectiveSearch(), make_matcher("auto"))
    rec = reconstruct(fe, model=PoserNet.from_checkpoint(default_checkpoint()),
                      backend=get_backend("eig_se3"))
    write_poses_json("out/poses.json", rec)

No ground truth is needed. Poses are world-to-camera up to the gauge of motion averaging: each
connected component of the view graph is expressed in the frame of its first camera (identity),
and translations carry the scale policy of the backend (unit relative translations by default),
so positions are up to a similarity. Cameras that could not be placed (no edge, or a component
the backend could not solve) are reported with ``solved: false`` and no pose.
"""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from .frontend.graphs import GraphStats
from .frontend.pipeline import ImageFrontend
from .geometry import invert_se3
from .graph import ViewGraph
from .io import atomic_write_json
from .pipeline import RefineResult, refine_graphs

__all__ = ["Reconstruction", "gauge_fixed", "poses_json", "reconstruct", "write_poses_json"]


@dataclass
class Reconstruction:
    """The graph of all images, the refine/average result and the front end that made it."""

    frontend: ImageFrontend
    graph: ViewGraph
    stats: GraphStats
    result: RefineResult

    @property
    def stage(self) -> str:
        """The final stage: ``refined`` when PoserNet ran, else ``initial``."""
        return "refined" if "refined" in self.result.edge_pose else "initial"


def reconstruct(
    frontend: ImageFrontend,
    model: torch.nn.Module | None,
    backend: Any,
    device: str | torch.device = "cpu",
    name: str = "images",
    estimate: str = "kp",
    progress: bool = True,
    guard: bool = False,
) -> Reconstruction:
    """Evaluate every image pair, assemble the graph, refine its ``estimate`` (``kp`` or ``bb``)
    initial poses with ``model`` (``None``: no refinement) and average them with ``backend``.
    ``guard``: keep the input pose where the model's confidence says refinement would not help
    (:func:`posernet.pipeline.refine_graphs`; needs a confidence head)."""
    n = len(frontend.records)
    frontend.prepare(progress=progress)
    frontend.evaluate_pairs(list(itertools.combinations(range(n), 2)), progress=progress)
    graph, stats = frontend.graph(range(n), meta={"name": name, "size": "all"})
    graph = graph.with_estimate(estimate)
    if graph.num_edges == 0:
        raise ValueError(
            f"no image pair shares {frontend.rules.min_boxes} matched boxes, so no camera can "
            f"be placed ({'; '.join(frontend.summary.lines()[:2])})")
    result = refine_graphs(model, [graph], backend=backend, batch_size=1, device=device,
                           progress=False, guard=guard)
    return Reconstruction(frontend, graph, stats, result)


def gauge_fixed(poses: Tensor, solved: Tensor, component: Tensor) -> Tensor:
    """World-to-camera ``poses (N, 4, 4)`` with each component's first solved camera at the
    identity (``w2c_i <- w2c_i inv(w2c_ref)``); unsolved cameras are left as they are."""
    out = poses.clone().double()
    for c in torch.unique(component[solved]).tolist():
        members = torch.nonzero(solved & (component == c)).flatten()
        ref_inv = invert_se3(out[members[0]])
        out[members] = out[members] @ ref_inv
    return out


def _mat(T: Tensor) -> list[list[float]]:
    return [[round(float(v), 9) for v in row] for row in T.tolist()]


def poses_json(rec: Reconstruction, info: dict[str, Any] | None = None) -> dict[str, Any]:
    """JSON-ready record (format ``posernet-poses``, version 1), see the README."""
    from .geometry import matrix_to_pose_vec, pose_vec_to_matrix

    g, res, stage = rec.graph, rec.result, rec.stage
    cams: dict[str, Any] = {}
    if res.absolute:
        poses = res.absolute[stage][0]
        solved, comp = res.solved[stage][0].bool(), res.component[stage][0]
        fixed = gauge_fixed(poses, solved, comp)
    degree = torch.bincount(g.edge_index.flatten(), minlength=g.num_nodes)
    n_boxes = torch.bincount(g.det_node, minlength=g.num_nodes)
    for i, r in enumerate(rec.frontend.records):
        cam: dict[str, Any] = {"solved": False, "component": None, "camera_to_world": None,
                               "world_to_camera": None, "q_wxyz": None, "t": None,
                               "edges": int(degree[i]), "boxes": int(n_boxes[i])}
        if res.absolute and bool(solved[i]):
            T = fixed[i]
            cam.update(solved=True, component=int(comp[i]), world_to_camera=_mat(T),
                       camera_to_world=_mat(invert_se3(T)),
                       q_wxyz=[float(v) for v in matrix_to_pose_vec(T)[:4]],
                       t=[float(v) for v in T[:3, 3]])
        cams[r.key] = cam
    keys = [r.key for r in rec.frontend.records]
    edges = []
    for e, (i, j) in enumerate(g.edge_index.T.tolist()):
        rows = int((g.pair_edge == e).sum())
        item: dict[str, Any] = {"source": keys[i], "target": keys[j], "matched_boxes": rows}
        for s, p in res.edge_pose.items():
            item[s] = {"q_wxyz": [float(v) for v in p[0][e, :4]],
                       "t": [float(v) for v in p[0][e, 4:]],
                       "matrix": _mat(pose_vec_to_matrix(p[0][e].double()))}
        edges.append(item)
    return {"format": "posernet-poses", "version": 1, **(info or {}), "stage": stage,
            "backend": res.backend, "frontend": rec.frontend.summary.to_dict(),
            "cameras": cams, "edges": edges}


def write_poses_json(path: str | os.PathLike[str], rec: Reconstruction,
                     info: dict[str, Any] | None = None) -> Path:
    """Write :func:`poses_json` atomically."""
    return atomic_write_json(path, poses_json(rec, info), indent=1)

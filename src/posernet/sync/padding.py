"""The padded per-component layout every batched backend works on: the solvable components
(>= 2 nodes) laid out as ``[G, n]`` nodes and ``[G, m]`` edges for batched linear algebra, and
the scatter of per-component results back to nodes, edges and graphs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..geometry import make_se3, quaternion_to_rotation_matrix
from ..scatter import scatter_all, scatter_count
from .components import Components

__all__ = ["PaddedProblem", "assemble", "build_padded", "edge_rotations"]


@dataclass
class PaddedProblem:
    """Solvable components (>= 2 nodes) laid out padded for batched linear algebra.

    ``G`` components, ``n`` = largest component, ``m`` = most edges in a component.
    ``node [G, n]`` global node id (-1 pad), ``node_mask [G, n]``; ``edge [G, m]`` global edge id
    (-1 pad), ``edge_mask [G, m]``, ``src``/``dst [G, m]`` local endpoints (0 on pads);
    ``R [G, m, 3, 3]``, ``t [G, m, 3]`` relative rotation/translation of ``src -> dst``
    (identity/zero on pads); ``comp_id [G]`` global component id; ``count [G]`` node count.
    """

    node: Tensor
    node_mask: Tensor
    edge: Tensor
    edge_mask: Tensor
    src: Tensor
    dst: Tensor
    R: Tensor
    t: Tensor
    comp_id: Tensor
    count: Tensor

    @property
    def G(self) -> int:
        return int(self.node.shape[0])

    @property
    def n(self) -> int:
        return int(self.node.shape[1])

    @property
    def m(self) -> int:
        return int(self.edge.shape[1])

    def select(self, idx: Tensor) -> PaddedProblem:
        """Sub-problem of the components ``idx`` (trimmed to their own padding)."""
        n = int(self.count[idx].max())
        m = int(self.edge_mask[idx].sum(1).max())
        return PaddedProblem(
            node=self.node[idx, :n], node_mask=self.node_mask[idx, :n],
            edge=self.edge[idx, :m], edge_mask=self.edge_mask[idx, :m],
            src=self.src[idx, :m], dst=self.dst[idx, :m], R=self.R[idx, :m], t=self.t[idx, :m],
            comp_id=self.comp_id[idx], count=self.count[idx],
        )


def build_padded(edge_index: Tensor, R: Tensor, t: Tensor, comps: Components) -> PaddedProblem:
    """Pad the solvable components; ``R [E, 3, 3]``, ``t [E, 3]`` per stored edge."""
    dev = edge_index.device
    solvable = (comps.size >= 2).nonzero().squeeze(1)
    G = int(solvable.numel())
    remap = torch.full((comps.num,), -1, dtype=torch.long, device=dev)
    remap[solvable] = torch.arange(G, device=dev)
    n = int(comps.size[solvable].max())
    node_g = remap[comps.comp]
    keep = node_g >= 0
    node = torch.full((G, n), -1, dtype=torch.long, device=dev)
    node[node_g[keep], comps.local[keep]] = keep.nonzero().squeeze(1)
    E = edge_index.shape[1]
    edge_g = remap[comps.comp[edge_index[0]]]
    ecount = scatter_count(edge_g, G)
    m = int(ecount.max())
    order = torch.argsort(edge_g, stable=True)
    start = torch.cumsum(ecount, 0) - ecount
    epos = torch.empty_like(edge_g)
    epos[order] = torch.arange(E, device=dev) - start[edge_g[order]]
    edge = torch.full((G, m), -1, dtype=torch.long, device=dev)
    edge[edge_g, epos] = torch.arange(E, device=dev)
    edge_mask = edge >= 0
    safe = edge.clamp_min(0)
    src = torch.where(edge_mask, comps.local[edge_index[0, safe]], 0)
    dst = torch.where(edge_mask, comps.local[edge_index[1, safe]], 0)
    eye = torch.eye(3, dtype=R.dtype, device=dev)
    Rp = torch.where(edge_mask[..., None, None], R[safe], eye)
    tp = torch.where(edge_mask[..., None], t[safe], torch.zeros((), dtype=t.dtype, device=dev))
    return PaddedProblem(node=node, node_mask=node >= 0, edge=edge, edge_mask=edge_mask,
                         src=src, dst=dst, R=Rp, t=tp, comp_id=solvable,
                         count=comps.size[solvable])


def edge_rotations(edge_pose: Tensor) -> Tensor:
    """Rotation matrices ``[E, 3, 3]`` of edge pose vectors ``[E, 7]``."""
    return quaternion_to_rotation_matrix(edge_pose[:, :4])


def assemble(struct: dict[str, Any], comps: Components, prob: PaddedProblem | None, R: Tensor,
             t: Tensor, w_edge: Tensor, iters: Tensor, conv: Tensor, dtype: torch.dtype,
             device: torch.device) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Scatter padded per-component results back to nodes/edges/graphs.

    Returns ``poses [N, 4, 4]``, ``solved [N]``, ``edge_weight [E]``, ``iterations [B]``,
    ``converged [B]``.
    """
    N, B = struct["num_nodes"], struct["num_graphs"]
    E = struct["edge_index"].shape[1]
    poses = torch.eye(4, dtype=dtype, device=device).expand(N, 4, 4).clone()
    solved = torch.zeros(N, dtype=torch.bool, device=device)
    edge_weight = torch.ones(E, dtype=dtype, device=device)
    it_g = torch.zeros(B, dtype=torch.long, device=device)
    conv_g = torch.ones(B, dtype=torch.bool, device=device)
    if prob is not None and prob.G:
        sel = prob.node_mask
        nodes = prob.node[sel]
        poses[nodes] = make_se3(R[sel], t[sel])
        solved[nodes] = True
        edge_weight[prob.edge[prob.edge_mask]] = w_edge[prob.edge_mask]
        graph = comps.graph[prob.comp_id]
        it_g.scatter_reduce_(0, graph, iters.to(it_g.dtype), reduce="amax")
        conv_g = scatter_all(conv, graph, B)  # not scatter_reduce: no bool kernel on CUDA
    return poses, solved, edge_weight, it_g, conv_g

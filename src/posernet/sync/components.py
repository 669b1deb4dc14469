"""Connected components of a batch of view graphs (every backend solves each one on its own,
in its own gauge), found without a Python loop over graphs or edges."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..scatter import scatter_count

__all__ = ["Components", "connected_components"]


@dataclass
class Components:
    """Connected components of a batch. ``comp [N]`` component id of every node (ids are
    global, ``0..C-1``, ordered by smallest node id), ``size [C]``, ``graph [C]``,
    ``local [N]`` position of the node inside its component, ``graph_num_components [B]``."""

    comp: Tensor
    size: Tensor
    graph: Tensor
    local: Tensor
    graph_num_components: Tensor

    @property
    def num(self) -> int:
        return int(self.size.numel())


def connected_components(edge_index: Tensor, num_nodes: int, node_batch: Tensor,
                         num_graphs: int) -> Components:
    """Batched connected components by min-label propagation with pointer jumping.

    Each round sets every node's label to the smallest label among itself and its neighbours,
    then shortcuts ``label <- label[label]``; it stops when nothing changes (O(log diameter)
    rounds in practice). No Python loop over graphs or edges.
    """
    dev = edge_index.device
    label = torch.arange(num_nodes, device=dev)
    src, dst = edge_index[0], edge_index[1]
    while True:
        new = label.clone()
        new.scatter_reduce_(0, dst, label[src], reduce="amin")
        new.scatter_reduce_(0, src, label[dst], reduce="amin")
        new = new[new]
        if torch.equal(new, label):
            break
        label = new
    roots, comp = torch.unique(label, return_inverse=True)
    size = scatter_count(comp, roots.numel())
    graph = node_batch[roots]
    order = torch.argsort(comp, stable=True)
    start = torch.cumsum(size, 0) - size
    local = torch.empty_like(comp)
    local[order] = torch.arange(num_nodes, device=dev) - start[comp[order]]
    gnc = scatter_count(graph, num_graphs)
    return Components(comp=comp, size=size, graph=graph, local=local, graph_num_components=gnc)

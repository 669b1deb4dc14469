"""Inputs shared by the device tests: ``tests/test_cuda.py`` (CUDA against the CPU) and
``tests/test_cuda_ops_on_cpu.py`` (CUDA's failures caught on the CPU)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import torch
from helpers import make_graph

from posernet.graph import ViewGraph
from posernet.testing import random_view_graph

#: the adaptive network (``conf/model/adaptive.yaml``): gate and confidence head
ADAPTIVE: dict[str, Any] = {"residual": True, "unit_output": True, "edge_hidden": 8,
                            "gate": True, "confidence": True, "cycle_feature": True}


def _subgraph(g: ViewGraph, keep: torch.Tensor) -> ViewGraph:
    z = torch.zeros(0, dtype=torch.long)
    return dataclasses.replace(g, edge_index=g.edge_index[:, keep], edge_pose=g.edge_pose[keep],
                               edge_pose_gt=g.edge_pose_gt[keep], pair_edge=z, pair_src=z,
                               pair_dst=z)


def sync_graphs() -> list[ViewGraph]:
    """Motion-averaging inputs (float64): a noisy graph with outlier edges; one of two
    components plus an isolated camera (node 8); one over ``dense_max_nodes`` (Krylov)."""
    g = make_graph(9, 20, seed=12, rot_noise_deg=2.0, trans_noise=0.05)
    src, dst = g.edge_index
    side = lambda v: (v < 4).long() + 2 * ((v >= 4) & (v < 8)).long()  # noqa: E731
    split = _subgraph(g, (side(src) == side(dst)) & (src != 8) & (dst != 8))
    return [make_graph(8, 10, seed=3, rot_noise_deg=3.0, trans_noise=0.05, outlier_frac=0.2),
            split, make_graph(70, 140, seed=4, rot_noise_deg=1.0, trans_noise=0.02)]


def net_graphs(n: int = 3, dtype: torch.dtype = torch.float32) -> list[ViewGraph]:
    """Graphs with detections and matched pairs for the network, with ``kp``/``bb``
    estimates (as the commands read them)."""
    gen = torch.Generator().manual_seed(0)
    out = []
    for k in range(n):
        g = random_view_graph(num_nodes=6 + k % 3, extra_edges=5, generator=gen, name=f"c{k}",
                              dtype=dtype)
        g.estimates = {"kp": g.edge_pose, "bb": g.edge_pose}
        g.meta["scene"] = "heads"
        out.append(g)
    return out


def save_learned_sync(path: Path) -> Path:
    """A small untrained learned-synchronisation checkpoint at ``path`` (what the loader
    reads; Lightning's own file has more)."""
    from posernet.lit.learned_sync_module import LearnedSyncModule

    torch.manual_seed(0)
    m = LearnedSyncModule(net={"hidden": 8, "rounds": 2})
    torch.save({"state_dict": m.state_dict(), "hyper_parameters": dict(m.hparams),
                "posernet": {"tag": m.CHECKPOINT_TAG, "version": "test"}}, path)
    return path


def backend_variants(name: str, learned_ckpt: Path) -> list[dict[str, Any]]:
    """Option sets of sync backend ``name`` that take different code paths."""
    return {
        "eig_se3": [{}, {"scale": "given"}, {"solver": "dense"}, {"solver": "krylov"}],
        "rotation_translation": [{}, {"translation": "lud"}, {"translation": "linear"},
                                 {"weight_mode": "prior"}],
        "learned": [{"ckpt_path": str(learned_ckpt)}],  # callers add device=
    }.get(name, [{}])


def translation_weights(num_edges: int) -> torch.Tensor:
    """``[E, 2]`` per-edge (rotation, translation) weights, every third translation
    down-weighted."""
    w = torch.ones(num_edges, 2, dtype=torch.float64)
    w[::3, 1] = 0.1
    return w

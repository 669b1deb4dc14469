"""Helpers shared by test modules (``pythonpath = ["tests"]``: ``from helpers import ...``)."""

from __future__ import annotations

import numpy as np
import torch

from posernet.geometry import (
    axis_angle_to_rotation_matrix,
    compose_pose_vec,
    make_se3,
    matrix_to_pose_vec,
    relative_pose,
)
from posernet.graph import GraphBatch, ViewGraph
from posernet.metrics import absolute_pose_errors
from posernet.testing import random_absolute_poses, random_edges

F64 = torch.float64


def posernet_train_callbacks(out_dir: object) -> list:
    """The checkpoint callbacks ``posernet-train`` builds from ``conf/callbacks/default.yaml``
    for a run folder ``out_dir`` (best and last, in ``out_dir/checkpoints``)."""
    from hydra import compose, initialize_config_dir
    from lightning.pytorch.callbacks import ModelCheckpoint

    from posernet.cli import CONFIG_DIR
    from posernet.cli.train import _instantiate_dict

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"out_dir={out_dir}"])
    return [c for c in _instantiate_dict(cfg.callbacks) if isinstance(c, ModelCheckpoint)]


def make_graph(n: int, extra: int, seed: int, rot_noise_deg: float = 0.0,
               trans_noise: float = 0.0, outlier_frac: float = 0.0,
               dtype: torch.dtype = F64, edge_index: torch.Tensor | None = None) -> ViewGraph:
    """Graph with metric ground truth; ``edge_pose`` = GT plus Gaussian rotation noise (deg),
    translation noise (m) and a fraction of random outlier edges. Edges: a random spanning
    tree plus ``extra`` random ones, or ``edge_index [2, E]``."""
    g = torch.Generator().manual_seed(seed)
    P = random_absolute_poses(n, g, F64)
    ei = random_edges(n, extra, g) if edge_index is None else edge_index
    gt = matrix_to_pose_vec(relative_pose(P[ei[0]], P[ei[1]]))
    E = ei.shape[1]
    ax = torch.nn.functional.normalize(torch.randn(E, 3, generator=g, dtype=F64), dim=-1)
    ang = torch.deg2rad(torch.randn(E, 1, generator=g, dtype=F64) * rot_noise_deg)
    noise = matrix_to_pose_vec(make_se3(axis_angle_to_rotation_matrix(ax * ang),
                                        torch.zeros(E, 3, dtype=F64)))
    ep = compose_pose_vec(noise, gt)
    ep[:, 4:] += trans_noise * torch.randn(E, 3, generator=g, dtype=F64)
    if outlier_frac > 0:
        bad = torch.rand(E, generator=g) < outlier_frac
        rnd = matrix_to_pose_vec(make_se3(
            axis_angle_to_rotation_matrix(torch.randn(E, 3, generator=g, dtype=F64) * 2),
            torch.randn(E, 3, generator=g, dtype=F64)))
        ep = torch.where(bad[:, None], rnd, ep)
    z = torch.zeros(0, dtype=torch.long)
    graph = ViewGraph(
        node_attr=torch.zeros(n, 4, dtype=F64), K=torch.eye(3, dtype=F64).expand(n, 3, 3),
        image_size=torch.ones(n, 2, dtype=F64), edge_index=ei, edge_pose=ep,
        det_box=torch.zeros(0, 4, dtype=F64), det_node=z, pair_edge=z, pair_src=z, pair_dst=z,
        edge_pose_gt=gt, pose_gt=P, meta={"name": f"g{seed}"},
    )
    return graph.apply(lambda x: x.to(dtype) if x.is_floating_point() else x)


def rel_to_first(M: torch.Tensor) -> np.ndarray:
    """Gauge-free view of absolute poses: ``M_i M_0^{-1}`` for all i."""
    M = torch.as_tensor(M, dtype=F64)
    return (M @ torch.linalg.inv(M[0])).numpy()


def errors(poses, graph_or_batch, alignment="rigid"):
    b = graph_or_batch
    nb = getattr(b, "node_batch", None)
    if nb is None:
        nb = torch.zeros(b.num_nodes, dtype=torch.long)
    B = getattr(b, "num_graphs", 1) if isinstance(b, GraphBatch) else 1
    return absolute_pose_errors(poses, b.pose_gt, nb, B, alignment=alignment)


def as_from_a_terminal() -> None:
    """``preexec_fn`` of a child that a test interrupts with SIGINT: the signal handled and
    unblocked, as in a command started from a terminal. A child inherits an ignored or
    blocked SIGINT from the test runner's process (a parallel worker may have either), and
    would then sleep through the interrupt the test sends."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})

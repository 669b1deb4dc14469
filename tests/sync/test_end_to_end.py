"""Differentiable synchronisation and end-to-end training through it."""

from __future__ import annotations

import pytest
import torch

from posernet.graph import GraphBatch
from posernet.lit import PoserNetModule
from posernet.sync import EigSE3
from posernet.sync.differentiable import aligned_pose_loss, differentiable_sync, stable_eigh
from posernet.testing import random_view_graph


def _batch(n_graphs: int = 3, seed: int = 0, **kwargs) -> GraphBatch:
    gen = torch.Generator().manual_seed(seed)
    return GraphBatch.from_graphs([random_view_graph(generator=gen, dtype=torch.float64,
                                                     **kwargs) for _ in range(n_graphs)])


def _sync(b: GraphBatch, edge_pose: torch.Tensor, **kw):
    return differentiable_sync(b.edge_index, edge_pose, b.num_nodes, b.node_batch,
                               b.num_graphs, **kw)


def test_stable_eigh_matches_eigh_and_its_subspace_gradient() -> None:
    torch.manual_seed(0)
    X = torch.randn(2, 6, 6, dtype=torch.float64)
    A = X + X.mT
    L, V = stable_eigh(A, k=3)
    L0, _ = torch.linalg.eigh(A)
    torch.testing.assert_close(L, L0)
    torch.testing.assert_close(V @ torch.diag_embed(L) @ V.mT, A)
    W = torch.randn(6, 6, dtype=torch.float64)

    def projector_score(a: torch.Tensor) -> torch.Tensor:  # invariant to the top-3 basis
        _, v = stable_eigh(0.5 * (a + a.mT), k=3)
        top = v[..., -3:]
        return ((top @ top.mT) * W).sum() + stable_eigh(0.5 * (a + a.mT))[0].sum()

    assert torch.autograd.gradcheck(projector_score, (A.clone().requires_grad_(),))


def test_ground_truth_input_gives_exact_rotations_and_eig_se3_agrees_on_noisy_input() -> None:
    b = _batch()
    poses, solved = _sync(b, b.edge_pose_gt)
    assert solved.all()
    rot, _ = aligned_pose_loss(poses, b.pose_gt, b.node_batch, b.num_graphs)
    assert rot.max() < 1e-20
    # with the ground-truth baselines the positions are exact too
    poses, _ = _sync(b, b.edge_pose_gt, translation_norm=b.edge_pose_gt[:, 4:].norm(dim=-1))
    rot, pos = aligned_pose_loss(poses, b.pose_gt, b.node_batch, b.num_graphs)
    assert rot.max() < 1e-20 and pos.max() < 1e-10  # the gauge ridge: ~1e-6 m
    # noisy input: the same solution as the (non-robust, unit-norm) EIG-SE3 backend
    noisy = b.edge_pose.double()
    ours, _ = _sync(b, noisy)
    eig = EigSE3(robust=False, scale="unit").solve(b, noisy).double()
    r1, p1 = aligned_pose_loss(ours, b.pose_gt, b.node_batch, b.num_graphs)
    r2, p2 = aligned_pose_loss(eig, b.pose_gt, b.node_batch, b.num_graphs)
    assert r1.min() > 1e-6  # the noise shows
    torch.testing.assert_close(r1, r2, rtol=0.05, atol=1e-5)
    torch.testing.assert_close(p1, p2, rtol=0.1, atol=1e-3)


@pytest.mark.parametrize("noise", [1e-1, 1e-7])
def test_aligned_loss_gradient_is_exact_even_when_eigenvalues_cluster(noise: float) -> None:
    """float64 gradcheck through eigh, SO(3) projection, least squares and the alignment; with
    near-perfect input the top-3 eigenvalues coincide (the gauge), and the gradient stays
    finite and exact."""
    b = _batch(n_graphs=1, seed=3, num_nodes=5, extra_edges=3)
    gen = torch.Generator().manual_seed(1)
    x = (b.edge_pose_gt + noise * torch.randn(b.edge_pose_gt.shape, generator=gen,
                                              dtype=torch.float64)).requires_grad_(True)
    norm = b.edge_pose_gt[:, 4:].norm(dim=-1)

    def loss(ep: torch.Tensor) -> torch.Tensor:
        poses, solved = _sync(b, ep, translation_norm=norm)
        rot, pos = aligned_pose_loss(poses, b.pose_gt, b.node_batch, 1, solved)
        return rot.sum() + 0.5 * pos.sum()

    assert torch.autograd.gradcheck(loss, (x,), eps=1e-6, atol=1e-7, rtol=1e-3)
    loss(x).backward()
    assert torch.isfinite(x.grad).all()


def test_isolated_nodes_are_unsolved_and_left_out() -> None:
    g = random_view_graph(generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    keep = (g.edge_index != 7).all(0)  # node 7 loses its edges
    g.edge_index, g.edge_pose, g.edge_pose_gt = (g.edge_index[:, keep], g.edge_pose[keep],
                                                 g.edge_pose_gt[keep])
    poses, solved = differentiable_sync(g.edge_index, g.edge_pose_gt, g.num_nodes,
                                        torch.zeros(g.num_nodes, dtype=torch.long), 1)
    assert solved.tolist() == [True] * 7 + [False]
    assert torch.equal(poses[7], torch.eye(4, dtype=poses.dtype))
    rot, _ = aligned_pose_loss(poses, g.pose_gt, torch.zeros(8, dtype=torch.long), 1, solved)
    assert rot.item() < 1e-20


def test_end_to_end_loss_trains_every_parameter_and_is_off_by_default() -> None:
    gen = torch.Generator().manual_seed(0)
    batch = GraphBatch.from_graphs([random_view_graph(generator=gen) for _ in range(4)])
    torch.manual_seed(0)
    plain = PoserNetModule()
    torch.manual_seed(0)
    e2e = PoserNetModule(loss={"end_to_end": True, "absolute_weight": 2.0})
    assert e2e.hparams.loss["end_to_end"] and not plain.hparams.loss["end_to_end"]
    logged: dict[str, float] = {}
    for m in (plain, e2e):
        m.log = lambda name, value, **kw: logged.__setitem__(
            name, float(value.detach()))
    base = plain._step(batch, "train")
    assert "train/loss_abs_rot" not in logged
    total = e2e._step(batch, "train")
    rot, pos = logged["train/loss_abs_rot"], logged["train/loss_abs_pos"]
    assert rot > 0 and pos > 0
    torch.testing.assert_close(total, base + 2.0 * (torch.tensor(rot) + pos), rtol=1e-5,
                               atol=1e-5)
    total.backward()
    for name, p in e2e.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_end_to_end_needs_ground_truth_poses() -> None:
    g = random_view_graph(generator=torch.Generator().manual_seed(0))
    g.pose_gt = None
    module = PoserNetModule(loss={"end_to_end": True})
    module.log = lambda *a, **k: None
    with pytest.raises(ValueError, match="end_to_end needs batches with pose_gt"):
        module._step(GraphBatch.from_graphs([g]), "train")

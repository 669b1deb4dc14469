"""Differentiable synchronisation, for training PoserNet end to end through motion averaging.

:func:`differentiable_sync` maps relative poses ``edge_pose [E, 7]`` (with gradients) to
absolute world-to-camera poses ``[N, 4, 4]`` (with gradients), in the spirit of the spectral
EIG-SE3 solver with the ``unit`` translation policy:

1. **Rotations** by spectral synchronisation: the symmetric ``3n x 3n`` block matrix with
   ``w_e R_ij`` at block ``(j, i)`` and its transpose at ``(i, j)``, normalised by the weighted
   degrees, has the stacked true rotations (times ``D^{1/2}``) as its top-3 eigenspace. Its
   eigenvectors come from :func:`stable_eigh`, whose backward drops the terms that rotate
   inside that (clustered) top-3 space -- they are the global gauge, so every loss that is
   invariant to the gauge gets its exact gradient -- and clamps the others where eigenvalues
   nearly coincide. Each 3x3 block is projected onto SO(3) (Newton polar iteration, so autograd
   differentiates it stably).
2. **Translations** by weighted least squares on ``t_j - R_j R_i^T t_i = t_ij`` with unit-norm
   ``t_ij``, a tiny ridge fixing the translation gauge (batched dense solve).

:func:`aligned_pose_loss` measures absolute poses against ground truth after the gauge
alignment the tables use (rotations: the best global rotation; camera centres: Umeyama
similarity). The alignment is computed without gradient: it is the exact minimiser of the same
squared errors, so by the envelope theorem the gradient is the true gradient of the aligned
loss.

Every graph (every connected component) is solved in one batched padded problem
(:mod:`posernet.sync.padding`); isolated nodes keep the identity and are left out of the loss.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ..geometry import make_se3, project_to_so3, quaternion_normalize
from .components import connected_components
from .padding import PaddedProblem, build_padded, edge_rotations

__all__ = ["aligned_pose_loss", "differentiable_sync", "stable_eigh"]


class _StableEigh(torch.autograd.Function):
    """``torch.linalg.eigh`` with a backward that ignores the top-``k`` cluster's internal
    rotations and clamps small eigenvalue gaps (see :func:`stable_eigh`)."""

    @staticmethod
    def forward(ctx: Any, A: Tensor, k: int, eps: float) -> tuple[Tensor, Tensor]:
        L, V = torch.linalg.eigh(A)
        ctx.save_for_backward(L, V)
        ctx.k, ctx.eps = k, eps
        return L, V

    @staticmethod
    def backward(ctx: Any, gL: Tensor | None, gV: Tensor | None) -> tuple[Tensor, None, None]:
        L, V = ctx.saved_tensors
        n = L.shape[-1]
        inner = torch.zeros_like(V) if gV is None else V.mT @ gV
        gap = L[..., None, :] - L[..., :, None]  # [..., i, j] = lambda_j - lambda_i
        F = torch.where(gap.abs() > ctx.eps, 1.0 / torch.where(gap == 0, 1.0, gap), 0.0)
        top = torch.arange(n, device=L.device) >= n - ctx.k  # eigh sorts ascending
        F = F.masked_fill(top[:, None] & top[None, :], 0.0)
        core = F * inner
        if gL is not None:
            core = core + torch.diag_embed(gL)
        gA = V @ core @ V.mT
        return 0.5 * (gA + gA.mT), None, None


def stable_eigh(A: Tensor, k: int = 3, eps: float = 1e-9) -> tuple[Tensor, Tensor]:
    """Eigenvalues (ascending) and eigenvectors of symmetric ``A [..., n, n]``.

    The backward treats the top ``k`` eigenvectors as one subspace (rotations inside it carry
    no gradient: the caller's result must not depend on the basis chosen inside it) and drops
    the terms of eigenvalue pairs closer than ``eps`` instead of dividing by their gap.
    """
    return _StableEigh.apply(A, k, eps)


def _blocks(G: int, n: int, like: Tensor) -> Tensor:
    return like.new_zeros(G, n, n, 3, 3)


def _sync_rotations(prob: PaddedProblem, R: Tensor, w: Tensor) -> Tensor:
    """Spectral rotations ``[G, n, 3, 3]`` (world-to-camera, one gauge per component)."""
    G, n = prob.G, prob.n
    g = torch.arange(G, device=R.device)[:, None].expand_as(prob.src)
    wR = w[..., None, None] * R
    M = _blocks(G, n, R)
    M = M.index_put((g, prob.dst, prob.src), wR, accumulate=True)
    M = M.index_put((g, prob.src, prob.dst), wR.mT, accumulate=True)
    deg = R.new_zeros(G, n)
    deg = deg.index_put((g, prob.src), w, accumulate=True)
    deg = deg.index_put((g, prob.dst), w, accumulate=True)
    inv_sqrt = torch.where(deg > 0, deg.clamp_min(1e-300).rsqrt(), torch.zeros_like(deg))
    S = inv_sqrt[:, :, None, None, None] * M * inv_sqrt[:, None, :, None, None]
    S = S.permute(0, 1, 3, 2, 4).reshape(G, 3 * n, 3 * n)
    _, V = stable_eigh(0.5 * (S + S.mT), k=3)
    X = V[..., -3:].reshape(G, n, 3, 3) * inv_sqrt[..., None, None]
    # the eigenvectors fix the gauge only up to a reflection: choose the proper one
    det = torch.linalg.det(X.detach()) * prob.node_mask
    flip = torch.where(det.sum(1) < 0, -1.0, 1.0).to(X.dtype)
    X = torch.cat((X[..., :2], X[..., 2:] * flip[:, None, None, None]), dim=-1)
    eye = torch.eye(3, dtype=X.dtype, device=X.device)
    X = torch.where(prob.node_mask[..., None, None], X, eye)
    return project_to_so3(X)


def _sync_translations(prob: PaddedProblem, R_abs: Tensor, t_rel: Tensor, w: Tensor,
                       ridge: float) -> Tensor:
    """Least-squares translations ``[G, n, 3]`` given the absolute rotations."""
    G, n = prob.G, prob.n
    g = torch.arange(G, device=R_abs.device)[:, None].expand_as(prob.src)
    Ri, Rj = R_abs[g, prob.src], R_abs[g, prob.dst]
    Rij = Rj @ Ri.mT  # consistent relative rotations of the synchronised solution
    eye = torch.eye(3, dtype=R_abs.dtype, device=R_abs.device)
    wI = w[..., None, None] * eye
    H = _blocks(G, n, R_abs)
    H = H.index_put((g, prob.src, prob.src), wI, accumulate=True)
    H = H.index_put((g, prob.dst, prob.dst), wI, accumulate=True)
    H = H.index_put((g, prob.src, prob.dst), -w[..., None, None] * Rij.mT, accumulate=True)
    H = H.index_put((g, prob.dst, prob.src), -w[..., None, None] * Rij, accumulate=True)
    b = R_abs.new_zeros(G, n, 3)
    b = b.index_put((g, prob.src), -w[..., None] * (Rij.mT @ t_rel[..., None]).squeeze(-1),
                    accumulate=True)
    b = b.index_put((g, prob.dst), w[..., None] * t_rel, accumulate=True)
    H = H.permute(0, 1, 3, 2, 4).reshape(G, 3 * n, 3 * n)
    pad = (~prob.node_mask).to(H.dtype).repeat_interleave(3, dim=1)  # pads: t = 0
    H = H + torch.diag_embed(pad + ridge)
    return torch.linalg.solve(H, b.reshape(G, 3 * n)).reshape(G, n, 3)


def differentiable_sync(edge_index: Tensor, edge_pose: Tensor, num_nodes: int,
                        node_batch: Tensor, num_graphs: int, weight: Tensor | None = None,
                        translation_norm: Tensor | None = None,
                        ridge: float = 1e-6) -> tuple[Tensor, Tensor]:
    """Absolute world-to-camera poses from relative ones, differentiably.

    Args:
        edge_index: ``[2, E]`` stored edges ``i -> j``; ``edge_pose [E, 7]`` their poses
            ``M_j M_i^{-1}`` as ``[q, t]`` (any quaternion norm; ``t`` is rescaled to unit norm,
            the ``unit`` translation policy).
        num_nodes, node_batch ``[N]``, num_graphs: the batch's nodes and graphs.
        weight: optional per-edge weights ``[E]`` (>= 0; default 1).
        translation_norm: optional ``[E]`` lengths given to the unit directions (e.g. the
            ground-truth baselines while training: the ``given`` policy); default 1.
        ridge: Tikhonov weight fixing the translation gauge.

    Returns:
        ``poses [N, 4, 4]`` (identity for nodes without an edge) and ``solved [N]``.
    """
    E = edge_index.shape[1]
    dtype = edge_pose.dtype
    q = quaternion_normalize(edge_pose[:, :4])
    t = edge_pose[:, 4:]
    t = t / t.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    if translation_norm is not None:
        t = t * translation_norm.to(dtype)[:, None]
    w = edge_pose.new_ones(E) if weight is None else weight.to(dtype)
    comps = connected_components(edge_index, num_nodes, node_batch, num_graphs)
    prob = build_padded(edge_index, edge_rotations(torch.cat((q, t), 1)), t, comps)
    poses = torch.eye(4, dtype=dtype, device=edge_pose.device).expand(num_nodes, 4, 4).clone()
    solved = torch.zeros(num_nodes, dtype=torch.bool, device=edge_pose.device)
    if prob.G == 0:
        return poses, solved
    wp = torch.where(prob.edge_mask, w[prob.edge.clamp_min(0)], w.new_zeros(()))
    R_abs = _sync_rotations(prob, prob.R, wp)
    t_abs = _sync_translations(prob, R_abs, prob.t, wp, ridge)
    sel = prob.node_mask
    poses = poses.index_put((prob.node[sel],), make_se3(R_abs[sel], t_abs[sel]))
    solved[prob.node[sel]] = True
    return poses, solved


def aligned_pose_loss(poses: Tensor, pose_gt: Tensor, node_batch: Tensor, num_graphs: int,
                      mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Mean squared absolute-pose errors after gauge alignment, per graph.

    ``poses, pose_gt [N, 4, 4]`` world-to-camera; ``mask [N]`` the nodes to use (default all).
    Rotations: ``|R_i - R_gt_i A|_F^2 / 8`` (= ``sin^2(angle / 2)``) with ``A`` the best global
    rotation; positions: ``|s Q c_i + b - c_gt_i|^2`` of camera centres after the Umeyama
    similarity. Returns ``rot [B]``, ``pos [B]`` (graphs with fewer than 2 used nodes: 0).
    """
    from ..geometry import umeyama_alignment

    N = poses.shape[0]
    dev, dtype = poses.device, poses.dtype
    use = torch.ones(N, dtype=torch.bool, device=dev) if mask is None else mask
    count = torch.zeros(num_graphs, dtype=torch.long, device=dev).index_add_(
        0, node_batch, torch.ones_like(node_batch))
    start = torch.cumsum(count, 0) - count
    local = torch.arange(N, device=dev) - start[node_batch]
    n = int(count.max()) if N else 0
    R = poses[:, :3, :3]
    Rg = pose_gt[:, :3, :3].to(dtype)
    c = -(R.mT @ poses[:, :3, 3:]).squeeze(-1)
    cg = -(Rg.mT @ pose_gt[:, :3, 3:].to(dtype)).squeeze(-1)

    def pad(x: Tensor, fill: float = 0.0) -> Tensor:
        out = x.new_full((num_graphs, n, *x.shape[1:]), fill)
        return out.index_put((node_batch, local), x)

    m = pad(use.to(dtype)) > 0
    with torch.no_grad():  # the alignment minimises the same errors: envelope theorem
        A = project_to_so3((pad(Rg).mT @ pad(R.detach()) * m[..., None, None]).sum(1)
                           + 1e-12 * torch.eye(3, dtype=dtype, device=dev))
        s, Q, b = umeyama_alignment(pad(c.detach()), pad(cg), mask=m)
    rot = ((R - Rg @ A[node_batch]) ** 2).sum((-1, -2)) / 8
    aligned = s[node_batch, None] * (Q[node_batch] @ c[..., None]).squeeze(-1) + b[node_batch]
    pos = ((aligned - cg) ** 2).sum(-1)
    used = use.to(dtype)
    per = torch.zeros(num_graphs, dtype=dtype, device=dev)
    cnt = per.index_add(0, node_batch, used)
    ok = cnt >= 2
    denom = cnt.clamp_min(1.0)
    rot_g = torch.where(ok, per.index_add(0, node_batch, rot * used) / denom, 0.0)
    pos_g = torch.where(ok, per.index_add(0, node_batch, pos * used) / denom, 0.0)
    return rot_g, pos_g

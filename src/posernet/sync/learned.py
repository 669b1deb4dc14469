"""Learned synchronisation: a MultiReg-style message-passing network (after the idea of Yew &
Lee, 3DV 2021; written for this project) that turns relative poses into absolute poses, and the
``learned`` motion-averaging backend that runs a trained one.

**Network** (:class:`LearnedSyncNet`). Every node carries a feature ``h_i [H]`` and an absolute
world-to-camera pose ``T_i [4, 4]``, initialised from the spectral EIG-SE3 solution
(``init="spectral"``, non-robust, unit translations) or at the identity (``init="identity"``).
``rounds`` weight-shared rounds follow. For every stored edge ``e = (i -> j)`` with measured
pose ``P_e`` two messages are sent, one into each end ``d`` from the other end ``s``; each sees
the residual of its own direction expressed in camera ``d``'s frame,

    rho_{s->d} = log(T_d T_s^{-1} P_{s->d}^{-1})  in se(3),  P_{j->i} = P_e^{-1},

(zero when the current poses agree with the measurement; ``exp(-rho)`` is the left increment
that would make ``T_d`` agree with it). With ``c`` the current relative translation
(``T_d T_s^{-1}``) and ``u`` the measured unit direction, both in ``d``'s frame, a message MLP
over ``[h_s, h_d, rho, |omega|, |v|, u, c_perp, cos(c, u), |c|, confidence]`` (``c_perp`` the
part of ``c`` off ``u``: the scale-free direction error) gives a feature and a weight; node
``d`` averages the features (:func:`posernet.scatter.scatter_mean`) and, with the learned weights,
the suggested corrections ``corr = [-omega, -c_perp, -v]`` (a learned robust mean, like one
IRLS step), updates ``h_d <- LayerNorm(h_d + MLP([h_d, agg, corr]))`` and moves on the
manifold by a bounded increment ``delta = s tanh((head([h_d, corr]) + g * corr[:6]) / s)``:
``T_d <- exp(delta) T_d`` (``s = step_scale``, ``g`` a learned per-axis gain, starting as a
damped rotation-averaging step). Nodes without an edge keep their initial pose.

*Gauge.* Messages see only ``T_d T_s^{-1}`` and the measurements, and increments act from the
left, so right-multiplying every initial pose by one ``G in SE(3)`` right-multiplies every
output by ``G``; node order does not matter either (tests check both). Poses are kept in
float64 (compositions over rounds), the MLPs run in their parameters' dtype.

*Scale.* Like EIG-SE3 with ``scale="unit"``, the network rescales every measured relative
translation to unit norm (5-point / PoserNet directions carry no scale); its output positions
are therefore only meaningful up to a similarity (``SyncResult.metric`` is False).

**Loss** (:func:`learned_sync_loss`): relative poses of *all* node pairs of each graph against
the ground truth: geodesic rotation angle (rad) plus ``translation_weight`` times the chordal
distance of the unit translation directions (scale-free), mean per graph then over graphs;
round ``k`` of ``K`` weighted ``gamma^(K-1-k)`` (normalised), so later rounds count more.

**Backend** (:class:`LearnedSync`, ``sync=learned``): loads a ``LearnedSyncModule`` checkpoint
(``posernet-train model=learned_sync``) once, caches it, and solves batches like any backend.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from ..checkpoints import CHECKPOINT_TAG, CheckpointError, read_checkpoint
from ..geometry import invert_se3, pose_vec_to_matrix, rotation_angle, se3_exp, se3_log
from ..graph import GraphBatch, ViewGraph
from ..nn.mlp import MLP
from ..options import DEVICE, option, path
from ..scatter import scatter_count, scatter_mean, scatter_sum
from .backend import SyncBackend, SyncOptions, SyncResult
from .components import Components
from .eig_se3 import EigSE3

__all__ = [
    "INITS",
    "LEARNED_SYNC_TAG",
    "LearnedSync",
    "LearnedSyncLoss",
    "LearnedSyncNet",
    "LearnedSyncOptions",
    "all_pairs",
    "learned_sync_loss",
    "load_learned_sync",
]

#: written into checkpoints by :class:`posernet.lit.LearnedSyncModule`
LEARNED_SYNC_TAG = "posernet.LearnedSyncModule"
#: initial absolute poses of :class:`LearnedSyncNet`
INITS: tuple[str, ...] = ("spectral", "identity")
#: per-message features: rho (6), |omega|, |v|, measured direction u (3), c_perp (3),
#: cos(c, u), |c| (c: current relative translation)
_RESIDUAL_FEATURES = 16
#: aggregated suggestions per node: -omega (3), -c_perp (3), -v (3)
_CORRECTION = 9


def _spectral() -> EigSE3:
    """The spectral initialisation: EIG-SE3, one non-robust solve, unit translations."""
    return EigSE3(robust=False, scale="unit")


def _soft_norm(x: Tensor, eps: float = 1e-9) -> Tensor:
    """``|x|`` over the last axis, smooth at 0 (a residual is exactly 0 for perfect input)."""
    return ((x * x).sum(-1, keepdim=True) + eps * eps).sqrt() - eps


def _unit_translation(edge_pose: Tensor) -> Tensor:
    """``[q, t / |t|]`` (zero translations stay zero): the ``unit`` scale policy."""
    t = edge_pose[:, 4:]
    n = t.norm(dim=-1, keepdim=True)
    return torch.cat((edge_pose[:, :4], torch.where(n > 0, t / n.clamp_min(1e-300), 0 * t)), 1)


# --------------------------------------------------------------------------- network


class LearnedSyncNet(nn.Module):
    """MultiReg-style learned pose synchronisation (see the module docstring).

    Args:
        hidden: node feature and MLP width ``H`` (default 64).
        rounds: weight-shared message-passing rounds ``K`` (default 6).
        mlp_layers: linear layers per MLP (message, node update, increment head; default 2).
        init: ``"spectral"`` (EIG-SE3, default) or ``"identity"`` initial poses.
        step_scale: bound of each increment component, ``|delta| < step_scale`` (rad / unit
            translation; default 0.5).
        use_confidence: messages also see a per-edge confidence ``[E]`` (1 when not given).
        negative_slope: leaky ReLU slope of the MLPs.

    Shapes: ``forward(batch) -> [N, 4, 4]`` float64 world-to-camera poses (a list of ``K`` with
    ``return_all=True``).
    """

    def __init__(self, hidden: int = 64, rounds: int = 6, mlp_layers: int = 2,
                 init: str = "spectral", step_scale: float = 0.5, use_confidence: bool = False,
                 negative_slope: float = 0.01) -> None:
        super().__init__()
        for name, v in (("hidden", hidden), ("rounds", rounds), ("mlp_layers", mlp_layers)):
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"LearnedSyncNet: {name} must be an integer >= 1, got {v!r}")
        if init not in INITS:
            raise ValueError(f"LearnedSyncNet: init={init!r}; choose one of {list(INITS)}")
        if not isinstance(step_scale, int | float) or isinstance(step_scale, bool) or \
                not 0 < step_scale <= 3.0:
            raise ValueError(f"LearnedSyncNet: step_scale must be in (0, 3], got {step_scale!r}")
        self.hidden, self.rounds, self.mlp_layers = hidden, rounds, mlp_layers
        self.init, self.step_scale = init, float(step_scale)
        self.use_confidence, self.negative_slope = bool(use_confidence), negative_slope
        feats = _RESIDUAL_FEATURES + int(self.use_confidence)
        # Every node starts from the same learned state: features carry no gauge information.
        self.h0 = nn.Parameter(torch.zeros(hidden))
        self.message = MLP(2 * hidden + feats, hidden + 1, hidden, mlp_layers, negative_slope,
                           act_last=False)  # feature [H] + weight logit [1]
        self.update = MLP(2 * hidden + _CORRECTION, hidden, hidden, mlp_layers, negative_slope,
                          act_last=False)
        self.norm = nn.LayerNorm(hidden)
        self.head = MLP(hidden + _CORRECTION, 6, hidden, mlp_layers, negative_slope, act_last=False)
        # The gain term starts the network as a damped rotation-averaging step (half-way
        # towards the weighted mean of what the neighbours predict); translations start
        # without one (averaging perpendicular residuals alone shrinks the graph, averaging
        # unit-scale ones imposes unit baselines): the head learns them, starting small so the
        # first epochs do not undo the spectral solution.
        self.gain = nn.Parameter(torch.tensor([0.5] * 3 + [0.0] * 3))
        last = self.head.net[-1]
        with torch.no_grad():
            last.weight.mul_(0.01)
            last.bias.zero_()

    # ------------------------------------------------------------------ initial poses
    def initial_poses(self, batch: GraphBatch | ViewGraph, edge_pose: Tensor | None = None
                      ) -> Tensor:
        """Initial absolute poses ``[N, 4, 4]`` float64 (no gradient): the spectral EIG-SE3
        solution of ``edge_pose`` (``batch.edge_pose`` by default) or identities."""
        n = batch.num_nodes
        if edge_pose is None:
            edge_pose = batch.edge_pose
        if self.init == "identity":
            eye = torch.eye(4, dtype=torch.float64, device=edge_pose.device)
            return eye.expand(n, 4, 4).clone()
        with torch.no_grad():
            return _spectral().solve_with_info(batch, edge_pose.detach().double()).poses

    # ------------------------------------------------------------------ forward
    def forward(self, batch: GraphBatch | ViewGraph, edge_pose: Tensor | None = None,
                confidence: Tensor | None = None, init_pose: Tensor | None = None,
                return_all: bool = False) -> Tensor | list[Tensor]:
        """Absolute world-to-camera poses ``[N, 4, 4]`` (float64) from ``edge_pose [E, 7]``
        (``batch.edge_pose`` by default); ``init_pose [N, 4, 4]`` overrides
        :meth:`initial_poses`; ``confidence [E]`` is used with ``use_confidence``;
        ``return_all`` gives the poses after every round (a list of ``rounds``)."""
        if edge_pose is None:
            edge_pose = batch.edge_pose
        if init_pose is None:
            init_pose = self.initial_poses(batch, edge_pose)
        out, _ = self.propagate(batch.edge_index, edge_pose, init_pose, confidence)
        return out if return_all else out[-1]

    def propagate(self, edge_index: Tensor, edge_pose: Tensor, init_pose: Tensor,
                  confidence: Tensor | None = None) -> tuple[list[Tensor], Tensor]:
        """The rounds on plain tensors: ``edge_index [2, E]``, ``edge_pose [E, 7]``,
        ``init_pose [N, 4, 4]``, ``confidence [E]`` -> (poses after each round, a list of
        ``[N, 4, 4]`` float64; the last round's message weights averaged over both directions,
        ``[E]``)."""
        N, E = init_pose.shape[0], edge_index.shape[1]
        ei = edge_index.long()
        src = torch.cat((ei[0], ei[1]))  # message s -> d; the second half are the reverse ones
        dst = torch.cat((ei[1], ei[0]))
        P = pose_vec_to_matrix(_unit_translation(edge_pose.to(torch.float64)))
        P_inv = invert_se3(P)
        meas = torch.cat((P, P_inv))  # the measured pose of each message s -> d
        meas_inv = torch.cat((P_inv, P))
        pdtype = self.h0.dtype
        extra = []
        if self.use_confidence:
            c = torch.ones(E, dtype=pdtype, device=ei.device) if confidence is None \
                else confidence.to(pdtype).reshape(E)
            extra = [torch.cat((c, c))[:, None]]
        active = (scatter_count(dst, N) > 0)[:, None]  # isolated nodes keep their pose
        T = init_pose.to(torch.float64)
        h = self.h0.expand(N, -1)
        outs: list[Tensor] = []
        w = torch.ones(2 * E, dtype=pdtype, device=ei.device)
        u = meas[:, :3, 3].to(pdtype)  # measured unit direction of s -> d, in d's frame
        for _ in range(self.rounds):
            C = T[dst] @ invert_se3(T[src])  # current relative pose s -> d (gauge-invariant)
            rho = se3_log(C @ meas_inv).to(pdtype)  # [2E, 6] residual, in d's frame
            c = C[:, :3, 3].to(pdtype)
            cu = (c * u).sum(1, keepdim=True)
            c_perp = c - cu * u  # the part of c off the measured direction (scale-free error)
            c_norm = _soft_norm(c)
            feats = torch.cat((rho, _soft_norm(rho[:, :3]), _soft_norm(rho[:, 3:]), u, c_perp,
                               cu / (c_norm + 1e-6), c_norm), 1)
            out = self.message(torch.cat((h[src], h[dst], feats, *extra), 1))
            w = torch.sigmoid(out[:, -1])
            agg = scatter_mean(out[:, :-1], dst, 0, N)
            # weighted means of what the messages suggest: rotation -omega, scale-free
            # translation -c_perp, unit-scale translation -v
            target = torch.cat((-rho[:, :3], -c_perp, -rho[:, 3:]), 1)
            corr = scatter_sum(w[:, None] * target, dst, 0, N) / \
                scatter_sum(w, dst, 0, N).clamp_min(1e-6)[:, None]
            h = self.norm(h + self.update(torch.cat((h, agg, corr), 1)))
            raw = self.head(torch.cat((h, corr), 1)) + self.gain * corr[:, :6]
            delta = self.step_scale * torch.tanh(raw / self.step_scale)
            delta = torch.where(active, delta, torch.zeros_like(delta))
            T = se3_exp(delta.to(torch.float64)) @ T
            outs.append(T)
        return outs, 0.5 * (w[:E] + w[E:])

    def extra_repr(self) -> str:
        return (f"hidden={self.hidden}, rounds={self.rounds}, mlp_layers={self.mlp_layers}, "
                f"init={self.init!r}, step_scale={self.step_scale}, "
                f"use_confidence={self.use_confidence}")


# --------------------------------------------------------------------------- loss


class LearnedSyncLoss(NamedTuple):
    """``loss`` (weighted over rounds), the last round's ``rotation`` (mean geodesic angle,
    rad) and ``translation`` (mean chordal distance of unit directions) terms, and the loss of
    every round ``per_round [K]``."""

    loss: Tensor
    rotation: Tensor
    translation: Tensor
    per_round: Tensor


def all_pairs(ptr: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Every unordered node pair ``i < j`` of every graph of a batch, vectorised.

    ``ptr [B + 1]`` node offsets -> ``(i [M], j [M], graph [M])`` global node indices and the
    graph of each pair (``M = sum n_g (n_g - 1) / 2``).
    """
    ptr = ptr.long()
    n = ptr.diff()
    dev = ptr.device
    graph_of_node = torch.repeat_interleave(torch.arange(n.numel(), device=dev), n)
    reps = n[graph_of_node]  # node i is paired with every node of its graph
    i = torch.repeat_interleave(torch.arange(graph_of_node.numel(), device=dev), reps)
    start = torch.cumsum(reps, 0) - reps
    k = torch.arange(i.numel(), device=dev) - torch.repeat_interleave(start, reps)
    j = ptr[graph_of_node[i]] + k
    keep = i < j
    i, j = i[keep], j[keep]
    return i, j, graph_of_node[i]


def _pair_terms(T: Tensor, T_gt: Tensor, i: Tensor, j: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Rotation angle and unit-direction distance of the relative poses ``i -> j`` of
    ``T [..., N, 4, 4]`` against ``T_gt [N, 4, 4]``, and the pairs whose true translation has
    a direction."""
    def rel(T: Tensor) -> tuple[Tensor, Tensor]:
        R, t = T[..., :3, :3], T[..., :3, 3]
        R_ij = R[..., j, :, :] @ R[..., i, :, :].mT
        return R_ij, t[..., j, :] - (R_ij @ t[..., i, :, None]).squeeze(-1)

    R, t = rel(T)
    R_gt, t_gt = rel(T_gt)
    rot = rotation_angle(R_gt.mT @ R)
    n_gt = t_gt.norm(dim=-1, keepdim=True)
    valid = n_gt[..., 0] > 1e-9
    u = t / (_soft_norm(t) + 1e-12)
    u_gt = t_gt / n_gt.clamp_min(1e-9)
    return rot, _soft_norm(u - u_gt)[..., 0], valid


def learned_sync_loss(poses: Tensor | Sequence[Tensor], pose_gt: Tensor, ptr: Tensor,
                      gamma: float = 0.8, translation_weight: float = 1.0,
                      pairs: tuple[Tensor, Tensor, Tensor] | None = None) -> LearnedSyncLoss:
    """Loss on the relative poses of all node pairs of every graph (module docstring).

    ``poses`` one ``[N, 4, 4]`` or the ``K`` rounds' (list, or ``[K, N, 4, 4]``);
    ``pose_gt [N, 4, 4]`` world-to-camera ground truth; ``ptr [B + 1]`` node offsets;
    ``pairs`` precomputed :func:`all_pairs` (built here otherwise). Invariant to a similarity
    transform of either side; 0 at the ground truth.
    """
    T = poses if isinstance(poses, Tensor) else torch.stack(list(poses))
    if T.ndim == 3:
        T = T[None]
    T = T.to(torch.float64)
    K = T.shape[0]
    i, j, g = all_pairs(ptr) if pairs is None else pairs
    B = int(ptr.numel() - 1)
    rot, tr, valid = _pair_terms(T, pose_gt.to(T), i, j)  # [K, M], [K, M], [M]
    # mean over each graph's pairs, then over graphs: every graph counts the same
    rot_g = scatter_mean(rot.T, g, 0, B)  # [B, K]
    cnt = scatter_sum(valid.to(T.dtype), g, 0, B).clamp_min(1.0)[:, None]
    tr_g = scatter_sum(tr.T * valid[:, None], g, 0, B) / cnt
    rot_k, tr_k = rot_g.mean(0), tr_g.mean(0)  # [K]
    per_round = rot_k + translation_weight * tr_k
    w = gamma ** torch.arange(K - 1, -1, -1, dtype=T.dtype, device=T.device)
    loss = (w * per_round).sum() / w.sum()
    f = torch.float32
    return LearnedSyncLoss(loss.to(f), rot_k[-1].to(f), tr_k[-1].to(f), per_round.to(f))


# --------------------------------------------------------------------------- checkpoints

_CACHE: dict[tuple[str, int, int], tuple[LearnedSyncNet, dict[str, Any]]] = {}


def load_learned_sync(path: str | Path) -> tuple[LearnedSyncNet, dict[str, Any]]:
    """The network (CPU, eval mode, frozen) and hyper-parameters of a ``LearnedSyncModule``
    checkpoint, cached per file (path, modification time, size).

    Raises :class:`posernet.checkpoints.CheckpointError` naming the file for a missing,
    foreign (e.g. a PoserNet checkpoint) or mismatching checkpoint.
    """
    p = Path(path).expanduser()
    key = None
    if p.is_file():
        st = p.stat()
        key = (str(p.resolve()), st.st_mtime_ns, st.st_size)
        if key in _CACHE:
            return _CACHE[key]
    try:
        ckpt = read_checkpoint(p, LEARNED_SYNC_TAG)
    except CheckpointError as exc:
        if CHECKPOINT_TAG in str(exc):  # the usual mix-up: the refiner's checkpoint
            raise CheckpointError(
                f"{exc}: this is a PoserNet checkpoint; the learned synchronisation needs one "
                "written by `posernet-train model=learned_sync` (a PoserNet checkpoint goes to "
                "ckpt_path / model.input.refiner_ckpt)") from None
        raise
    hp = dict(ckpt.get("hyper_parameters") or {})
    net_hp = hp.get("net")
    if not isinstance(net_hp, dict):
        raise CheckpointError(f"{p}: learned-sync checkpoint without 'net' hyper-parameters")
    try:
        net = LearnedSyncNet(**net_hp)
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{p}: checkpoint does not fit LearnedSyncNet ({exc})") from exc
    state = {k[len("net."):]: v for k, v in ckpt["state_dict"].items() if k.startswith("net.")}
    try:
        net.load_state_dict(state)
    except RuntimeError as exc:
        first = (str(exc).strip().splitlines() or [""])[0]
        raise CheckpointError(f"{p}: weights do not fit LearnedSyncNet ({first})") from exc
    net.eval().requires_grad_(False)
    out = (net, hp)
    if key is not None:
        _CACHE[key] = out
    return out


# --------------------------------------------------------------------------- backend


@dataclass(frozen=True)
class LearnedSyncOptions(SyncOptions):
    """``ckpt_path``: a ``LearnedSyncModule`` checkpoint (required); ``device``: where the
    network runs (``cpu``, ``cuda``, ``cuda:N`` or ``auto``)."""

    ckpt_path: str | None = option(None, rule=path(), help="a checkpoint written by "
                                   "`posernet-train model=learned_sync`")
    device: str = option("cpu", rule=DEVICE, help="where the network runs")

    def check(self) -> None:
        if self.ckpt_path in (None, ""):
            raise ValueError("sync backend 'learned' needs ckpt_path=<a checkpoint written by "
                             "`posernet-train model=learned_sync`>")
        super().check()
        if self.device.startswith("cuda") and not torch.cuda.is_available():
            raise ValueError(f"device={self.device!r} but CUDA is not available here")


class LearnedSync(SyncBackend):
    """Learned synchronisation backend (``sync=learned``): a trained :class:`LearnedSyncNet`.

    Only ``scale="unit"``: the network was trained on unit-norm relative translations (it
    normalises them itself), so its positions hold up to a similarity (``metric`` False).
    The checkpoint is read when the backend is built (a bad file fails early) and cached.
    Each connected component is solved in its own gauge (messages never cross components);
    nodes without an edge keep the identity and are ``solved=False``. ``edge_weight`` holds the
    last round's learned message weights (mean of both directions), ``iterations`` the rounds.
    """

    name = "learned"
    Options = LearnedSyncOptions
    scales = ("unit",)

    def __init__(self, **options: Any) -> None:
        super().__init__(**options)
        o: LearnedSyncOptions = self.options  # type: ignore[assignment]
        self._net, self._hparams = load_learned_sync(str(o.ckpt_path))
        dev = o.device
        if dev == "auto":
            dev = "cuda" if torch.cuda.is_available() else "cpu"
        self.device = torch.device(dev)
        if self.device.type != "cpu":  # the cached copy stays on the CPU for other users
            self._net = copy.deepcopy(self._net).to(self.device)

    @property
    def network(self) -> LearnedSyncNet:
        return self._net

    def describe(self) -> dict[str, Any]:
        d = super().describe()
        refiner = (self._hparams.get("input") or {}).get("refiner_ckpt")
        d.update(rounds=self._net.rounds, init=self._net.init,
                 trained_on="refined input" if refiner else "raw input")
        return d

    def _solve(self, struct: dict[str, Any], edge_pose: Tensor, edge_pose_gt: Tensor | None,
               comps: Components) -> SyncResult:
        net, dev = self._net, self.device
        n, B = struct["num_nodes"], struct["num_graphs"]
        if net.init == "spectral":
            # The input is validated and split into components already: EIG-SE3's own solver
            # on the same structure (solve_with_info would need the batch and redo both).
            init = _spectral()._solve(struct, edge_pose, None, comps).poses
        else:
            init = torch.eye(4, dtype=torch.float64).expand(n, 4, 4).clone()
        with torch.inference_mode():
            outs, w = net.propagate(struct["edge_index"].to(dev), edge_pose.to(dev),
                                    init.to(dev))
        poses = outs[-1].to(device=edge_pose.device, dtype=torch.float64)
        solved = comps.size[comps.comp] > 1
        # belt and braces: an isolated node has no message, so it kept its initial identity
        eye = torch.eye(4, dtype=poses.dtype, device=poses.device)
        poses = torch.where(solved[:, None, None], poses, eye)
        dev0 = edge_pose.device
        return SyncResult(
            poses=poses, component=comps.comp, solved=solved,
            edge_weight=w.to(device=dev0, dtype=torch.float64),
            iterations=torch.full((B,), net.rounds, dtype=torch.long, device=dev0),
            converged=torch.ones(B, dtype=torch.bool, device=dev0),
            scale=self.options.scale, metric=False, backend=self.name,
            info={"ckpt_path": str(self.options.ckpt_path), "init": net.init,  # type: ignore
                  "rounds": net.rounds})

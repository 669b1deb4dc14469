"""``PoserNet``: ``depth`` rounds of :class:`PoserConv`, refined relative pose per edge.

.. math::

    (h^{0}, e^{0}) = (\\text{node\\_attr}, \\text{edge\\_pose}), \\qquad
    (h^{k+1}, e^{k+1}, g^{k+1}) = \\mathrm{PoserConv}_k(h^{k}, e^{k}, g^{k}),
    \\qquad \\hat e = e^{\\text{depth}}

Every round refines the pose of every stored edge ``i -> j``; the output is the 7-vector
``[qw, qx, qy, qz, tx, ty, tz]`` of the last round (sign-canonical quaternion; unit quaternion
and unit translation when ``unit_output=True``). See :mod:`posernet.nn.conv` for the round and
for why the output of a flipped edge is exactly the inverse pose.

Only the edge poses of the last round are read, so the last round has no node-update network
(and no hidden-edge-state output): every parameter reaches the loss, as distributed data
parallel training requires.
"""

from __future__ import annotations

import dataclasses
import inspect
import os
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from ..geometry import quaternion_canonical, quaternion_normalize
from ..options import check_options, option
from .adaptive import (
    CYCLE_DIM,
    AdaptiveOutput,
    EdgeHead,
    blend_poses,
    cycle_features,
    pair_stats,
)
from .conv import PoserConv, check_module_inputs, graph_inputs, is_graph_input, validate_inputs

__all__ = ["PoserNet", "PoserNetOptions"]


@dataclass(frozen=True)
class PoserNetOptions:
    """The architecture options of :class:`PoserNet` (``model.net.*``; see there)."""

    depth: int = option(2, ge=1, help="message-passing rounds")
    node_in: int = option(4, ge=1, help="size of the node input (width, height, focal, k1)")
    node_hidden: int = option(32, ge=1, help="node state size after each round")
    edge_hidden: int = option(0, ge=0, help="hidden edge state per direction (0: the pose only)")
    mlp_hidden: int = option(32, ge=1, help="units of each hidden layer of Psi_E / Psi_N")
    mlp_layers: int = option(3, ge=1, help="linear layers per MLP")
    negative_slope: float = option(0.01, help="leaky ReLU slope")
    shared_weights: bool = option(False, help="one PoserConv reused by every round")
    residual: bool = option(False, help="predict a correction composed with the input pose")
    unit_output: bool = option(False, help="normalise the output quaternion and translation")
    nested_mean: bool = option(True, help="the paper's nested mean for the node update")
    gate: bool = option(False, help="a learned per-edge gate between input and prediction")
    confidence: bool = option(False, help="a per-edge error-scale head")
    cycle_feature: bool = option(False, help="input rotation cycle consistency as the initial "
                                             "edge state (needs edge_hidden >= 3)")
    head_hidden: int = option(32, ge=1, help="width of the gate / confidence MLP")

    def __post_init__(self) -> None:
        check_options(self)
        if self.cycle_feature and self.edge_hidden < CYCLE_DIM:
            raise ValueError(f"PoserNet cycle_feature=True needs edge_hidden >= {CYCLE_DIM} "
                             f"(the cycle features are the initial edge state), got "
                             f"edge_hidden={self.edge_hidden}")


class PoserNet(nn.Module):
    """The PoserNet graph network (paper Sec. 3.2).

    Args:
        depth: number of message-passing rounds (default 2, the paper's best).
        node_in: size of the node input (default 4: width, height, focal, k1).
        node_hidden: size of the node state after each round (default 32).
        edge_hidden: size of the hidden edge state per direction (default 0: pose only).
        mlp_hidden: units of each hidden layer of ``Psi_E`` / ``Psi_N`` (default 32).
        mlp_layers: linear layers per MLP (default 3).
        negative_slope: leaky ReLU slope (default 0.01).
        shared_weights: one :class:`PoserConv` reused by every round (default False). The node
            input is then first embedded to ``node_hidden`` by a linear layer so every round
            sees the same sizes.
        residual: each round predicts a correction composed with the current pose (default
            False: direct regression, as in the paper).
        unit_output: normalise the output quaternion and translation (default False: the paper
            leaves the norms to the loss' normalisation terms).
        nested_mean: the paper's nested mean for the node update (default True).
        gate: a learned per-edge gate between the input pose and the prediction
            (:class:`posernet.nn.adaptive.EdgeHead`; default False).
        confidence: a per-edge heteroscedastic error head: the expected rotation / direction
            error of the output and of the input (default False).
        cycle_feature: the rotation cycle consistency of the input poses
            (:func:`posernet.nn.adaptive.cycle_features`) is the initial hidden edge state;
            needs ``edge_hidden >= 3`` (default False).
        head_hidden: width of the gate / confidence MLP (default 32).

        The four adaptive options default off: a network without them has exactly the
        parameters and outputs it had before they existed (old checkpoints load unchanged).

    Shapes:
        ``forward(graph)`` with a ``ViewGraph``/``GraphBatch`` (or a PyG ``Batch`` of
        :class:`posernet.nn.pyg.PoserData`), or
        ``forward(x [N, node_in], edge_index [2, E], edge_pose [E, 7], pair_edge [M],
        pair_box_src [M, 4], pair_box_dst [M, 4])`` -> refined ``edge_pose [E, 7]``
        (a list of ``depth`` of them, one per round, with ``return_all=True``).
    """

    Options = PoserNetOptions

    def __init__(
        self,
        depth: int = 2,
        node_in: int = 4,
        node_hidden: int = 32,
        edge_hidden: int = 0,
        mlp_hidden: int = 32,
        mlp_layers: int = 3,
        negative_slope: float = 0.01,
        shared_weights: bool = False,
        residual: bool = False,
        unit_output: bool = False,
        nested_mean: bool = True,
        gate: bool = False,
        confidence: bool = False,
        cycle_feature: bool = False,
        head_hidden: int = 32,
    ) -> None:
        super().__init__()
        args = locals()
        PoserNetOptions(**{f.name: args[f.name] for f in dataclasses.fields(PoserNetOptions)})
        self.edge_hidden = edge_hidden
        self.gate, self.confidence, self.cycle_feature = bool(gate), bool(confidence), \
            bool(cycle_feature)
        self.depth, self.node_in, self.node_hidden = depth, node_in, node_hidden
        self.shared_weights, self.residual, self.unit_output = shared_weights, residual, unit_output

        def conv(n_in: int, last: bool) -> PoserConv:
            # the last round's node states and hidden edge state are never read: not built
            return PoserConv(n_in, node_hidden, edge_dim=edge_hidden,
                             hidden_channels=mlp_hidden, num_layers=mlp_layers,
                             negative_slope=negative_slope, residual=residual,
                             nested_mean=nested_mean, update_nodes=not last,
                             update_edge_state=not last)

        if shared_weights:
            self.encoder: nn.Module = nn.Linear(node_in, node_hidden)
            # one layer for every round: it needs the node update unless it is the only round
            self.convs = nn.ModuleList([conv(node_hidden, last=depth == 1)])
        else:
            self.encoder = nn.Identity()
            self.convs = nn.ModuleList([conv(node_in if k == 0 else node_hidden,
                                             last=k == depth - 1) for k in range(depth)])
        # built only when asked for: old checkpoints have no such weights
        self.head: EdgeHead | None = (
            EdgeHead(self.gate, self.confidence, hidden=head_hidden, layers=mlp_layers,
                     negative_slope=negative_slope)
            if (self.gate or self.confidence) else None)

    @property
    def adaptive(self) -> bool:
        """True when the network has a gate or a confidence head (``return_extras`` helps)."""
        return self.head is not None

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike[str],
                        map_location: str | torch.device = "cpu") -> PoserNet:
        """The network of a ``PoserNetModule`` checkpoint, in eval mode, without Lightning;
        ``path`` may name a shipped one (``"shipped"``, ``"shipped:NAME"``, a shipped file's name).

        Raises :class:`CheckpointError` for a missing, foreign or mismatching checkpoint.
        """
        from ..checkpoints import read_checkpoint  # the checkpoint file format (torch only)

        return cls.from_checkpoint_dict(read_checkpoint(path), path).to(map_location).eval()

    @classmethod
    def from_checkpoint_dict(cls, ckpt: dict[str, Any],
                             path: str | os.PathLike[str] = "checkpoint") -> PoserNet:
        """The network (on the CPU, train mode) of a checkpoint dict from
        :func:`posernet.checkpoints.read_checkpoint`.

        The one place that turns a checkpoint into weights: :meth:`from_checkpoint` and
        ``posernet.lit.load_posernet_checkpoint`` both use it. The network's arguments are
        :func:`posernet.checkpoints.network_hparams` (``hyper_parameters["net"]``); every entry
        of ``state_dict`` must be a ``model.`` weight that fits, else
        :class:`posernet.checkpoints.CheckpointError` (naming ``path``) is raised.
        """
        from ..checkpoints import CheckpointError, network_hparams

        names = set(inspect.signature(cls).parameters)
        prefix = "model."
        state_dict = ckpt["state_dict"]
        foreign = [k for k in state_dict if not k.startswith(prefix)]
        state = {k[len(prefix):]: v for k, v in state_dict.items() if k.startswith(prefix)}
        try:
            hp = network_hparams(ckpt)
            if foreign:
                raise RuntimeError(f"unexpected weights {foreign[:3]}")
            unknown = sorted(set(hp) - names)
            if unknown:
                raise TypeError(f"unknown network arguments {unknown}")
            model = cls(**hp)
            model.load_state_dict(state)
        except (TypeError, RuntimeError, ValueError) as exc:
            raise CheckpointError(f"{path}: checkpoint does not fit this PoserNet ({exc})") from exc
        return model

    def reset_parameters(self) -> None:
        if isinstance(self.encoder, nn.Linear):
            self.encoder.reset_parameters()
        for c in self.convs:
            c.reset_parameters()
        if self.head is not None:
            self.head.reset_parameters()

    def forward(
        self,
        x: Tensor | Any,
        edge_index: Tensor | None = None,
        edge_pose: Tensor | None = None,
        pair_edge: Tensor | None = None,
        pair_box_src: Tensor | None = None,
        pair_box_dst: Tensor | None = None,
        return_all: bool = False,
        return_extras: bool = False,
    ) -> Tensor | list[Tensor] | AdaptiveOutput:
        """Refine every edge's relative pose.

        ``x`` may be a graph: a ``ViewGraph``/``GraphBatch``, or a
        :class:`posernet.nn.pyg.PoserData` / a PyTorch Geometric ``Batch`` of them.
        ``return_extras=True`` returns an :class:`~posernet.nn.adaptive.AdaptiveOutput`
        (final pose, pre-gate prediction, gate and error scales; ``None`` where not built).
        """
        if is_graph_input(x):
            inputs = graph_inputs(x)
            if edge_pose is not None:
                inputs["edge_pose"] = edge_pose
        else:
            inputs = {"x": x, "edge_index": edge_index, "edge_pose": edge_pose,
                      "pair_edge": pair_edge, "pair_box_src": pair_box_src,
                      "pair_box_dst": pair_box_dst}
        validate_inputs(type(self).__name__, node_dim=self.node_in, **inputs)
        check_module_inputs(self, inputs["x"])
        h = self.encoder(inputs["x"])
        pose = pose_in = inputs["edge_pose"]
        state = None
        cyc_in = None
        if self.cycle_feature or self.head is not None:
            cyc_in = cycle_features(inputs["edge_index"], pose_in, inputs["x"].shape[0])
        if self.cycle_feature:
            assert cyc_in is not None
            # both directions see the same (direction-invariant) consistency features
            state = pose.new_zeros(pose.shape[0], 2, self.edge_hidden)
            state[:, :, :cyc_in.shape[1]] = cyc_in[:, None]
        outputs = []
        for k in range(self.depth):
            conv = self.convs[0 if self.shared_weights else k]
            last = k == self.depth - 1  # only its edge poses are read
            # inputs checked once above: each round runs without the checks' host sync
            h, pose, state = conv.propagate(
                h, inputs["edge_index"], pose, inputs["pair_edge"], inputs["pair_box_src"],
                inputs["pair_box_dst"], state, update_nodes=not last,
                update_edge_state=not last,
            )
            if last or return_all:  # the other rounds' outputs are not returned
                outputs.append(self._finalise(pose))
        raw = outputs[-1]
        gate = sigma = None
        if self.head is not None:
            assert cyc_in is not None
            E = raw.shape[0]
            stats = pair_stats(inputs["pair_edge"], inputs["pair_box_src"],
                                inputs["pair_box_dst"], E)
            cyc_raw = cycle_features(inputs["edge_index"], raw, inputs["x"].shape[0])
            # the head judges the prediction; it does not train the prediction through its
            # features (the pose loss does, through the blend)
            feats = EdgeHead.features(pose_in, raw.detach(), cyc_in, cyc_raw, stats)
            gate, sigma = self.head(feats)
            if gate is not None:
                outputs[-1] = blend_poses(pose_in, raw, gate)
        if return_extras:
            return AdaptiveOutput(outputs[-1], raw, gate, sigma)
        return outputs if return_all else outputs[-1]

    def _finalise(self, pose: Tensor) -> Tensor:
        q, t = pose[:, :4], pose[:, 4:]
        if self.unit_output:
            q = quaternion_normalize(q)
            t = nn.functional.normalize(t, dim=-1, eps=1e-12)
        return torch.cat((quaternion_canonical(q), t), dim=-1)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(depth={self.depth}, node_hidden={self.node_hidden}, "
                f"shared_weights={self.shared_weights}, residual={self.residual}, "
                f"unit_output={self.unit_output}, convs={list(self.convs)})")

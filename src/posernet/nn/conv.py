"""``PoserConv``: one round of PoserNet message passing over matched detection pairs.

The paper (Sec. 3.2) sends one message per matched detection pair ("layer" ``l``) on an edge
``(i, j)``. This module implements that round with plain tensors so that any GNN can use it:
``edge_index [2, E]`` (row 0 source, row 1 target, as in PyG) and one row per matched pair
(``pair_edge [M]`` plus the two boxes of the pair). It also accepts a
:class:`posernet.graph.ViewGraph` / :class:`posernet.graph.GraphBatch` directly, and PyTorch
Geometric users batch :class:`posernet.nn.pyg.PoserData` with PyG's own ``Batch`` /
``DataLoader`` (a plain ``Data`` would not offset the matched-pair indices; see
:mod:`posernet.nn.pyg`). Sizes use PyG's argument names (``in_channels``, ``out_channels``,
``hidden_channels``, ``num_layers``), and ``Psi_E`` / ``Psi_N`` can be your own modules.

Direction awareness
-------------------
Each image pair is stored once, ``i -> j`` with pose ``e_ij``; the reverse direction is the
inverse pose ``e_ji = e_ij^{-1}`` with the boxes of every pair swapped. Refining a relative pose
must not depend on which direction happens to be stored, so the round runs every message in
*both* directions ("views") of every edge and fuses them:

* forward view of edge ``i -> j``:  ``(h_i, h_j, e_ij, g_ij, bb_i^l, bb_j^l)``,
* backward view (as ``j`` sees it): ``(h_j, h_i, e_ji, g_ji, bb_j^l, bb_i^l)``,

where ``g`` is an optional hidden edge state kept per direction. The same ``Psi_E`` applied to
the forward view predicts the new pose ``P_ij``; applied to the backward view it predicts
``P_ji``. The new pose of ``i -> j`` is the inverse-equivariant mean
``mu(P_ij, P_ji^{-1})`` (:func:`posernet.geometry.symmetric_pose_mean`), which satisfies
``mu(a, b)^{-1} = mu(a^{-1}, b^{-1})`` and ``mu(a, b) = mu(b, a)`` exactly. Storing the edge the
other way round swaps the two views, so the refined pose of the flipped edge is *exactly* the
inverse of the refined pose of the original edge (up to float round-off), whatever the weights.
The hidden states ``g_ij``, ``g_ji`` simply swap. A node hears each neighbour through the view
that starts at itself, as the paper prescribes, so node states do not depend on the stored
direction either.

Update rule of one round (``k -> k+1``), with ``L_ij`` the matched pairs of edge ``(i, j)``:

.. math::

    m^E_{ij,l} = \\Psi_E(h_i, h_j, e_{ij}, g_{ij}, bb_{i,l}, bb_{j,l}), \\qquad
    [P_{ij}, g'_{ij}] = \\frac{1}{|L_{ij}|} \\sum_{l \\in L_{ij}} m^E_{ij,l}

    e'_{ij} = \\mu(P_{ij}, P_{ji}^{-1})

    m^N_{ij,l} = \\Psi_N(h_i, h_j, e_{ij}, g_{ij}, bb_{i,l}, bb_{j,l}), \\qquad
    h'_i = \\frac{1}{|\\mathcal N_i|} \\sum_{j \\in \\mathcal N_i}
           \\frac{1}{|L_{ij}|} \\sum_{l \\in L_{ij}} m^N_{ij,l}

(the paper's nested mean; ``nested_mean=False`` gives the flat mean over all pairs of all
neighbours). With ``residual=True`` the pose part of ``Psi_E`` is a correction
``delta = [1 + d_q, d_t]`` composed with the current pose, ``P_ij = delta o e_ij``; otherwise
the pose is regressed directly, as in the paper. Edges without any matched pair keep their
pose and hidden state, and nodes without neighbours get a zero state.

The last round of a network
---------------------------
Only the edge poses of the last round are read. A layer built with ``update_nodes=False`` has no
``Psi_N`` at all and returns ``x = None``; with ``update_edge_state=False`` its ``Psi_E``
predicts the pose only and it returns ``edge_state = None``. Nothing that cannot reach the
output is built or computed, so every parameter gets a gradient (distributed data parallel
training needs that) and the edge poses are exactly those of a full layer with the same
``Psi_E`` pose weights.

Fast path
---------
With the built-in MLPs (``fused=True``, the default) a round computes the same maths in fewer
operations; the stored parameters are unchanged (the fused weights are views built at run
time), so checkpoints load either way, and the outputs agree with ``fused=False`` (the literal
computation above) to float round-off (tested, with gradients):

* the first linear layer is split by input: the columns reading ``h_i, h_j, e_ij, g_ij`` are
  applied once per edge view and gathered to its pairs, only the 8 box columns run per pair;
* ``Psi_E`` and ``Psi_N`` read the same input: their first layers run as one wider product;
* ``Psi_E``'s last layer has no activation, so it commutes with the mean over the pairs: it runs
  once per edge view on the averaged hidden units;
* the two views of a pair are adjacent rows (``[M, 2, *]``), one gather serving both;
* each network's first layer has one more unit, constant 1 (weights 0, bias 1), so the later
  per-pair layers take their bias as a weight row: plain products, without first copying the
  bias into every output row;
* leaky ReLUs run in place (autograd allows it for a non-negative slope);
* inference on the CPU (no autograd, not under ``torch.compile``) runs in blocks of edges with
  about ``_BLOCK_PAIRS`` pairs each: activations stay in the cache and no tensor of the size of
  all pairs is allocated (fresh large allocations cost page faults that outweigh the
  arithmetic); a block's means over each edge's pairs are one sparse product (deterministic).

A ``psi_edge`` / ``psi_node`` of your own (any module other than :class:`~posernet.nn.MLP`), or
an MLP with forward hooks, runs the literal path.
"""

from __future__ import annotations

import warnings
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from ..geometry import (
    compose_pose_vec,
    invert_pose_raw,
    quaternion_canonical,
    symmetric_pose_mean,
)
from ..graph import check_edge_index
from ..scatter import scatter_count, scatter_mean, scatter_sum, scatter_sum_unchecked
from .mlp import MLP

__all__ = [
    "PoserConv",
    "PoserConvOutput",
    "graph_inputs",
    "is_graph_input",
]

BOX_DIM = 4
POSE_DIM = 7


class PoserConvOutput(NamedTuple):
    """Result of one :class:`PoserConv` round.

    ``x [N, out_channels]`` new node states (``None`` when the layer does not update nodes),
    ``edge_pose [E, 7]`` new pose of every stored direction ``i -> j``,
    ``edge_state [E, 2, edge_dim]`` hidden state of the forward (index 0) and backward (index 1)
    direction, or ``None`` when ``edge_dim == 0`` or the layer does not update it.
    """

    x: Tensor | None
    edge_pose: Tensor
    edge_state: Tensor | None


# --------------------------------------------------------------------------- inputs


def graph_inputs(graph: Any) -> dict[str, Tensor]:
    """Plain-tensor inputs of :class:`PoserConv` / ``PoserNet`` from a graph object.

    ``graph``: a ``ViewGraph``/``GraphBatch``, or a :class:`posernet.nn.pyg.PoserData` and the
    PyTorch Geometric ``Batch`` of them (any object with the ``ViewGraph`` field names).
    Returns ``x = node_attr [N, 4]``, ``edge_index [2, E]``, ``edge_pose [E, 7]``,
    ``pair_edge [M]``, ``pair_box_src = det_box[pair_src] [M, 4]`` and
    ``pair_box_dst = det_box[pair_dst] [M, 4]``.

    A PyG ``Batch`` whose ``pair_*`` fields were not offset (built from a plain
    ``torch_geometric.data.Data``, which offsets only fields named ``*index*``) raises
    ``ValueError`` instead of giving pairs that point into the wrong graph.
    """
    for name in ("node_attr", "edge_index", "edge_pose", "pair_edge", "pair_src", "pair_dst",
                 "det_box"):
        if getattr(graph, name, None) is None:
            raise ValueError(f"graph {getattr(graph, 'name', '?')!r} has no field {name!r}")
    _check_pyg_offsets(graph)
    return {
        "x": graph.node_attr,
        "edge_index": graph.edge_index,
        "edge_pose": graph.edge_pose,
        "pair_edge": graph.pair_edge,
        "pair_box_src": graph.det_box[graph.pair_src],
        "pair_box_dst": graph.det_box[graph.pair_dst],
    }


def _check_pyg_offsets(graph: Any) -> None:
    """A PyG ``Batch`` records each field's per-graph increment (``_inc_dict``) and slices
    (``_slice_dict``): ``pair_edge`` must have moved by the edges of the graphs before it,
    ``pair_src`` / ``pair_dst`` by their detections. Read by duck typing: no PyG import."""
    incs, slices = getattr(graph, "_inc_dict", None), getattr(graph, "_slice_dict", None)
    if not isinstance(incs, dict) or not isinstance(slices, dict):
        return
    for name, ref, what in (("pair_edge", "edge_index", "edges"),
                            ("pair_src", "det_box", "detections"),
                            ("pair_dst", "det_box", "detections")):
        inc, sl = incs.get(name), slices.get(ref)
        if not isinstance(sl, Tensor) or sl.ndim != 1:
            continue
        expected = sl[:-1].cpu()
        got = torch.zeros_like(expected) if inc is None else torch.as_tensor(inc).cpu()
        if got.shape != expected.shape or not torch.equal(got.to(expected.dtype), expected):
            raise ValueError(
                f"{type(graph).__name__}: torch_geometric batched {name!r} without adding the "
                f"number of {what} of the graphs before each graph (PyG offsets only fields "
                f"named '*index*'), so matched pairs would point into the wrong graph; build "
                f"the graphs with posernet.nn.pyg.PoserData.from_view_graph(g) (or a Data "
                f"class whose __inc__ offsets {name!r})")


def is_graph_input(x: Any) -> bool:
    return not isinstance(x, Tensor) and hasattr(x, "edge_index") and hasattr(x, "det_box")


def _shape(t: Any) -> str:
    return str(tuple(t.shape)) if isinstance(t, Tensor) else type(t).__name__


def check_module_inputs(module: nn.Module, x: Tensor) -> None:
    """Inputs must share the parameters' dtype and device (clear message instead of a deep one)."""
    p = next(module.parameters(), None)
    if p is None:
        return
    who = type(module).__name__
    if x.dtype != p.dtype:
        raise ValueError(f"{who}: inputs are {x.dtype} but the parameters are {p.dtype}; "
                         f"convert the model (.to({x.dtype})) or the graph")
    if x.device != p.device:
        raise ValueError(f"{who}: inputs are on {x.device} but the parameters on {p.device}; "
                         f"move the graph (.to(device)) or the model")


def validate_inputs(
    who: str,
    x: Tensor,
    edge_index: Tensor,
    edge_pose: Tensor,
    pair_edge: Tensor,
    pair_box_src: Tensor,
    pair_box_dst: Tensor,
    node_dim: int | None = None,
) -> None:
    """Check shapes, dtypes and index ranges; raise ``ValueError`` naming the argument."""

    def fail(msg: str) -> None:
        raise ValueError(f"{who}: {msg}")

    for name, t in (("x", x), ("edge_index", edge_index), ("edge_pose", edge_pose),
                    ("pair_edge", pair_edge), ("pair_box_src", pair_box_src),
                    ("pair_box_dst", pair_box_dst)):
        if not isinstance(t, Tensor):
            fail(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if x.ndim != 2 or not x.is_floating_point():
        fail(f"x (node features) must be a float tensor [N, F], got {_shape(x)} {x.dtype}")
    if node_dim is not None and x.shape[1] != node_dim:
        fail(f"x has {x.shape[1]} features per node, the layer expects {node_dim}")
    N = x.shape[0]
    try:
        check_edge_index(edge_index)
    except ValueError as exc:
        fail(str(exc))
    E = edge_index.shape[1]
    if edge_pose.shape != (E, POSE_DIM):
        fail(f"edge_pose must have shape [E, 7] = [{E}, 7], got {_shape(edge_pose)}")
    if edge_pose.dtype != x.dtype:
        fail(f"edge_pose dtype {edge_pose.dtype} differs from x dtype {x.dtype}")
    if pair_edge.ndim != 1:
        fail(f"pair_edge must be 1-D [M], got {_shape(pair_edge)}")
    M = pair_edge.shape[0]
    for name, t in (("pair_box_src", pair_box_src), ("pair_box_dst", pair_box_dst)):
        if t.shape != (M, BOX_DIM):
            fail(f"{name} must have shape [M, 4] = [{M}, 4], got {_shape(t)}")
        if t.dtype != x.dtype:
            fail(f"{name} dtype {t.dtype} differs from x dtype {x.dtype}")
    # dtypes, index ranges and self loops: one host sync for all of them (see
    # posernet.graph.check_edge_index), none when the inputs are valid.
    try:
        check_edge_index(edge_index, N, others=(("pair_edge", pair_edge, E, "edges"),))
    except ValueError as exc:
        fail(str(exc))


# --------------------------------------------------------------------------- the layer


class PoserConv(nn.Module):
    """One round of PoserNet message passing (see the module docstring for the update rule).

    The size arguments follow PyTorch Geometric's names.

    Args:
        in_channels: size of the incoming node state ``h`` (4 for the raw camera attributes).
        out_channels: size of the new node state (default 32).
        edge_dim: size of the hidden edge state kept per direction (default 0: the edge
            state is the 7-vector pose only, as in the paper).
        hidden_channels: units of the hidden layers of ``Psi_E`` and ``Psi_N`` (default 32).
            Unused by a network passed as ``psi_edge`` / ``psi_node``.
        num_layers: linear layers per MLP (default 3).
        negative_slope: leaky ReLU slope (default 0.01).
        residual: predict a correction composed with the current pose instead of the pose
            itself (default False, the paper's direct regression).
        nested_mean: node update = mean over neighbours of the mean over their pairs (default
            True, the paper's equation); False = flat mean over all incoming pair messages.
        update_nodes: build ``Psi_N`` and return new node states (default True). False for the
            last round of a network, whose node states nothing reads: ``x`` is then ``None``.
        update_edge_state: ``Psi_E`` also predicts the new hidden edge state (default True;
            only matters when ``edge_dim > 0``). False for the last round of a network: the
            input state is still read, the output ``edge_state`` is ``None``.
        psi_edge: your own ``Psi_E`` (any module), used instead of the built-in MLP. It maps
            ``[*, message_dim]`` to ``[*, 7 + edge_dim]`` (``[*, 7]`` when the layer does not
            update the edge state); no activation on the pose outputs.
        psi_node: your own ``Psi_N``, ``[*, message_dim] -> [*, out_channels]``.
            ``message_dim = 2 * in_channels + 7 + edge_dim + 8``
            (``PoserConv.message_size(in_channels, edge_dim)``): the two node states, the
            pose, the hidden edge state and the two boxes of a pair, in that order.
        fused: run the built-in MLPs through the fused fast path (default True; see
            "Fast path" in the module docstring). False runs every network on the
            concatenated message of every pair, literally as written above (the reference the
            fast path is tested against). Settable later: ``conv.fused = False``.

    Shapes:
        ``x [N, in_channels]``, ``edge_index [2, E]`` (long), ``edge_pose [E, 7]``,
        ``pair_edge [M]`` (long), ``pair_box_src, pair_box_dst [M, 4]``,
        ``edge_state [E, 2, edge_dim]`` (optional) ->
        :class:`PoserConvOutput` ``(x [N, out_channels], edge_pose [E, 7], edge_state)``.
    """

    psi_edge: nn.Module
    psi_node: nn.Module | None

    def __init__(
        self,
        in_channels: int | None = None,
        out_channels: int | None = None,
        edge_dim: int = 0,
        hidden_channels: int | None = None,
        num_layers: int = 3,
        negative_slope: float = 0.01,
        residual: bool = False,
        nested_mean: bool = True,
        update_nodes: bool = True,
        update_edge_state: bool = True,
        psi_edge: nn.Module | None = None,
        psi_node: nn.Module | None = None,
        *,
        fused: bool = True,
    ) -> None:
        super().__init__()
        self.fused = bool(fused)
        if in_channels is None:
            raise TypeError("PoserConv needs in_channels (the size of the node input)")
        out_channels = 32 if out_channels is None else out_channels
        hidden_channels = 32 if hidden_channels is None else hidden_channels
        if in_channels < 1 or out_channels < 1 or edge_dim < 0:
            raise ValueError(f"PoserConv sizes must be positive: in_channels={in_channels}, "
                             f"out_channels={out_channels}, edge_dim={edge_dim}")
        if psi_node is not None and not update_nodes:
            raise ValueError("PoserConv: psi_node was given but update_nodes=False "
                             "(a layer without node update has no Psi_N)")
        for name, net in (("psi_edge", psi_edge), ("psi_node", psi_node)):
            if net is not None and not isinstance(net, nn.Module):
                raise TypeError(f"PoserConv: {name} must be a torch.nn.Module, "
                                f"got {type(net).__name__}")
        self.in_channels, self.out_channels, self.edge_dim = in_channels, out_channels, edge_dim
        self.hidden_channels, self.num_layers = hidden_channels, num_layers
        self.residual, self.nested_mean = residual, nested_mean
        self.update_nodes = bool(update_nodes)
        self.update_edge_state = bool(update_edge_state) and edge_dim > 0
        in_dim = self.message_dim
        # Psi_E regresses signed pose values: no activation after its last layer.
        self.psi_edge = psi_edge if psi_edge is not None else MLP(
            in_dim, self.edge_out_dim, hidden_channels, num_layers, negative_slope,
            act_last=False)
        # Psi_N: every layer followed by a leaky ReLU (paper, supplementary). Not built when
        # nothing reads the new node states (the last round of a network).
        if not self.update_nodes:
            self.psi_node = None
        else:
            self.psi_node = psi_node if psi_node is not None else MLP(
                in_dim, out_channels, hidden_channels, num_layers, negative_slope,
                act_last=True)

    @staticmethod
    def message_size(in_channels: int, edge_dim: int = 0) -> int:
        """Input size of ``Psi_E`` / ``Psi_N`` for these sizes (to build your own networks):
        ``2 * in_channels + 7 + edge_dim + 8``."""
        return 2 * in_channels + POSE_DIM + edge_dim + 2 * BOX_DIM

    @property
    def message_dim(self) -> int:
        """Input size of this layer's ``Psi_E`` / ``Psi_N`` (:meth:`message_size`)."""
        return self.message_size(self.in_channels, self.edge_dim)

    @property
    def edge_out_dim(self) -> int:
        """Output size of ``Psi_E``: ``7 + edge_dim``, or 7 without an edge-state update."""
        return POSE_DIM + (self.edge_dim if self.update_edge_state else 0)

    def reset_parameters(self) -> None:
        """Re-initialise ``Psi_E`` and ``Psi_N`` (for networks passed in: every submodule
        that has a ``reset_parameters``)."""
        _reset(self.psi_edge)
        if self.psi_node is not None:
            _reset(self.psi_node)

    def __repr__(self) -> str:
        if isinstance(self.psi_edge, MLP):
            nets = f"hidden={self.psi_edge.hidden}, layers={self.psi_edge.num_layers}"
        else:
            nets = f"psi_edge={type(self.psi_edge).__name__}"
        if self.psi_node is not None and not isinstance(self.psi_node, MLP):
            nets += f", psi_node={type(self.psi_node).__name__}"
        return (f"{type(self).__name__}(node {self.in_channels} -> {self.out_channels}, "
                f"edge_dim={self.edge_dim}, {nets}, residual={self.residual}, "
                f"nested_mean={self.nested_mean}"
                + ("" if self.update_nodes else ", update_nodes=False")
                + ("" if self.update_edge_state or not self.edge_dim
                   else ", update_edge_state=False") + ")")

    def forward(
        self,
        x: Tensor | Any,
        edge_index: Tensor | None = None,
        edge_pose: Tensor | None = None,
        pair_edge: Tensor | None = None,
        pair_box_src: Tensor | None = None,
        pair_box_dst: Tensor | None = None,
        edge_state: Tensor | None = None,
        *,
        update_nodes: bool | None = None,
        update_edge_state: bool | None = None,
    ) -> PoserConvOutput:
        """Check the inputs and run one round (:meth:`propagate`).

        ``x`` may be a graph instead of tensors (a ``ViewGraph``/``GraphBatch``, or a
        :class:`posernet.nn.pyg.PoserData` / its PyG ``Batch``); its fields are then used
        (``edge_pose`` and ``edge_state`` may still be given to override / continue).
        ``update_nodes`` / ``update_edge_state``: see :meth:`propagate`.
        """
        if is_graph_input(x):
            inputs = graph_inputs(x)
            if edge_pose is not None:
                inputs["edge_pose"] = edge_pose
            x, edge_index, edge_pose, pair_edge, pair_box_src, pair_box_dst = (
                inputs[k] for k in ("x", "edge_index", "edge_pose", "pair_edge", "pair_box_src",
                                    "pair_box_dst"))
        validate_inputs(type(self).__name__, x, edge_index, edge_pose, pair_edge,
                        pair_box_src, pair_box_dst, node_dim=self.in_channels)
        check_module_inputs(self, x)
        E = edge_index.shape[1]
        if self.edge_dim and edge_state is not None and \
                edge_state.shape != (E, 2, self.edge_dim):
            raise ValueError(f"{type(self).__name__}: edge_state must have shape "
                             f"[E, 2, {self.edge_dim}], got {_shape(edge_state)}")
        return self.propagate(x, edge_index, edge_pose, pair_edge, pair_box_src, pair_box_dst,
                              edge_state, update_nodes=update_nodes,
                              update_edge_state=update_edge_state)

    def propagate(
        self,
        x: Tensor,
        edge_index: Tensor,
        edge_pose: Tensor,
        pair_edge: Tensor,
        pair_box_src: Tensor,
        pair_box_dst: Tensor,
        edge_state: Tensor | None = None,
        *,
        update_nodes: bool | None = None,
        update_edge_state: bool | None = None,
    ) -> PoserConvOutput:
        """The round itself, on tensors, without :meth:`forward`'s input checks.

        The checks cost a host synchronisation (index ranges); a caller that ran them once
        (:func:`validate_inputs`), such as a network running several rounds on one graph, calls
        this directly. Wrong inputs here give wrong results or errors from deep inside torch.

        ``edge_state`` defaults to zeros. ``update_nodes`` / ``update_edge_state`` (default: the
        layer's own settings) switch the node update / the hidden-edge-state output off for this
        call, e.g. for the last round of a network that reuses one layer; ``update_nodes=True``
        on a layer built without ``Psi_N`` raises ``ValueError``.
        """
        box_src, box_dst = pair_box_src, pair_box_dst
        if update_nodes is None:
            update_nodes = self.update_nodes
        elif update_nodes and self.psi_node is None:
            raise ValueError(f"{type(self).__name__} was built with update_nodes=False")
        if update_edge_state is None:
            update_edge_state = self.update_edge_state
        update_edge_state = update_edge_state and self.update_edge_state
        if self.edge_dim and edge_state is None:
            edge_state = x.new_zeros(edge_index.shape[1], 2, self.edge_dim)
        nets = self._fusable_nets(update_nodes)
        if nets is not None:
            return self._propagate_fused(nets, x, edge_index, edge_pose, pair_edge, box_src,
                                         box_dst, edge_state, update_edge_state)
        N, E = x.shape[0], edge_index.shape[1]
        src, dst = edge_index
        # Directed views: rows [0, E) are i -> j as stored, rows [E, 2E) the reverse j -> i.
        own = torch.cat((src, dst))
        other = torch.cat((dst, src))
        pose_view = torch.cat((edge_pose, invert_pose_raw(edge_pose)))
        # The network sees sign-canonical quaternions (q and -q are one rotation);
        # canonical(conj q) = conj(canonical q), so this keeps the two views consistent.
        pose_in = torch.cat((quaternion_canonical(pose_view[:, :4]), pose_view[:, 4:]), dim=-1)
        view_pair = torch.cat((pair_edge, pair_edge + E))  # [2M] directed edge of each row
        box_own = torch.cat((box_src, box_dst))
        box_other = torch.cat((box_dst, box_src))
        feats = [x[own[view_pair]], x[other[view_pair]], pose_in[view_pair]]
        if self.edge_dim:
            state_view = torch.cat((edge_state[:, 0], edge_state[:, 1]))
            feats.append(state_view[view_pair])
        feats += [box_own, box_other]
        z = torch.cat(feats, dim=-1)  # [2M, in_dim]

        # ---- edge update: mean over the edge's pairs, per direction, then fuse the directions.
        n_pairs = scatter_count(view_pair, 2 * E)  # [2E]
        has = (n_pairs > 0)[:, None]
        m_edge = scatter_mean(self._psi("psi_edge", z, self.edge_out_dim), view_pair, 0, 2 * E)
        out = m_edge[:, :POSE_DIM]
        if self.residual:
            one = torch.zeros_like(out)
            one[:, 0] = 1.0
            delta = out + one  # zero output = identity correction
            pred = compose_pose_vec(delta, pose_view)
        else:
            pred = out
        pred = torch.where(has, pred, pose_view)  # edges without pairs keep their pose
        fwd, bwd = pred[:E], pred[E:]
        new_pose = symmetric_pose_mean(fwd, invert_pose_raw(bwd), edge_pose)
        new_state = None
        if update_edge_state:
            s = torch.where(has, m_edge[:, POSE_DIM:], state_view)
            new_state = torch.stack((s[:E], s[E:]), dim=1)
        if not update_nodes:
            return PoserConvOutput(None, new_pose, new_state)

        # ---- node update: each node hears every neighbour through the view starting at itself.
        assert self.psi_node is not None
        m_node = self._psi("psi_node", z, self.out_channels)  # [2M, out_channels]
        if self.nested_mean:
            per_view = scatter_mean(m_node, view_pair, 0, 2 * E)  # mean over the pairs
            w = has.to(x.dtype)  # views without pairs are not neighbours
            total = scatter_sum(per_view * w, own, 0, N)
            count = scatter_sum(w, own, 0, N).clamp_min(1.0)
            h = total / count
        else:
            h = scatter_mean(m_node, own[view_pair], 0, N)
        return PoserConvOutput(h, new_pose, new_state)

    def _psi(self, name: str, z: Tensor, width: int) -> Tensor:
        """Apply ``Psi_E`` / ``Psi_N``; a network passed in must give ``[2M, width]``."""
        out = getattr(self, name)(z)
        if not isinstance(out, Tensor) or out.shape != (z.shape[0], width):
            raise ValueError(f"{type(self).__name__}: {name} maps [{z.shape[0]}, "
                             f"{z.shape[1]}] messages to {_shape(out)}, expected "
                             f"[{z.shape[0]}, {width}]")
        return out

    # ----------------------------------------------------------------------- fast path

    def _fusable_nets(self, update_nodes: bool) -> list[MLP] | None:
        """``[Psi_E]`` or ``[Psi_E, Psi_N]`` when the fast path applies to this call, else None.

        Only the built-in :class:`MLP` (exactly that class, of Linear and LeakyReLU modules,
        no hooks, the layer's sizes) can be split: the fast path reads its weights directly.
        Anything else runs the generic path, which also reports wrong sizes.
        """
        if not self.fused:
            return None
        nets = [self.psi_edge] + ([self.psi_node] if update_nodes else [])
        for net, width in zip(nets, (self.edge_out_dim, self.out_channels), strict=False):
            if (type(net) is not MLP or net.in_dim != self.message_dim or net.out_dim != width
                    or net._forward_hooks or net._forward_pre_hooks
                    or not all(type(m) in (nn.Linear, nn.LeakyReLU) for m in net.net)):
                return None
        return nets  # type: ignore[return-value]

    def _propagate_fused(
        self,
        nets: list[MLP],
        x: Tensor,
        edge_index: Tensor,
        edge_pose: Tensor,
        pair_edge: Tensor,
        box_src: Tensor,
        box_dst: Tensor,
        edge_state: Tensor | None,
        update_edge_state: bool,
    ) -> PoserConvOutput:
        """The round of :meth:`propagate` with the first layers split and fused (same maths).

        Layout: the two views of edge ``e`` are adjacent (``[E, 2, *]``, index 0 = ``i -> j``
        as stored, 1 = ``j -> i``) and so are the two view rows of pair ``p`` (``[M, 2, *]``),
        so that one gather by ``pair_edge`` serves both directions.
        """
        N, E = x.shape[0], edge_index.shape[1]
        M = pair_edge.shape[0]
        src, dst = edge_index[0], edge_index[1]
        own = torch.stack((src, dst), dim=1)  # [E, 2] node each view starts at
        other = torch.stack((dst, src), dim=1)
        own_flat = own.reshape(-1)  # [2E] in view order
        pose_view = torch.stack((edge_pose, invert_pose_raw(edge_pose)), dim=1)  # [E, 2, 7]
        pose_in = torch.cat((quaternion_canonical(pose_view[..., :4]), pose_view[..., 4:]), -1)
        layers = [_linear_layers(net) for net in nets]
        widths = [lyr[0][0].weight.shape[0] for lyr in layers]
        # Psi_E's last linear layer (no activation after it) commutes with the mean over the
        # pairs: averaged hidden units, then one product per edge view instead of per pair.
        edge_layers = layers[0]
        defer = len(edge_layers) > 1 and edge_layers[-1][1] is None
        edge_rest = edge_layers[1:-1] if defer else edge_layers[1:]
        rests = [edge_rest] + [lyr[1:] for lyr in layers[1:]]
        # Each network's first-layer block has one more unit, constant 1 (weights 0, bias 1;
        # the leaky ReLU keeps it), so the layers after it take their bias as one more weight
        # column: plain products, no bias copied into every output row first.
        firsts = [lyr[0][0] for lyr in layers]
        one = firsts[0].weight.new_ones(1)
        w1 = torch.cat([torch.cat((lin.weight, lin.weight.new_zeros(1, lin.weight.shape[1])))
                        for lin in firsts])  # [H1 + number of networks, message_dim]
        b1 = torch.cat([torch.cat((_bias(lin), one)) for lin in firsts])
        h1 = w1.shape[0]
        chains = [_homogeneous(rest) for rest in rests]
        k = self.message_dim - 2 * BOX_DIM  # inputs shared by the pairs of a view
        w_view = w1[:, :k]
        # A pair's input is ``[box_src, box_dst]``; the backward view reads the boxes swapped,
        # which is the same input against swapped weight columns: one [P, 8] x [8, 2 H1].
        wb = w1[:, k:]  # [H1, 8]: own box, other box
        wb2 = torch.cat((wb, torch.cat((wb[:, BOX_DIM:], wb[:, :BOX_DIM]), dim=1))).t()
        slopes = [lyr[0][1] for lyr in layers]
        shared_act = all(sl == slopes[0] for sl in slopes)
        n_pairs = scatter_count(pair_edge, E)  # [E], the same for both views
        has = n_pairs > 0
        denom = n_pairs.clamp_min(1).to(x.dtype)[:, None]
        w_view_has = has.repeat_interleave(2).to(x.dtype)[:, None]  # [2E, 1]

        def view_inputs(e0: int, e1: int) -> Tensor:
            """First-layer part shared by the pairs of each view of edges ``e0:e1`` (node
            states, pose, hidden state), computed once per view: ``[e1 - e0, 2 * H1]``."""
            feats = [x[own[e0:e1]], x[other[e0:e1]], pose_in[e0:e1]]
            if self.edge_dim:
                assert edge_state is not None
                feats.append(edge_state[e0:e1])
            z = nn.functional.linear(torch.cat(feats, dim=-1), w_view, b1)
            return z.reshape(e1 - e0, 2 * h1)

        def messages(per_view: Tensor, pe: Tensor, bs: Tensor, bd: Tensor) -> list[Tensor]:
            """Per pair, the outputs ``[P, 2 * width]`` of each network (both views; Psi_E
            without its deferred last layer) for pairs of edges ``pe [P]`` (rows of
            ``per_view``) with boxes ``bs, bd [P, 4]``."""
            z = per_view.index_select(0, pe).addmm_(torch.cat((bs, bd), dim=1), wb2)
            z = z.view(-1, h1)  # [2P, H1]: rows 2p (forward view), 2p + 1 (backward view)
            if shared_act:
                z = _leaky(z, slopes[0])
            outs, col = [], 0
            for i, (chain, width) in enumerate(zip(chains, widths, strict=True)):
                # with the constant unit when layers follow (their bias column reads it)
                y = z[:, col:col + width + (1 if chain else 0)]
                col += width + 1
                if not shared_act:
                    y = _leaky(y, slopes[i], inplace=False)
                for weight, slope in chain:
                    y = _leaky(torch.mm(y, weight), slope)
                outs.append(y.reshape(pe.shape[0], 2 * y.shape[1]))
            return outs

        def reduce(sums: list[Tensor], e0: int, e1: int,
                   means: bool = False) -> tuple[Tensor, Tensor | None]:
            """Per-pair sums of edges ``e0:e1`` -> ``Psi_E``'s mean ``[e1 - e0, 2, 7 (+ d)]``
            and the rows each view adds to its own node ``[2 (e1 - e0), out]``. ``means``:
            ``sums`` are already the means over the edges' pairs where the round needs them
            (``Psi_E``'s, and ``Psi_N``'s with ``nested_mean``)."""
            m_edge = sums[0] if means else sums[0] / denom[e0:e1]
            m_edge = m_edge.view(e1 - e0, 2, sums[0].shape[1] // 2)
            if defer:
                lin = edge_layers[-1][0]
                m_edge = nn.functional.linear(m_edge, lin.weight, lin.bias)
            if len(sums) == 1:
                return m_edge, None
            node = sums[1].view(2 * (e1 - e0), sums[1].shape[1] // 2)
            if self.nested_mean and not means:  # the view's mean; views without pairs add 0
                node = node / denom[e0:e1].repeat_interleave(2, dim=0)
            return m_edge, node

        grads = torch.is_grad_enabled() and any(
            t.requires_grad for t in (w1, x, edge_pose, box_src, box_dst))
        if grads or x.device.type != "cpu" or torch.compiler.is_compiling() or \
                M <= 2 * _BLOCK_PAIRS:
            m_edge, node_rows = reduce(
                [scatter_sum_unchecked(y, pair_edge, 0, E) for y in
                 messages(view_inputs(0, E), pair_edge, box_src, box_dst)], 0, E)
            node_total = (None if node_rows is None
                          else scatter_sum_unchecked(node_rows, own_flat, 0, N))
        else:
            m_edge, node_total = self._blocked(
                view_inputs, messages, reduce, pair_edge, box_src, box_dst, n_pairs,
                own_flat, N, len(nets) > 1, self.nested_mean)

        # ---- edge update: fuse the directions of the mean message.
        out = m_edge[..., :POSE_DIM]
        if self.residual:
            one = torch.zeros_like(out)
            one[..., 0] = 1.0
            pred = compose_pose_vec(out + one, pose_view)
        else:
            pred = out
        has3 = has[:, None, None]
        pred = torch.where(has3, pred, pose_view)  # edges without pairs keep their pose
        new_pose = symmetric_pose_mean(pred[:, 0], invert_pose_raw(pred[:, 1]), edge_pose)
        new_state = None
        if update_edge_state:
            assert edge_state is not None
            new_state = torch.where(has3, m_edge[..., POSE_DIM:], edge_state)
        if node_total is None:
            return PoserConvOutput(None, new_pose, new_state)

        # ---- node update: each node hears every neighbour through the view starting at itself.
        if self.nested_mean:  # the mean over the views that have pairs
            count = scatter_sum_unchecked(w_view_has, own_flat, 0, N)
        else:  # the mean over all pair rows
            count = scatter_sum_unchecked(n_pairs.repeat_interleave(2)[:, None].to(x.dtype),
                                          own_flat, 0, N)
        return PoserConvOutput(node_total / count.clamp_min(1.0), new_pose, new_state)

    @staticmethod
    def _blocked(view_inputs: Any, messages: Any, reduce: Any, pair_edge: Tensor,
                 box_src: Tensor, box_dst: Tensor, n_pairs: Tensor, own_flat: Tensor, N: int,
                 nodes: bool, nested_mean: bool) -> tuple[Tensor, Tensor | None]:
        """The messages of :meth:`_propagate_fused` block by block of edges (inference on the
        CPU): each block's pairs (about ``_BLOCK_PAIRS``) run through the networks and are
        reduced while their activations are in the cache, and no tensor of the size of all
        pairs (or of all edge views times the hidden width) is ever allocated; large fresh
        allocations cost page faults that take longer than the arithmetic on them.

        Pairs are visited edge by edge (a stable sort when ``pair_edge`` is not sorted), so
        each block's pairs are contiguous per edge: the means over an edge's pairs are one
        product with the block's ``[edges, pairs]`` CSR matrix of ``1 / n_pairs`` (sparse
        times dense runs each row's terms in order: deterministic; ``Psi_N``'s plain sums
        with ``nested_mean=False``, a second matrix of ones).
        Returns ``Psi_E``'s mean message ``[E, 2, *]`` and the node sums ``[N, out]``.
        """
        E = n_pairs.shape[0]
        if bool((pair_edge[1:] < pair_edge[:-1]).any()):
            order = torch.argsort(pair_edge, stable=True)
            pair_edge, box_src, box_dst = pair_edge[order], box_src[order], box_dst[order]
        ptr = torch.cat((n_pairs.new_zeros(1), torch.cumsum(n_pairs, 0)))  # [E + 1]
        M = int(ptr[-1])
        targets = torch.arange(_BLOCK_PAIRS, M, _BLOCK_PAIRS, device=ptr.device)
        cuts = torch.searchsorted(ptr[1:], targets, right=True)  # edges with all pairs < T
        bounds = torch.unique_consecutive(torch.cat((cuts.new_zeros(1), cuts,
                                                     cuts.new_full((1,), E))))
        edges = bounds.tolist()
        starts = ptr[bounds].tolist()
        cols = torch.arange(M, device=ptr.device)
        dtype = box_src.dtype
        inv = (1.0 / n_pairs.clamp_min(1).to(dtype)).repeat_interleave(n_pairs, output_size=M)
        ones = inv.new_ones(M) if nodes and not nested_mean else None
        m_edge: Tensor | None = None
        total: Tensor | None = None
        for e0, e1, q0, q1 in zip(edges[:-1], edges[1:], starts[:-1], starts[1:], strict=True):
            pe = pair_edge[q0:q1] - e0
            outs = messages(view_inputs(e0, e1), pe, box_src[q0:q1], box_dst[q0:q1])
            crow, col = ptr[e0:e1 + 1] - q0, cols[:q1 - q0]
            sums = [_csr(crow, col, inv[q0:q1], outs[0])]
            if nodes:
                sums.append(_csr(crow, col, inv[q0:q1] if nested_mean else ones[:q1 - q0],
                                 outs[1]))
            m_blk, node_rows = reduce(sums, e0, e1, means=True)
            if m_edge is None:
                m_edge = m_blk.new_empty(E, *m_blk.shape[1:])
            m_edge[e0:e1] = m_blk
            if nodes:
                assert node_rows is not None
                if total is None:
                    total = node_rows.new_zeros(N, node_rows.shape[1])
                total.index_add_(0, own_flat[2 * e0:2 * e1], node_rows)
        assert m_edge is not None
        return m_edge, total


def _csr(crow: Tensor, col: Tensor, values: Tensor, y: Tensor) -> Tensor:
    """``S @ y`` for the CSR matrix ``S [len(crow) - 1, len(col)]`` (row pointers ``crow``,
    columns ``col``, ``values``) and ``y [len(col), C]``."""
    with warnings.catch_warnings():  # "sparse CSR support is in beta": only S @ dense is used
        warnings.simplefilter("ignore", UserWarning)
        S = torch.sparse_csr_tensor(crow, col, values, (crow.shape[0] - 1, col.shape[0]),
                                    check_invariants=False)
    return S @ y


# Pairs per block of the blocked fast path (inference on the CPU): a block's activations
# (``[P, 2, 64]`` floats, 4 MB at 8192 pairs) stay in the cache from one layer to the next.
# Measured on 7000 paper-size graphs, 2 threads (2 MB L2 per core, 36 MB L3): 8192-12288
# pairs 0.90-0.95 s, 4096 1.05-1.10 s (half of the blocks, half of the per-op overhead),
# 2048 1.25 s.
_BLOCK_PAIRS = 8192


def _linear_layers(net: MLP) -> list[tuple[nn.Linear, float | None]]:
    """The linear layers of a built-in MLP, each with the slope of the leaky ReLU after it
    (``None`` when none follows)."""
    out: list[tuple[nn.Linear, float | None]] = []
    for m in net.net:
        if isinstance(m, nn.Linear):
            out.append((m, None))
        else:
            out[-1] = (out[-1][0], float(m.negative_slope))
    return out


def _bias(lin: nn.Linear) -> Tensor:
    return lin.bias if lin.bias is not None else lin.weight.new_zeros(lin.weight.shape[0])


def _homogeneous(chain: list[tuple[nn.Linear, float | None]]) -> list[tuple[Tensor,
                                                                              float | None]]:
    """The layers ``chain`` as plain products on inputs whose last column is 1: each weight
    ``[in + 1, out]`` (transposed, the bias as the last row), and ``[in + 1, out + 1]`` with
    the constant passed on (``e_last``) for every layer but the last; with its slope."""
    out: list[tuple[Tensor, float | None]] = []
    for j, (lin, slope) in enumerate(chain):
        w = torch.cat((lin.weight, _bias(lin)[:, None]), dim=1)  # [out, in + 1]
        if j < len(chain) - 1:  # the next layer reads the constant too
            keep = w.new_zeros(1, w.shape[1])
            keep[0, -1] = 1.0
            w = torch.cat((w, keep))
        out.append((w.t(), slope))
    return out


def _leaky(t: Tensor, slope: float | None, inplace: bool = True) -> Tensor:
    """Leaky ReLU, in place where autograd allows it (a non-negative slope: the backward pass
    then reads the sign from the output). ``slope=None``: no activation."""
    if slope is None:
        return t
    if inplace and slope >= 0:
        return nn.functional.leaky_relu_(t, slope)
    return nn.functional.leaky_relu(t, slope)


def _reset(module: nn.Module) -> None:
    """``reset_parameters()`` of ``module``, or else of each child (recursively)."""
    reset = getattr(module, "reset_parameters", None)
    if callable(reset):
        reset()
        return
    for child in module.children():
        _reset(child)

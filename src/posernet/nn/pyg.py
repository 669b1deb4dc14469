"""PyTorch Geometric interop: :class:`PoserData`, a view graph as a ``torch_geometric`` ``Data``.

PyG's ``Batch.from_data_list`` (and its ``DataLoader``) concatenate graphs and offset index
fields by asking each graph's ``__inc__``; a plain ``Data`` offsets only fields whose name
contains ``index`` (by the number of nodes). A view graph has four more index fields, so a plain
``Data`` with them batches into pairs that point into the wrong graph. :class:`PoserData` keeps
the field names of :class:`posernet.graph.ViewGraph` and offsets each one by the right count:

==============  ==========================  =======================================
field           offset by the number of     as in :meth:`GraphBatch.from_graphs`
==============  ==========================  =======================================
edge_index      nodes                       yes
det_node        nodes                       yes
pair_edge       edges                       yes
pair_src        detections                  yes
pair_dst        detections                  yes
==============  ==========================  =======================================

so a PyG ``Batch`` of them gives :class:`~posernet.nn.PoserNet` / :class:`~posernet.nn.PoserConv`
exactly the inputs of a :class:`~posernet.graph.GraphBatch` of the same graphs. Node features are
stored as ``x`` (PyG's name, so ``data.x`` feeds PyG layers); ``node_attr`` is an alias of it.
Floating-point tensors (features, poses, boxes, ``estimates``) are never offset.

Optional: this module needs ``torch_geometric`` (``pip install torch_geometric``); the rest of
:mod:`posernet.nn` needs torch alone and never imports it.

Example::

    from torch_geometric.data import Batch
    from posernet.nn import PoserNet
    from posernet.nn.pyg import PoserData

    batch = Batch.from_data_list([PoserData.from_view_graph(g) for g in graphs])
    refined = PoserNet()(batch)                   # [E, 7], same as with GraphBatch.from_graphs
"""

from __future__ import annotations

from typing import Any

from torch import Tensor

try:
    from torch_geometric.data import Batch, Data
except ImportError as exc:  # pragma: no cover - exercised only without torch_geometric
    raise ImportError("posernet.nn.pyg needs PyTorch Geometric: pip install torch_geometric "
                      "(the rest of posernet.nn needs torch alone)") from exc

from ..graph import GraphBatch, ViewGraph

__all__ = ["GraphMeta", "PoserData"]

# PoserData field -> what its per-graph offset counts (the table in the module docstring)
_OFFSET_BY = {
    "edge_index": "nodes",
    "det_node": "nodes",
    "pair_edge": "edges",
    "pair_src": "dets",
    "pair_dst": "dets",
}
_REQUIRED = ("K", "image_size", "edge_index", "edge_pose", "det_box", "det_node", "pair_edge",
             "pair_src", "pair_dst")
_OPTIONAL = ("edge_pose_gt", "pose_gt")


class GraphMeta:
    """A graph's plain metadata (``ViewGraph.meta``), kept whole through PyG batching.

    PyG would take a ``dict`` apart key by key (turning numbers into tensors and failing when
    graphs have different keys); this holder is batched as one object per graph, so a
    ``Batch`` has a list of them and ``to_data_list()`` gives each graph its own back.
    """

    __slots__ = ("data",)

    def __init__(self, data: dict[str, Any] | None = None) -> None:
        self.data = dict(data or {})

    def __eq__(self, other: object) -> bool:
        return isinstance(other, GraphMeta) and other.data == self.data

    __hash__ = None  # type: ignore[assignment]  # mutable

    def __repr__(self) -> str:
        return f"GraphMeta({self.data!r})"

    def __getstate__(self) -> dict[str, Any]:
        return {"data": self.data}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.data = state["data"]


class PoserData(Data):
    """One view graph as a PyG ``Data`` whose batching offsets every index field correctly.

    Fields (shapes as in :class:`posernet.graph.ViewGraph`): ``x`` (= ``node_attr``,
    ``[N, 4]``), ``K``, ``image_size``, ``edge_index``, ``edge_pose``, ``det_box``, ``det_node``,
    ``pair_edge``, ``pair_src``, ``pair_dst``, optionally ``edge_pose_gt`` and ``pose_gt``,
    ``estimates`` (dict of ``[E, 7]``) and ``meta`` (:class:`GraphMeta`). PyG batches only
    fields every graph has: batch graphs with the same optional fields and estimate names.

    Build one with :meth:`from_view_graph`; :meth:`to_view_graph` converts back (a ``Batch`` of
    them converts to a :class:`~posernet.graph.GraphBatch`).
    """

    # -- PyG's batching rule
    def __inc__(self, key: str, value: Any, *args: Any, **kwargs: Any) -> Any:
        what = _OFFSET_BY.get(key)
        if what == "nodes":
            return self.num_nodes
        if what == "edges":
            return int(self["edge_index"].shape[-1])
        if what == "dets":
            return int(self["det_box"].shape[0])
        if isinstance(value, Tensor) and value.is_floating_point():
            return 0  # features, poses, boxes and estimates (dict entries come by their name)
        return super().__inc__(key, value, *args, **kwargs)

    # -- ViewGraph's names
    @property
    def node_attr(self) -> Tensor | None:
        """Normalised camera attributes ``[N, 4]``: the same tensor as ``x``."""
        return self.x

    @node_attr.setter
    def node_attr(self, value: Tensor | None) -> None:
        self.x = value

    @property
    def num_dets(self) -> int:
        return int(self["det_box"].shape[0])

    @property
    def num_pairs(self) -> int:
        return int(self["pair_edge"].shape[0])

    @property
    def name(self) -> str:
        """The graph's name (``meta['name']``); a ``Batch`` of several graphs names itself."""
        meta = self._store.get("meta")
        if isinstance(meta, GraphMeta):
            return str(meta.data.get("name", "<unnamed graph>"))
        if isinstance(meta, list):
            return f"batch of {len(meta)} graphs"
        return "<unnamed graph>"

    # -- conversions
    @classmethod
    def from_view_graph(cls, graph: ViewGraph) -> PoserData:
        """The :class:`PoserData` of one :class:`~posernet.graph.ViewGraph` (tensors shared,
        not copied). A ``GraphBatch`` is refused: convert its graphs one by one
        (``[PoserData.from_view_graph(g) for g in batch.to_graphs()]``)."""
        if isinstance(graph, GraphBatch):
            raise TypeError("PoserData.from_view_graph takes one ViewGraph, got a GraphBatch; "
                            "convert its graphs one by one: "
                            "[PoserData.from_view_graph(g) for g in batch.to_graphs()]")
        if not isinstance(graph, ViewGraph):
            raise TypeError(f"PoserData.from_view_graph takes a ViewGraph, "
                            f"got {type(graph).__name__}")
        data = cls(x=graph.node_attr)
        for k in (*_REQUIRED, *_OPTIONAL):
            value = getattr(graph, k)
            if value is not None:
                data[k] = value
        data.estimates = dict(graph.estimates)
        data.meta = GraphMeta(graph.meta)
        return data

    def to_view_graph(self) -> ViewGraph:
        """Back to a :class:`~posernet.graph.ViewGraph`; on a PyG ``Batch`` of
        :class:`PoserData`, the :class:`~posernet.graph.GraphBatch` of its graphs."""
        if isinstance(self, Batch):
            return GraphBatch.from_graphs([d.to_view_graph() for d in self.to_data_list()])
        missing = [k for k in ("x", *_REQUIRED) if k not in self._store]
        if missing:
            raise ValueError(f"{type(self).__name__} {self.name!r} has no field(s) {missing}")
        fields: dict[str, Any] = {"node_attr": self.x}
        fields.update({k: self[k] for k in _REQUIRED})
        fields.update({k: self[k] for k in _OPTIONAL if k in self._store})
        fields["estimates"] = dict(self._store.get("estimates") or {})
        meta = self._store.get("meta")
        fields["meta"] = dict(meta.data) if isinstance(meta, GraphMeta) else {}
        return ViewGraph(**fields)

    def validate_graph(self) -> PoserData:
        """Check the view-graph data contract (:meth:`ViewGraph.validate`); returns ``self``.

        (PyG's own :meth:`validate` checks only its generic fields.)
        """
        self.to_view_graph().validate(where=f"PoserData {self.name!r}")
        return self


"""View graphs: the contract between the data front end, PoserNet and motion averaging.

A :class:`ViewGraph` is one graph of images (nodes), image pairs with a relative pose (edges,
each unordered pair stored once as ``i -> j``), object detections, and matched detection pairs
on edges (the paper's "layers"). A :class:`GraphBatch` concatenates graphs PyG-style into one
disconnected graph, offsetting every index field, and can be split back exactly.

Field table:

==============  ==========  ===============================================================
field           shape       meaning
==============  ==========  ===============================================================
node_attr       [N, 4]      normalised width, height, focal, k1 (:func:`node_attributes`)
K               [N, 3, 3]   intrinsics
image_size      [N, 2]      (W, H) in pixels
edge_index      [2, E]      source i, target j (long)
edge_pose       [E, 7]      initial relative pose i -> j, ``[q, t]`` with unit t
edge_pose_gt    [E, 7]      ground-truth relative pose, metric t (optional)
det_box         [D, 4]      normalised (cx, cy, w, h) (:func:`normalize_boxes`)
det_node        [D]         image of each detection (long)
pair_edge       [M]         edge of each matched detection pair (long)
pair_src        [M]         its detection in the source image (long)
pair_dst        [M]         its detection in the target image (long)
pose_gt         [N, 4, 4]   absolute world-to-camera ground truth (optional)
estimates       {name: [E, 7]}  further initial estimates (e.g. ``kp`` and ``bb``)
meta            dict        plain scalars: ``name``, ``scene``, ``split`` ...
==============  ==========  ===============================================================
"""

from __future__ import annotations

import dataclasses
import io
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from .io import atomic_path

__all__ = [
    "GraphBatch",
    "GraphValidationError",
    "ViewGraph",
    "check_edge_index",
    "denormalize_boxes",
    "load_graphs",
    "node_attributes",
    "normalize_boxes",
    "save_graphs",
]

# Reference values for the node attributes (Kinect-like camera of 7-Scenes).
REF_WIDTH, REF_HEIGHT, REF_FOCAL, REF_K1 = 640.0, 480.0, 585.0, 0.1

# Which fields are indexed by which entity; used for batching, splitting and validation.
NODE_FIELDS = ("node_attr", "K", "image_size", "pose_gt")
EDGE_FIELDS = ("edge_pose", "edge_pose_gt")
DET_FIELDS = ("det_box", "det_node")
PAIR_FIELDS = ("pair_edge", "pair_src", "pair_dst")
# Index fields and the entity whose count offsets them when graphs are concatenated.
INDEX_OFFSETS = {
    "edge_index": "node",
    "det_node": "node",
    "pair_edge": "edge",
    "pair_src": "det",
    "pair_dst": "det",
}
TENSOR_FIELDS = ("edge_index", *NODE_FIELDS, *EDGE_FIELDS, *DET_FIELDS, *PAIR_FIELDS)
OPTIONAL_FIELDS = ("edge_pose_gt", "pose_gt")

FORMAT_NAME = "posernet-graphs"
FORMAT_VERSION = 1


class GraphValidationError(ValueError):
    """A view graph (or a file of them) breaks the data contract; the message names the field."""


# --------------------------------------------------------------------------- index checks


def check_edge_index(
    edge_index: Any,
    num_nodes: int | None = None,
    *,
    name: str = "edge_index",
    others: Sequence[tuple[str, Tensor, int, str]] = (),
) -> None:
    """The one check of an ``edge_index`` (the graph contract, ``PoserConv``'s inputs and the
    motion-averaging backends all use it); raises ``ValueError`` naming the tensor, which
    callers prefix with where it came from.

    ``edge_index`` must be a ``[2, E]`` tensor; with ``num_nodes`` given also ``torch.long``
    with values in ``[0, num_nodes)`` and no self loop (``source == target``). Every
    ``(name, tensor, size, what)`` of ``others`` (e.g. ``("pair_edge", pair_edge, E,
    "edges")``) must be ``torch.long`` with values in ``[0, size)``, checked together with it.

    One host synchronisation for all range and self-loop tests (each ``int()`` / ``bool()`` of a
    CUDA tensor waits for the device): the flags are reduced on the device and read once, and
    the detailed message is worked out only when something is wrong.
    """
    if not isinstance(edge_index, Tensor) or edge_index.ndim != 2 or edge_index.shape[0] != 2:
        shape = (tuple(edge_index.shape) if isinstance(edge_index, Tensor)
                 else type(edge_index).__name__)
        raise ValueError(f"{name} must have shape [2, E], got {shape}")
    if num_nodes is None:
        return
    ranged = ((name, edge_index, num_nodes, "nodes"), *others)
    for key, t, _, _ in ranged:
        if t.dtype != torch.long:
            raise ValueError(f"{key} must be torch.long, got {t.dtype}")
    flags = [((t < 0) | (t >= size)).any() for _, t, size, _ in ranged if t.numel()]
    if edge_index.shape[1]:
        flags.append((edge_index[0] == edge_index[1]).any())
    if flags and torch.compiler.is_compiling():
        # Inside torch.compile reading the flag would break the graph (a host sync): assert
        # inside the graph instead; the detailed message needs an eager call.
        names = ", ".join(key for key, *_ in ranged)
        torch._assert_async(~torch.stack(flags).any(),
                            f"{names}: an index is out of range or {name} has a self loop "
                            "(found inside torch.compile; call eagerly for the details)")
        return
    if not flags or not bool(torch.stack(flags).any()):
        return
    for key, t, size, what in ranged:
        if t.numel() and (int(t.min()) < 0 or int(t.max()) >= size):
            raise ValueError(f"index field '{key}' out of range: {key} values must lie in "
                             f"[0, {size}) ({size} {what}), got [{int(t.min())}, {int(t.max())}]")
    e = int((edge_index[0] == edge_index[1]).nonzero()[0, 0])
    raise ValueError(f"{name} has a self loop: edge {e} on node {int(edge_index[0, e])} "
                     "(source == target)")


# --------------------------------------------------------------------------- normalisation


def normalize_boxes(boxes_xyxy: Tensor, image_size: Tensor) -> Tensor:
    """Pixel boxes ``(x1, y1, x2, y2)`` -> ``(cx, cy, w, h)`` normalised to the image.

    ``cx, cy`` in [-1, 1] relative to the image centre, ``w, h`` as fractions of the image size.
    Shapes: ``boxes (*, 4)``, ``image_size (*, 2)`` as (W, H) -> ``(*, 4)``.
    """
    W, H = image_size[..., 0], image_size[..., 1]
    x1, y1, x2, y2 = boxes_xyxy.unbind(-1)
    return torch.stack(
        ((x1 + x2) / W - 1.0, (y1 + y2) / H - 1.0, (x2 - x1) / W, (y2 - y1) / H), dim=-1
    )


def denormalize_boxes(boxes: Tensor, image_size: Tensor) -> Tensor:
    """Inverse of :func:`normalize_boxes`: ``(cx, cy, w, h)`` -> pixel ``(x1, y1, x2, y2)``."""
    W, H = image_size[..., 0], image_size[..., 1]
    cx, cy, w, h = boxes.unbind(-1)
    px, py = (cx + 1.0) * W / 2, (cy + 1.0) * H / 2
    pw, ph = w * W, h * H
    return torch.stack((px - pw / 2, py - ph / 2, px + pw / 2, py + ph / 2), dim=-1)


def node_attributes(K: Tensor, image_size: Tensor, k1: Tensor | float = 0.0) -> Tensor:
    """Normalised node input ``[W/640 - 1, H/480 - 1, f/585 - 1, k1/0.1]``.

    Shapes: ``K (N, 3, 3)``, ``image_size (N, 2)``, ``k1`` scalar or ``(N,)`` -> ``(N, 4)``.
    The focal length is the mean of ``fx`` and ``fy``.
    """
    f = 0.5 * (K[:, 0, 0] + K[:, 1, 1])
    k1 = torch.as_tensor(k1, dtype=K.dtype, device=K.device).expand(K.shape[0])
    return torch.stack(
        (
            image_size[:, 0].to(K.dtype) / REF_WIDTH - 1.0,
            image_size[:, 1].to(K.dtype) / REF_HEIGHT - 1.0,
            f / REF_FOCAL - 1.0,
            k1 / REF_K1,
        ),
        dim=-1,
    )


# --------------------------------------------------------------------------- the graph


@dataclass
class ViewGraph:
    """One view graph; see the module docstring for the field table."""

    node_attr: Tensor
    K: Tensor
    image_size: Tensor
    edge_index: Tensor
    edge_pose: Tensor
    det_box: Tensor
    det_node: Tensor
    pair_edge: Tensor
    pair_src: Tensor
    pair_dst: Tensor
    edge_pose_gt: Tensor | None = None
    pose_gt: Tensor | None = None
    estimates: dict[str, Tensor] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    # -- sizes
    @property
    def num_nodes(self) -> int:
        return int(self.node_attr.shape[0])

    @property
    def num_edges(self) -> int:
        return int(self.edge_index.shape[1])

    @property
    def num_dets(self) -> int:
        return int(self.det_box.shape[0])

    @property
    def num_pairs(self) -> int:
        return int(self.pair_edge.shape[0])

    @property
    def device(self) -> torch.device:
        return self.edge_pose.device

    @property
    def name(self) -> str:
        return str(self.meta.get("name", "<unnamed graph>"))

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(name={self.name!r}, nodes={self.num_nodes}, "
            f"edges={self.num_edges}, dets={self.num_dets}, pairs={self.num_pairs})"
        )

    # -- conversions
    def _tensor_items(self) -> dict[str, Tensor]:
        out = {k: getattr(self, k) for k in TENSOR_FIELDS if getattr(self, k) is not None}
        return out

    def apply(self, fn) -> ViewGraph:
        """Copy with ``fn`` applied to every tensor (fields and estimates)."""
        changes: dict[str, Any] = {k: fn(v) for k, v in self._tensor_items().items()}
        changes["estimates"] = {k: fn(v) for k, v in self.estimates.items()}
        changes["meta"] = dict(self.meta)
        return dataclasses.replace(self, **changes)

    def to(self, device: torch.device | str) -> ViewGraph:
        """Copy on ``device``."""
        return self.apply(lambda t: t.to(device))

    def with_estimate(self, name: str) -> ViewGraph:
        """Copy whose ``edge_pose`` is the named entry of ``estimates`` (e.g. ``kp``, ``bb``)."""
        if name not in self.estimates:
            raise KeyError(
                f"graph {self.name!r} has no initial estimate {name!r}; "
                f"available: {sorted(self.estimates)}"
            )
        return dataclasses.replace(self, edge_pose=self.estimates[name])

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of tensors and scalars (what :func:`save_graphs` stores)."""
        d: dict[str, Any] = dict(self._tensor_items())
        d["estimates"] = dict(self.estimates)
        d["meta"] = dict(self.meta)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ViewGraph:
        names = {f.name for f in dataclasses.fields(ViewGraph)}
        unknown = set(d) - names
        if unknown:
            raise GraphValidationError(f"unknown graph fields: {sorted(unknown)}")
        return ViewGraph(**d)

    # -- validation
    def validate(self, where: str | None = None) -> ViewGraph:
        """Check the data contract; raise :class:`GraphValidationError` naming graph and field.

        Checks shapes, dtypes, index ranges, that each matched pair's detections lie in its
        edge's two images, finite values, non-zero quaternions, no self loops and no pair of
        images stored twice. Returns ``self`` so calls can be chained.
        """
        label = where or f"graph {self.name!r}"

        def fail(msg: str) -> None:
            raise GraphValidationError(f"{label}: {msg}")

        for k in TENSOR_FIELDS:
            v = getattr(self, k)
            if v is None:
                if k not in OPTIONAL_FIELDS:
                    fail(f"field {k!r} is missing")
                continue
            if not isinstance(v, Tensor):
                fail(f"field {k!r} must be a torch.Tensor, got {type(v).__name__}")
        N, E = self.num_nodes, int(self.edge_index.shape[-1]) if self.edge_index.ndim else -1
        D, M = self.num_dets, self.num_pairs
        expected = {
            "node_attr": (N, 4), "K": (N, 3, 3), "image_size": (N, 2), "pose_gt": (N, 4, 4),
            "edge_index": (2, E), "edge_pose": (E, 7), "edge_pose_gt": (E, 7),
            "det_box": (D, 4), "det_node": (D,),
            "pair_edge": (M,), "pair_src": (M,), "pair_dst": (M,),
        }  # fmt: skip
        for k, shape in expected.items():
            v = getattr(self, k)
            if v is not None and tuple(v.shape) != shape:
                fail(f"field {k!r} has shape {tuple(v.shape)}, expected {shape}")
        for k, v in self.estimates.items():
            if not isinstance(v, Tensor) or tuple(v.shape) != (E, 7):
                shape = tuple(v.shape) if isinstance(v, Tensor) else type(v).__name__
                fail(f"estimate {k!r} has shape {shape}, expected {(E, 7)}")
        try:  # dtypes and ranges of every index field, no self loop
            check_edge_index(self.edge_index, N, others=(
                ("det_node", self.det_node, N, "nodes"), ("pair_edge", self.pair_edge, E, "edges"),
                ("pair_src", self.pair_src, D, "detections"),
                ("pair_dst", self.pair_dst, D, "detections")))
        except ValueError as exc:
            fail(str(exc))
        for k in ("node_attr", "K", "image_size", "pose_gt", "edge_pose", "edge_pose_gt",
                  "det_box"):
            v = getattr(self, k)
            if v is not None and not v.is_floating_point():
                fail(f"field {k!r} must be floating point, got {v.dtype}")
            if v is not None and not bool(torch.isfinite(v).all()):
                bad = (~torch.isfinite(v)).reshape(v.shape[0], -1).any(-1).nonzero()[0, 0]
                fail(f"field {k!r} has a NaN/inf value (row {int(bad)})")
        for k, v in self.estimates.items():
            if not bool(torch.isfinite(v).all()):
                fail(f"estimate {k!r} has a NaN/inf value")

        src, dst = self.edge_index
        if E > 1:
            key = torch.minimum(src, dst) * max(N, 1) + torch.maximum(src, dst)
            if torch.unique(key).numel() != E:
                fail("an image pair is stored more than once in 'edge_index' "
                     "(store each unordered pair once; the reverse is derived)")
        for k, v in [("edge_pose", self.edge_pose), ("edge_pose_gt", self.edge_pose_gt),
                     *self.estimates.items()]:
            if v is not None and E and bool((v[:, :4].norm(dim=-1) < 1e-8).any()):
                e = int((v[:, :4].norm(dim=-1) < 1e-8).nonzero()[0, 0])
                fail(f"{k!r} of edge {e} has a zero quaternion")
        if M:
            if bool((self.det_node[self.pair_src] != src[self.pair_edge]).any()):
                m = int((self.det_node[self.pair_src] != src[self.pair_edge]).nonzero()[0, 0])
                fail(f"matched pair {m}: detection {int(self.pair_src[m])} ('pair_src') is not in "
                     f"the source image {int(src[self.pair_edge[m]])} of edge "
                     f"{int(self.pair_edge[m])}")
            if bool((self.det_node[self.pair_dst] != dst[self.pair_edge]).any()):
                m = int((self.det_node[self.pair_dst] != dst[self.pair_edge]).nonzero()[0, 0])
                fail(f"matched pair {m}: detection {int(self.pair_dst[m])} ('pair_dst') is not in "
                     f"the target image {int(dst[self.pair_edge[m]])} of edge "
                     f"{int(self.pair_edge[m])}")
        return self


# --------------------------------------------------------------------------- batching


@dataclass(repr=False)
class GraphBatch(ViewGraph):
    """Several :class:`ViewGraph` concatenated into one disconnected graph.

    ``node_batch [N]``, ``edge_batch [E]``, ``det_batch [D]``, ``pair_batch [M]`` give the graph
    of every entity; ``ptr``, ``edge_ptr``, ``det_ptr``, ``pair_ptr`` (length ``B + 1``, starting
    at 0) its slice. ``metas`` keeps each graph's ``meta``.
    """

    node_batch: Tensor | None = None
    edge_batch: Tensor | None = None
    det_batch: Tensor | None = None
    pair_batch: Tensor | None = None
    ptr: Tensor | None = None
    edge_ptr: Tensor | None = None
    det_ptr: Tensor | None = None
    pair_ptr: Tensor | None = None
    metas: list[dict[str, Any]] = field(default_factory=list)

    @property
    def num_graphs(self) -> int:
        return int(self.ptr.numel() - 1)

    def __repr__(self) -> str:
        return (
            f"GraphBatch(graphs={self.num_graphs}, nodes={self.num_nodes}, "
            f"edges={self.num_edges}, dets={self.num_dets}, pairs={self.num_pairs})"
        )

    def _tensor_items(self) -> dict[str, Tensor]:
        out = super()._tensor_items()
        for k in ("node_batch", "edge_batch", "det_batch", "pair_batch",
                  "ptr", "edge_ptr", "det_ptr", "pair_ptr"):
            out[k] = getattr(self, k)
        return out

    def apply(self, fn) -> GraphBatch:
        out = super().apply(fn)
        out.metas = [dict(m) for m in self.metas]
        return out

    @classmethod
    def from_graphs(cls, graphs: Sequence[ViewGraph]) -> GraphBatch:
        """Concatenate graphs, offsetting ``edge_index``, ``det_node``, ``pair_*`` indices.

        Optional fields and estimates are kept only when every graph has them.
        """
        graphs = list(graphs)
        if not graphs:
            raise GraphValidationError("cannot batch an empty list of graphs")
        device = graphs[0].device
        counts = {
            "node": torch.tensor([g.num_nodes for g in graphs]),
            "edge": torch.tensor([g.num_edges for g in graphs]),
            "det": torch.tensor([g.num_dets for g in graphs]),
            "pair": torch.tensor([g.num_pairs for g in graphs]),
        }
        ptrs = {k: torch.cat((c.new_zeros(1), c.cumsum(0))) for k, c in counts.items()}
        out: dict[str, Any] = {}
        for k in TENSOR_FIELDS:
            vals = [getattr(g, k) for g in graphs]
            if any(v is None for v in vals):
                out[k] = None
                continue
            dim = 1 if k == "edge_index" else 0
            cat = torch.cat(vals, dim=dim)
            if k in INDEX_OFFSETS:
                ent = INDEX_OFFSETS[k]
                sizes = counts[{"edge_index": "edge", "det_node": "det"}.get(k, "pair")]
                off = ptrs[ent][:-1].repeat_interleave(sizes).to(device)
                cat = cat + off
            out[k] = cat
        common = set.intersection(*(set(g.estimates) for g in graphs))
        out["estimates"] = {k: torch.cat([g.estimates[k] for g in graphs]) for k in sorted(common)}
        out["meta"] = {"name": f"batch of {len(graphs)} graphs"}
        ids = torch.arange(len(graphs))
        for ent, name in (("node", "node_batch"), ("edge", "edge_batch"), ("det", "det_batch"),
                          ("pair", "pair_batch")):
            out[name] = ids.repeat_interleave(counts[ent]).to(device)
        out["ptr"] = ptrs["node"].to(device)
        out["edge_ptr"] = ptrs["edge"].to(device)
        out["det_ptr"] = ptrs["det"].to(device)
        out["pair_ptr"] = ptrs["pair"].to(device)
        out["metas"] = [dict(g.meta) for g in graphs]
        return cls(**out)

    def to_graphs(self) -> list[ViewGraph]:
        """Split back into the original graphs (indices made local again)."""
        ptrs = {
            "node": self.ptr.cpu(),
            "edge": self.edge_ptr.cpu(),
            "det": self.det_ptr.cpu(),
            "pair": self.pair_ptr.cpu(),
        }
        entity_of = {k: "node" for k in NODE_FIELDS}
        entity_of.update({k: "edge" for k in EDGE_FIELDS})
        entity_of.update({k: "det" for k in DET_FIELDS})
        entity_of.update({k: "pair" for k in PAIR_FIELDS})
        entity_of["edge_index"] = "edge"
        sizes = {k: torch.diff(p).tolist() for k, p in ptrs.items()}

        def split(t: Tensor, ent: str, dim: int = 0) -> list[Tensor]:
            return list(torch.split(t, sizes[ent], dim=dim))

        parts: dict[str, list[Tensor] | None] = {}
        for k in TENSOR_FIELDS:
            v = getattr(self, k)
            if v is None:
                parts[k] = None
                continue
            ent = entity_of[k]
            pieces = split(v, ent, dim=1 if k == "edge_index" else 0)
            if k in INDEX_OFFSETS:
                base = ptrs[INDEX_OFFSETS[k]][:-1].tolist()
                pieces = [p - b for p, b in zip(pieces, base, strict=True)]
            parts[k] = pieces
        est_parts = {k: split(v, "edge") for k, v in self.estimates.items()}
        graphs = []
        for b in range(self.num_graphs):
            kw: dict[str, Any] = {k: (None if p is None else p[b]) for k, p in parts.items()}
            kw["estimates"] = {k: p[b] for k, p in est_parts.items()}
            kw["meta"] = dict(self.metas[b]) if b < len(self.metas) else {}
            graphs.append(ViewGraph(**kw))
        return graphs


# --------------------------------------------------------------------------- storage


def _canonical(obj: Any) -> Any:
    """A copy of plain metadata whose pickle depends on its values only.

    Pickle writes an object once and refers back to it when the same object recurs, so equal
    strings that happen to be one object (or not) give different bytes. Interning strings and
    rebuilding containers makes graphs made in another process save to the same bytes.
    """
    if isinstance(obj, str):
        return sys.intern(str(obj))
    if isinstance(obj, dict):
        return {_canonical(k): _canonical(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_canonical(v) for v in obj]
    if isinstance(obj, tuple):
        return tuple(_canonical(v) for v in obj)
    return obj


def save_graphs(path: str | os.PathLike[str], graphs: Sequence[ViewGraph],
                extra: dict[str, Any] | None = None) -> Path:
    """Write graphs to one ``.pt`` file atomically (temp file + rename).

    Every graph is checked first with :meth:`ViewGraph.validate` (the check :func:`load_graphs`
    applies): a graph with a NaN value, a bad index or a wrong shape raises
    :class:`GraphValidationError` naming the file, the graph and the field, and nothing is
    written. The graphs are stored concatenated (a handful of large tensors, fast to load)
    together with their metadata. ``extra`` holds plain scalars/strings/lists saved beside
    them. The file loads with ``torch.load(weights_only=True)``: no pickled code runs on load.
    """
    graphs = list(graphs)
    if not graphs:
        raise GraphValidationError(f"{path}: refusing to write an empty graph file")
    for i, g in enumerate(graphs):  # what load_graphs would refuse is never written
        g.validate(where=f"{path}: graph {i} ({g.name!r})")
    batch = GraphBatch.from_graphs([g.to("cpu") for g in graphs])
    payload = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "tensors": {k: v for k, v in batch._tensor_items().items() if v is not None},
        "estimates": batch.estimates,
        "metas": _canonical(batch.metas),
        "extra": _canonical(dict(extra or {})),
    }
    buf = io.BytesIO()
    torch.save(payload, buf)  # a buffer keeps the archive name fixed: same graphs => same bytes
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.getvalue())
    return Path(path)


def load_graphs(path: str | os.PathLike[str], validate: bool = True) -> list[ViewGraph]:
    """Read graphs written by :func:`save_graphs`; errors name the file and the graph."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"graph file not found: {path}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt or foreign files
        raise GraphValidationError(f"{path}: not a readable posernet graph file ({exc})") from exc
    if not isinstance(payload, dict) or payload.get("format") != FORMAT_NAME:
        raise GraphValidationError(f"{path}: not a posernet graph file (missing format tag)")
    if payload.get("version") != FORMAT_VERSION:
        raise GraphValidationError(
            f"{path}: graph file version {payload.get('version')} is not supported "
            f"(this posernet reads version {FORMAT_VERSION})"
        )
    try:
        batch = GraphBatch(**payload["tensors"], estimates=payload["estimates"],
                           metas=payload["metas"])
        graphs = batch.to_graphs()
    except (TypeError, KeyError, RuntimeError, ValueError) as exc:
        raise GraphValidationError(f"{path}: malformed graph file ({exc})") from exc
    if validate:
        for i, g in enumerate(graphs):
            g.validate(where=f"{path}: graph {i} ({g.name!r})")
    return graphs

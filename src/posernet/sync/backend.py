"""The motion-averaging interface: :class:`SyncBackend` with its options and
:class:`SyncResult`, the input checks, and the translation-scale policy.

A backend turns relative poses on the edges of one or many view graphs into absolute
world-to-camera poses:

* edge ``e = (i -> j)`` carries ``P_e = M_j M_i^{-1}`` as ``[qw, qx, qy, qz, tx, ty, tz]``
  (it maps camera-i points to camera j: ``R_ij = R_j R_i^T``, ``t_ij = t_j - R_ij t_i``);
* the result is ``M_i = [[R_i, t_i], [0, 1]]`` for every node, ``x_cam = R_i X + t_i``.

**Components.** Every backend solves each connected component of each graph on its own (its
own gauge; :mod:`posernet.sync.components`). Nodes without any edge cannot be placed: they get
the identity pose and ``SyncResult.solved`` is ``False`` for them, so evaluation can leave them
out explicitly. With ``disconnected="error"`` a graph that is not connected raises a
``ValueError`` instead.

**Scale policy** (``scale=`` option, recorded in ``describe()``): the relative translations
fed to a metric solver are

* ``"unit"``: rescaled to unit norm (what 5-point / PoserNet directions are);
* ``"given"``: used as they are (they are metric, e.g. ground truth or a metric estimator);
* ``"oracle"``: rescaled to the ground-truth norms of ``edge_pose_gt`` -- a benchmark-only
  oracle, labelled as such everywhere;
* ``"free"``: no scale at all; translations are averaged from directions (scale-free, only
  meaningful after a similarity alignment).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

import torch
from torch import Tensor

from ..graph import GraphBatch, ViewGraph, check_edge_index
from ..options import check_options, option
from ..scatter import scatter_count
from .components import Components, connected_components

__all__ = [
    "DISCONNECTED_POLICIES",
    "SCALE_POLICIES",
    "SyncBackend",
    "SyncOptions",
    "SyncResult",
    "apply_scale_policy",
    "as_mapping",
    "check_edge_weight",
    "check_positive",
    "graph_structure",
    "scale_option",
    "validate_sync_input",
]

SCALE_POLICIES: tuple[str, ...] = ("unit", "given", "oracle", "free")
DISCONNECTED_POLICIES: tuple[str, ...] = ("components", "error")


# --------------------------------------------------------------------------- results


@dataclass
class SyncResult:
    """What a backend returns besides the poses.

    ``poses [N, 4, 4]`` world-to-camera (input dtype and device); ``component [N]`` a global
    component id (components of different graphs never share an id); ``solved [N]`` False for
    nodes with no edge (identity pose, not localised); ``edge_weight [E]`` final robust weights
    (1 where the backend is not robust); ``iterations [B]`` / ``converged [B]`` per graph;
    ``scale`` the translation-scale policy used; ``metric`` whether translations are in the
    input's metric units (``False`` means only a similarity alignment is meaningful).
    """

    poses: Tensor
    component: Tensor
    solved: Tensor
    edge_weight: Tensor
    iterations: Tensor
    converged: Tensor
    scale: str
    metric: bool
    backend: str
    info: dict[str, Any] = field(default_factory=dict)


def scale_option(default: str) -> Any:
    """The ``scale`` field of a backend's options, with that backend's default (the policies
    it supports are its ``scales``)."""
    return option(default, choices=SCALE_POLICIES,
                  help="relative-translation scale fed to the solver: unit (rescaled to unit "
                       "norm), given (as they are, metric), oracle (ground-truth norms; "
                       "benchmark only), free (scale-free, from directions)")


@dataclass(frozen=True)
class SyncOptions:
    """Options shared by every backend; subclasses add their own fields."""

    scale: str = scale_option("unit")
    disconnected: str = option("components", choices=DISCONNECTED_POLICIES,
                               help="components: solve each on its own; error: stop")

    def check(self) -> None:
        """Every field against its rule (:func:`posernet.options.check_options`); subclasses
        add their checks across fields after ``super().check()``."""
        check_options(self)


class SyncBackend(ABC):
    """One motion-averaging method. Subclasses set ``name`` and ``Options`` and implement
    :meth:`_solve`. Construct through :func:`posernet.sync.get_backend`."""

    name: ClassVar[str] = "abstract"
    Options: ClassVar[type[SyncOptions]] = SyncOptions
    #: scale policies this backend accepts
    scales: ClassVar[tuple[str, ...]] = SCALE_POLICIES

    def __init__(self, **options: Any) -> None:
        valid = {f.name for f in fields(self.Options)}
        unknown = sorted(set(options) - valid)
        if unknown:
            raise ValueError(f"unknown option(s) {unknown} for sync backend {self.name!r}; "
                             f"valid options: {sorted(valid)}")
        try:
            self.options = self.Options(**options)
        except TypeError as exc:  # pragma: no cover - guarded by the check above
            raise ValueError(f"bad options for sync backend {self.name!r}: {exc}") from exc
        self.options.check()
        if self.options.scale not in self.scales:
            raise ValueError(
                f"scale={self.options.scale!r} is not supported by sync backend {self.name!r} "
                f"(supported: {list(self.scales)})"
                + ("; scale-free averaging from directions is the 'rotation_translation' "
                   "backend" if self.options.scale == "free" else "")
            )

    # -- public API
    @property
    def scale(self) -> str:
        return self.options.scale

    @property
    def metric(self) -> bool:
        """True when the output translations carry the input's metric scale."""
        return self.options.scale in ("given", "oracle")

    def describe(self) -> dict[str, Any]:
        """Name, options and scale label for tables (``oracle`` is spelled out)."""
        d: dict[str, Any] = {"backend": self.name}
        d.update({f.name: getattr(self.options, f.name) for f in fields(self.options)})
        d["scale_label"] = {
            "unit": "unit-norm relative translations",
            "given": "relative translations as given",
            "oracle": "ORACLE ground-truth translation norms (benchmark only)",
            "free": "scale-free (translation averaging from directions)",
        }[self.options.scale]
        return d

    def __repr__(self) -> str:
        opts = ", ".join(f"{f.name}={getattr(self.options, f.name)!r}"
                         for f in fields(self.options))
        return f"{type(self).__name__}({opts})"

    def solve(self, batch: GraphBatch | ViewGraph, edge_pose: Tensor | None = None,
              edge_weight: Tensor | None = None) -> Tensor:
        """Absolute world-to-camera poses ``[N, 4, 4]`` from relative poses ``edge_pose [E, 7]``
        on the stored edges of ``batch`` (``batch.edge_pose`` when omitted).

        ``edge_weight [E]`` or ``[E, 2]`` (rotation, translation): optional positive per-edge
        confidence (e.g. PoserNet's error head) the robust solve starts from
        (:mod:`posernet.sync.weighted`); backends without support ignore it."""
        return self.solve_with_info(batch, edge_pose, edge_weight).poses

    def solve_with_info(self, batch: GraphBatch | ViewGraph,
                        edge_pose: Tensor | None = None,
                        edge_weight: Tensor | None = None) -> SyncResult:
        """Like :meth:`solve` but returns the full :class:`SyncResult`."""
        if edge_pose is None:
            edge_pose = getattr(batch, "edge_pose", None)
        struct = graph_structure(batch)
        validate_sync_input(struct, edge_pose)
        if edge_weight is not None:
            struct["edge_weight"] = check_edge_weight(edge_weight, struct["edge_index"].shape[1])
        gt = getattr(batch, "edge_pose_gt", None) if self.options.scale == "oracle" else None
        comps = connected_components(struct["edge_index"], struct["num_nodes"],
                                     struct["node_batch"], struct["num_graphs"])
        if self.options.disconnected == "error":
            bad = (comps.graph_num_components > 1).nonzero()
            if bad.numel():
                g = int(bad[0, 0])
                raise ValueError(
                    f"graph {g} ({struct['names'][g]!r}) is not connected: it has "
                    f"{int(comps.graph_num_components[g])} connected components (isolated "
                    "nodes count); set disconnected='components' to solve each one on its own"
                )
        t_dtype = edge_pose.dtype
        result = self._solve(struct, edge_pose.to(torch.float64), gt, comps)
        result.poses = result.poses.to(t_dtype)
        return result

    @abstractmethod
    def _solve(self, struct: dict[str, Any], edge_pose: Tensor, edge_pose_gt: Tensor | None,
               comps: Components) -> SyncResult:
        """Backend-specific work; ``edge_pose`` is float64 and already validated."""


# --------------------------------------------------------------------------- validation


def graph_structure(batch: GraphBatch | ViewGraph) -> dict[str, Any]:
    """Topology of a batch (or one graph) as plain tensors: ``edge_index [2, E]``,
    ``num_nodes``, ``node_batch [N]``, ``edge_batch [E]``, ``num_graphs``, ``names``."""
    if not isinstance(batch, ViewGraph):
        raise ValueError(f"batch must be a GraphBatch or ViewGraph, got {type(batch).__name__}")
    ei = batch.edge_index
    check_edge_index(ei, name="batch.edge_index")  # the shape; the values: validate_sync_input
    n = batch.num_nodes
    dev = ei.device
    if isinstance(batch, GraphBatch) and batch.ptr is not None:
        node_batch = batch.node_batch
        edge_batch = batch.edge_batch
        num_graphs = batch.num_graphs
        names = [str(m.get("name", f"graph {i}")) for i, m in enumerate(batch.metas)]
        if len(names) != num_graphs:
            names = [f"graph {i}" for i in range(num_graphs)]
    else:
        node_batch = torch.zeros(n, dtype=torch.long, device=dev)
        edge_batch = torch.zeros(ei.shape[1], dtype=torch.long, device=dev)
        num_graphs = 1
        names = [batch.name]
    return {"edge_index": ei.long(), "num_nodes": n, "node_batch": node_batch,
            "edge_batch": edge_batch, "num_graphs": num_graphs, "names": names}


def check_edge_weight(edge_weight: Tensor, num_edges: int) -> Tensor:
    """Validate per-edge weights ``[E]`` or ``[E, 2]`` (rotation, translation) and return them
    as ``[E, 2]`` float64; raises ``ValueError`` naming ``edge_weight``."""
    if not isinstance(edge_weight, Tensor):
        raise ValueError(f"edge_weight must be a tensor, got {type(edge_weight).__name__}")
    w = edge_weight.detach().to(torch.float64)
    if w.ndim == 1:
        w = w[:, None].expand(-1, 2)
    if w.ndim != 2 or w.shape != (num_edges, 2):
        raise ValueError(f"edge_weight must be [E] or [E, 2] with E = {num_edges}, got "
                         f"{tuple(edge_weight.shape)}")
    if not bool(torch.isfinite(w).all()):
        raise ValueError("edge_weight must be finite on every edge")
    if bool((w[:, 0] <= 0).any()):
        raise ValueError("edge_weight: the rotation weight (column 0, or the only column) must "
                         "be > 0 on every edge; a translation weight (column 1 of an [E, 2] "
                         "tensor) may be 0 to mark an edge without a usable direction")
    if bool((w[:, 1] < 0).any()):
        raise ValueError("edge_weight: translation weights (column 1) must be >= 0")
    return w


def validate_sync_input(struct: dict[str, Any], edge_pose: Tensor | None) -> None:
    """Clear ``ValueError`` (naming the input) for everything a backend cannot handle:
    wrong shapes, NaN/inf, zero quaternions, graphs with fewer than 2 nodes or no edge,
    out-of-range indices and self loops (:func:`posernet.graph.check_edge_index`)."""
    ei, n = struct["edge_index"], struct["num_nodes"]
    E = ei.shape[1]
    if not isinstance(edge_pose, Tensor):
        raise ValueError(f"edge_pose must be a torch.Tensor of shape [E, 7], got "
                         f"{type(edge_pose).__name__}")
    if edge_pose.ndim != 2 or edge_pose.shape != (E, 7):
        raise ValueError(f"edge_pose has shape {tuple(edge_pose.shape)}, expected ({E}, 7) "
                         "(one [q, t] row per stored edge of the batch)")
    if not edge_pose.is_floating_point():
        raise ValueError(f"edge_pose must be floating point, got {edge_pose.dtype}")
    finite = torch.isfinite(edge_pose).all(dim=1)
    if not bool(finite.all()):
        e = int((~finite).nonzero()[0, 0])
        raise ValueError(f"edge_pose has a NaN/inf value (edge {e}, graph "
                         f"{int(struct['edge_batch'][e])})")
    if E and bool((edge_pose[:, :4].norm(dim=1) < 1e-8).any()):
        e = int((edge_pose[:, :4].norm(dim=1) < 1e-8).nonzero()[0, 0])
        raise ValueError(f"edge_pose of edge {e} has a zero quaternion")
    check_edge_index(ei, n)
    B = struct["num_graphs"]
    nodes = scatter_count(struct["node_batch"], B)
    edges = scatter_count(struct["edge_batch"], B)
    for what, bad in (("fewer than 2 nodes", nodes < 2), ("no edges", edges == 0)):
        if bool(bad.any()):
            g = int(bad.nonzero()[0, 0])
            raise ValueError(
                f"graph {g} ({struct['names'][g]!r}) has {what} "
                f"({int(nodes[g])} nodes, {int(edges[g])} edges): motion averaging needs at "
                "least 2 nodes joined by an edge"
            )


def apply_scale_policy(t: Tensor, policy: str, edge_pose_gt: Tensor | None) -> Tensor:
    """Relative translations ``t [E, 3]`` after the scale policy (see the module docstring).

    Zero vectors stay zero (coincident centres carry no direction to rescale).
    """
    if policy in ("given", "free"):
        return t
    norm = t.norm(dim=-1, keepdim=True)
    unit = torch.where(norm > 0, t / norm.clamp_min(1e-300), torch.zeros_like(t))
    if policy == "unit":
        return unit
    if policy == "oracle":
        if edge_pose_gt is None:
            raise ValueError("scale='oracle' needs ground-truth relative poses "
                             "(batch.edge_pose_gt is missing)")
        if edge_pose_gt.shape != (t.shape[0], 7):
            raise ValueError(f"edge_pose_gt has shape {tuple(edge_pose_gt.shape)}, expected "
                             f"({t.shape[0]}, 7)")
        gt = edge_pose_gt.to(device=t.device, dtype=t.dtype)
        if not bool(torch.isfinite(gt).all()):
            raise ValueError("edge_pose_gt has a NaN/inf value (needed by scale='oracle')")
        return unit * gt[:, 4:].norm(dim=-1, keepdim=True)
    raise ValueError(f"unknown scale policy {policy!r}; choose one of {list(SCALE_POLICIES)}")


# --------------------------------------------------------------------------- option helpers


def check_positive(name: str, value: float, integer: bool = False) -> None:
    """Option check helper: finite, positive (and an int when ``integer``)."""
    if integer and (not isinstance(value, int) or isinstance(value, bool)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(
            value) or value <= 0:
        raise ValueError(f"{name} must be a positive number, got {value!r}")


def as_mapping(cfg: Any) -> Mapping[str, Any]:
    """Plain dict from a mapping or an OmegaConf node."""
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(cfg, DictConfig):
            return dict(OmegaConf.to_container(cfg, resolve=True))  # type: ignore[arg-type]
    except ImportError:  # pragma: no cover - hydra is a dependency
        pass
    if not isinstance(cfg, Mapping):
        raise ValueError(f"sync config must be a mapping with a 'name', got {type(cfg).__name__}")
    return dict(cfg)

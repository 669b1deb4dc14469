"""The motion-averaging interface: input checks, the translation-scale policy, connected
components, and the padded per-component layout every batched backend works on.

A backend turns relative poses on the edges of one or many view graphs into absolute
world-to-camera poses (``DESIGN.md`` section 2):

* edge ``e = (i -> j)`` carries ``P_e = M_j M_i^{-1}`` as ``[qw, qx, qy, qz, tx, ty, tz]``;
* the result is ``M_i = [[R_i, t_i], [0, 1]]`` for every node, ``x_cam = R_i X + t_i``.

**Components.** Every backend solves each connected component of each graph on its own (its
own gauge). Nodes without any edge cannot be placed: they get the identity pose and
``SyncResult.solved`` is ``False`` for them, so evaluation can leave them out explicitly. With
``disconnected="error"`` a graph that is not connected raises a ``ValueError`` instead.

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

from ..geometry import quaternion_to_rotation_matrix
from ..graph import GraphBatch, ViewGraph
from ..nn.scatter import scatter_count

__all__ = [
    "SCALE_POLICIES",
    "Components",
    "PaddedProblem",
    "SyncBackend",
    "SyncOptions",
    "SyncResult",
    "apply_scale_policy",
    "batch_median",
    "connected_components",
    "graph_structure",
    "mad_cauchy_weights",
    "mad_huber_weights",
    "project_to_so3",
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


@dataclass(frozen=True)
class SyncOptions:
    """Options shared by every backend; subclasses add their own fields."""

    scale: str = "unit"
    disconnected: str = "components"

    def check(self) -> None:
        if self.scale not in SCALE_POLICIES:
            raise ValueError(f"scale={self.scale!r} is not a scale policy; choose one of "
                             f"{list(SCALE_POLICIES)}")
        if self.disconnected not in DISCONNECTED_POLICIES:
            raise ValueError(f"disconnected={self.disconnected!r}; choose one of "
                             f"{list(DISCONNECTED_POLICIES)}")


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

    def solve(self, batch: GraphBatch | ViewGraph, edge_pose: Tensor | None = None) -> Tensor:
        """Absolute world-to-camera poses ``[N, 4, 4]`` from relative poses ``edge_pose [E, 7]``
        on the stored edges of ``batch`` (``batch.edge_pose`` when omitted)."""
        return self.solve_with_info(batch, edge_pose).poses

    def solve_with_info(self, batch: GraphBatch | ViewGraph,
                        edge_pose: Tensor | None = None) -> SyncResult:
        """Like :meth:`solve` but returns the full :class:`SyncResult`."""
        if edge_pose is None:
            edge_pose = getattr(batch, "edge_pose", None)
        struct = graph_structure(batch)
        validate_sync_input(struct, edge_pose)
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
    if not isinstance(ei, Tensor) or ei.ndim != 2 or ei.shape[0] != 2:
        shape = tuple(ei.shape) if isinstance(ei, Tensor) else type(ei).__name__
        raise ValueError(f"batch.edge_index must be a [2, E] tensor, got {shape}")
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


def validate_sync_input(struct: dict[str, Any], edge_pose: Tensor | None) -> None:
    """Clear ``ValueError`` (naming the input) for everything a backend cannot handle:
    wrong shapes, NaN/inf, zero quaternions, graphs with fewer than 2 nodes or no edge,
    out-of-range indices and self loops."""
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
    if E and (int(ei.min()) < 0 or int(ei.max()) >= n):
        raise ValueError(f"edge_index out of range [0, {n}) of nodes")
    if E and bool((ei[0] == ei[1]).any()):
        e = int((ei[0] == ei[1]).nonzero()[0, 0])
        raise ValueError(f"edge {e} is a self loop on node {int(ei[0, e])}")
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


# --------------------------------------------------------------------------- components


@dataclass
class Components:
    """Connected components of a batch. ``comp [N]`` component id of every node (ids are
    global, ``0..C-1``, ordered by smallest node id), ``size [C]``, ``graph [C]``,
    ``local [N]`` position of the node inside its component, ``graph_num_components [B]``."""

    comp: Tensor
    size: Tensor
    graph: Tensor
    local: Tensor
    graph_num_components: Tensor

    @property
    def num(self) -> int:
        return int(self.size.numel())


def connected_components(edge_index: Tensor, num_nodes: int, node_batch: Tensor,
                         num_graphs: int) -> Components:
    """Batched connected components by min-label propagation with pointer jumping.

    Each round sets every node's label to the smallest label among itself and its neighbours,
    then shortcuts ``label <- label[label]``; it stops when nothing changes (O(log diameter)
    rounds in practice). No Python loop over graphs or edges.
    """
    dev = edge_index.device
    label = torch.arange(num_nodes, device=dev)
    src, dst = edge_index[0], edge_index[1]
    while True:
        new = label.clone()
        new.scatter_reduce_(0, dst, label[src], reduce="amin")
        new.scatter_reduce_(0, src, label[dst], reduce="amin")
        new = new[new]
        if torch.equal(new, label):
            break
        label = new
    roots, comp = torch.unique(label, return_inverse=True)
    size = scatter_count(comp, roots.numel())
    graph = node_batch[roots]
    order = torch.argsort(comp, stable=True)
    start = torch.cumsum(size, 0) - size
    local = torch.empty_like(comp)
    local[order] = torch.arange(num_nodes, device=dev) - start[comp[order]]
    gnc = scatter_count(graph, num_graphs)
    return Components(comp=comp, size=size, graph=graph, local=local, graph_num_components=gnc)


@dataclass
class PaddedProblem:
    """Solvable components (>= 2 nodes) laid out padded for batched linear algebra.

    ``G`` components, ``n`` = largest component, ``m`` = most edges in a component.
    ``node [G, n]`` global node id (-1 pad), ``node_mask [G, n]``; ``edge [G, m]`` global edge id
    (-1 pad), ``edge_mask [G, m]``, ``src``/``dst [G, m]`` local endpoints (0 on pads);
    ``R [G, m, 3, 3]``, ``t [G, m, 3]`` relative rotation/translation of ``src -> dst``
    (identity/zero on pads); ``comp_id [G]`` global component id; ``count [G]`` node count.
    """

    node: Tensor
    node_mask: Tensor
    edge: Tensor
    edge_mask: Tensor
    src: Tensor
    dst: Tensor
    R: Tensor
    t: Tensor
    comp_id: Tensor
    count: Tensor

    @property
    def G(self) -> int:
        return int(self.node.shape[0])

    @property
    def n(self) -> int:
        return int(self.node.shape[1])

    @property
    def m(self) -> int:
        return int(self.edge.shape[1])

    def select(self, idx: Tensor) -> PaddedProblem:
        """Sub-problem of the components ``idx`` (trimmed to their own padding)."""
        n = int(self.count[idx].max())
        m = int(self.edge_mask[idx].sum(1).max())
        return PaddedProblem(
            node=self.node[idx, :n], node_mask=self.node_mask[idx, :n],
            edge=self.edge[idx, :m], edge_mask=self.edge_mask[idx, :m],
            src=self.src[idx, :m], dst=self.dst[idx, :m], R=self.R[idx, :m], t=self.t[idx, :m],
            comp_id=self.comp_id[idx], count=self.count[idx],
        )


def build_padded(edge_index: Tensor, R: Tensor, t: Tensor, comps: Components) -> PaddedProblem:
    """Pad the solvable components; ``R [E, 3, 3]``, ``t [E, 3]`` per stored edge."""
    dev = edge_index.device
    solvable = (comps.size >= 2).nonzero().squeeze(1)
    G = int(solvable.numel())
    remap = torch.full((comps.num,), -1, dtype=torch.long, device=dev)
    remap[solvable] = torch.arange(G, device=dev)
    n = int(comps.size[solvable].max())
    node_g = remap[comps.comp]
    keep = node_g >= 0
    node = torch.full((G, n), -1, dtype=torch.long, device=dev)
    node[node_g[keep], comps.local[keep]] = keep.nonzero().squeeze(1)
    E = edge_index.shape[1]
    edge_g = remap[comps.comp[edge_index[0]]]
    ecount = scatter_count(edge_g, G)
    m = int(ecount.max())
    order = torch.argsort(edge_g, stable=True)
    start = torch.cumsum(ecount, 0) - ecount
    epos = torch.empty_like(edge_g)
    epos[order] = torch.arange(E, device=dev) - start[edge_g[order]]
    edge = torch.full((G, m), -1, dtype=torch.long, device=dev)
    edge[edge_g, epos] = torch.arange(E, device=dev)
    edge_mask = edge >= 0
    safe = edge.clamp_min(0)
    src = torch.where(edge_mask, comps.local[edge_index[0, safe]], 0)
    dst = torch.where(edge_mask, comps.local[edge_index[1, safe]], 0)
    eye = torch.eye(3, dtype=R.dtype, device=dev)
    Rp = torch.where(edge_mask[..., None, None], R[safe], eye)
    tp = torch.where(edge_mask[..., None], t[safe], torch.zeros((), dtype=t.dtype, device=dev))
    return PaddedProblem(node=node, node_mask=node >= 0, edge=edge, edge_mask=edge_mask,
                         src=src, dst=dst, R=Rp, t=tp, comp_id=solvable,
                         count=comps.size[solvable])


def edge_rotations(edge_pose: Tensor) -> Tensor:
    """Rotation matrices ``[E, 3, 3]`` of edge pose vectors ``[E, 7]``."""
    return quaternion_to_rotation_matrix(edge_pose[:, :4])


# --------------------------------------------------------------------------- small linalg


def batch_median(x: Tensor, mask: Tensor) -> Tensor:
    """Median of the masked entries along the last dim (mean of the two middle values for an
    even count, numpy/MATLAB convention). ``x, mask [..., m] -> [...]``; NaN where empty."""
    big = torch.finfo(x.dtype).max
    s = torch.sort(torch.where(mask, x, torch.full_like(x, big)), dim=-1).values
    k = mask.sum(-1)
    lo = ((k - 1).clamp_min(0) // 2)[..., None]
    hi = (k // 2).clamp_max(x.shape[-1] - 1)[..., None]
    med = 0.5 * (s.gather(-1, lo) + s.gather(-1, hi)).squeeze(-1)
    return torch.where(k > 0, med, torch.full_like(med, float("nan")))


def det3(A: Tensor) -> Tensor:
    """Determinant of ``[..., 3, 3]`` in closed form (no LAPACK call per matrix)."""
    return _det9(A.reshape(-1, 9).T).reshape(A.shape[:-2])


def _det9(a: Tensor) -> Tensor:
    """Determinants of matrices stored entry-major: ``a [9, K]`` (row-major entries)."""
    return (a[0] * (a[4] * a[8] - a[5] * a[7]) - a[1] * (a[3] * a[8] - a[5] * a[6])
            + a[2] * (a[3] * a[7] - a[4] * a[6]))


def _cof9(a: Tensor) -> Tensor:
    """Cofactor matrices, entry-major ``[9, K]``: ``A^{-T} = cof(A) / det(A)``."""
    return torch.stack((
        a[4] * a[8] - a[5] * a[7], a[5] * a[6] - a[3] * a[8], a[3] * a[7] - a[4] * a[6],
        a[2] * a[7] - a[1] * a[8], a[0] * a[8] - a[2] * a[6], a[1] * a[6] - a[0] * a[7],
        a[1] * a[5] - a[2] * a[4], a[2] * a[3] - a[0] * a[5], a[0] * a[4] - a[1] * a[3],
    ))


def project_to_so3(A: Tensor, max_iter: int = 30) -> Tensor:
    """Nearest rotation (Frobenius) of every ``[..., 3, 3]`` matrix: ``U diag(1, 1, det UV^T) V^T``.

    Matrices with ``det > 0`` use the scaled Newton iteration for the polar factor,
    ``X <- (g X + X^{-T} / g) / 2`` with ``g = (|X^{-1}|_F / |X|_F)^{1/2}`` (Higham), on an
    entry-major ``[9, K]`` layout so that each step is a few dozen contiguous elementwise
    kernels; it converges quadratically, replacing one LAPACK SVD per matrix. The rest
    (``det <= 0``, or no convergence) fall back to a batched SVD.
    """
    shape = A.shape
    K = A.numel() // 9
    if K == 0:
        return A.clone()
    a = A.reshape(K, 9).T.contiguous()
    a = a / (a * a).sum(0).sqrt().clamp_min(1e-300)  # (a*a).sum: 10x faster than norm(dim=0)
    good = _det9(a) > 1e-12
    out = torch.empty_like(a)
    fallback = ~good
    if bool(good.any()):
        y = a[:, good]
        for _ in range(max_iter):
            cof = _cof9(y)
            inv_t = cof / (cof[:3] * y[:3]).sum(0)  # det = row 0 . cofactor row 0
            g = ((inv_t * inv_t).sum(0) / (y * y).sum(0)).sqrt().sqrt()
            yn = 0.5 * (g * y + inv_t / g)
            delta = (yn - y).abs().amax()
            y = yn
            if float(delta) < 1e-14:
                break
        cof = _cof9(y)  # one unscaled step polishes orthogonality to machine precision
        y = 0.5 * (y + cof / (cof[:3] * y[:3]).sum(0))
        yy = y.view(3, 3, -1)
        gram = torch.einsum("ikn,jkn->ijn", yy, yy)
        ok = (gram - torch.eye(3, dtype=y.dtype, device=y.device)[..., None]).abs().amax(
            dim=(0, 1)) < 1e-10
        out[:, good] = y
        gidx = good.nonzero().squeeze(1)
        fallback = fallback.clone()
        fallback[gidx[~ok]] = True
    if bool(fallback.any()):
        X = a[:, fallback].T.reshape(-1, 3, 3)
        U, _, Vh = torch.linalg.svd(X)
        sgn = torch.sign(torch.linalg.det(U @ Vh))
        sgn = torch.where(sgn == 0, torch.ones_like(sgn), sgn)
        U = torch.cat((U[..., :2], U[..., 2:] * sgn[:, None, None]), dim=-1)
        out[:, fallback] = (U @ Vh).reshape(-1, 9).T
    return out.T.reshape(shape)


def mad_cauchy_weights(res: Tensor, mask: Tensor, theta: float,
                       floor: float = 1e-9) -> Tensor:
    """Cauchy IRLS weights ``1 / (1 + (r / th)^2)`` with ``th = theta / 0.6745 * MAD(r)``
    per row. ``res, mask [G, m]``; ``MAD = median(|r - median(r)|)`` over the row's edges.

    ``floor`` keeps ``th`` positive for exact data (all residuals ~0), where the weights would
    otherwise be 0/0 round-off noise; it only acts when ``th < floor``.
    """
    med = batch_median(res, mask)
    mad = batch_median((res - med[:, None]).abs(), mask)
    th = (theta / 0.6745 * mad).clamp_min(floor)
    w = 1.0 / (1.0 + (res / th[:, None]) ** 2)
    return torch.where(mask, w, torch.zeros_like(w))


def mad_huber_weights(res: Tensor, mask: Tensor, theta: float,
                      floor: float = 1e-9) -> Tensor:
    """Huber IRLS weights ``min(1, th / r)`` with the same MAD threshold as
    :func:`mad_cauchy_weights`. ``res, mask [G, m]``."""
    med = batch_median(res, mask)
    mad = batch_median((res - med[:, None]).abs(), mask)
    th = (theta / 0.6745 * mad).clamp_min(floor)[:, None]
    w = torch.where(res <= th, torch.ones_like(res), th / res.clamp_min(1e-300))
    return torch.where(mask, w, torch.zeros_like(w))


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

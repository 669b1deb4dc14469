"""Scatter reductions in pure torch (no ``torch-scatter``, no ``torch_geometric``).

``scatter_*(src, index, dim=0, dim_size=None)`` reduces the rows of ``src`` that share an
``index`` value:

.. math::

    \\mathrm{out}_g = \\operatorname{reduce}_{r \\,:\\, \\mathrm{index}_r = g} \\mathrm{src}_r

Rows are taken along ``dim`` (0 by default); ``index`` is 1-D with one entry per row. Groups that
receive no row give 0 (never NaN), so isolated nodes and edges without matched pairs are safe.
All functions are differentiable, run on any device and in any floating dtype.

Flags (``bool``) are reduced with :func:`scatter_all` / :func:`scatter_any`: CUDA has no
scatter reduction kernel for ``bool`` tensors (``scatter_reduce`` of a bool tensor raises
there), so these count in ``long`` and compare.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["scatter_all", "scatter_any", "scatter_count", "scatter_max", "scatter_mean",
           "scatter_sum", "scatter_sum_unchecked"]


def _check(src: Tensor, index: Tensor, dim: int, dim_size: int | None) -> tuple[int, int]:
    """Validate arguments; return the normalised ``dim`` and the output size along it."""
    if not isinstance(index, Tensor) or index.ndim != 1:
        shape = tuple(index.shape) if isinstance(index, Tensor) else type(index).__name__
        raise ValueError(f"scatter: index must be a 1-D tensor, got shape {shape}")
    if index.dtype not in (torch.long, torch.int32):
        raise TypeError(f"scatter: index must be an integer tensor (long), got {index.dtype}")
    if src.ndim == 0:
        raise ValueError("scatter: src must have at least one dimension")
    d = dim if dim >= 0 else dim + src.ndim
    if not 0 <= d < src.ndim:
        raise ValueError(f"scatter: dim {dim} out of range for src of shape {tuple(src.shape)}")
    if src.shape[d] != index.numel():
        raise ValueError(
            f"scatter: index has {index.numel()} entries but src has {src.shape[d]} rows "
            f"along dim {dim} (shape {tuple(src.shape)})"
        )
    if index.device != src.device:
        raise ValueError(f"scatter: index is on {index.device} but src on {src.device}")
    if dim_size is None:
        dim_size = int(index.max()) + 1 if index.numel() else 0
    elif index.numel() and index.device.type == "cpu" and not torch.compiler.is_compiling() \
            and (int(index.min()) < 0 or int(index.max()) >= dim_size):
        # Range checked on the CPU and in eager mode only: on a GPU it would cost a host sync
        # per call, under torch.compile a graph break (callers such as PoserConv validate
        # their indices once per forward instead).
        raise IndexError(
            f"scatter: index values must lie in [0, {dim_size}), got "
            f"[{int(index.min())}, {int(index.max())}]"
        )
    return d, dim_size


def _broadcast(index: Tensor, src: Tensor, dim: int) -> Tensor:
    """View of ``index`` expanded to ``src``'s shape along ``dim`` (for ``scatter_reduce``)."""
    shape = [1] * src.ndim
    shape[dim] = -1
    return index.long().view(shape).expand_as(src)


def scatter_sum(src: Tensor, index: Tensor, dim: int = 0, dim_size: int | None = None) -> Tensor:
    """Sum of the rows of ``src`` per group.

    Args:
        src: values, any shape; rows along ``dim``.
        index: ``[R]`` group of each row (long).
        dim: the row dimension of ``src`` (default 0).
        dim_size: number of groups ``G`` (default ``index.max() + 1``).

    Shapes: ``src (..., R, ...)``, ``index (R,)`` -> ``(..., G, ...)``.
    """
    dim, dim_size = _check(src, index, dim, dim_size)
    return scatter_sum_unchecked(src, index, dim, dim_size)


def scatter_sum_unchecked(src: Tensor, index: Tensor, dim: int, dim_size: int) -> Tensor:
    """:func:`scatter_sum` without its input checks, for hot paths whose ``index`` is known
    to be valid (1-D, in ``[0, dim_size)``)."""
    shape = list(src.shape)
    shape[dim] = dim_size
    return src.new_zeros(shape).index_add(dim, index.long(), src)


def scatter_count(index: Tensor, dim_size: int | None = None) -> Tensor:
    """Number of rows per group, ``(G,)`` long (0 for empty groups)."""
    if not isinstance(index, Tensor) or index.ndim != 1:
        raise ValueError("scatter_count: index must be a 1-D tensor")
    if dim_size is None:
        dim_size = int(index.max()) + 1 if index.numel() else 0
    # index_add rather than bincount: bincount has no deterministic CUDA kernel and raises
    # under torch.use_deterministic_algorithms (Lightning's deterministic=True).
    out = torch.zeros(dim_size, dtype=torch.long, device=index.device)
    return out.index_add_(0, index.long(), torch.ones_like(index, dtype=torch.long))


def scatter_mean(src: Tensor, index: Tensor, dim: int = 0, dim_size: int | None = None) -> Tensor:
    """Mean of the rows of ``src`` per group; an empty group gives 0.

    ``out_g = sum_{r: index_r = g} src_r / max(1, |{r: index_r = g}|)``.
    Shapes as :func:`scatter_sum`.
    """
    dim, dim_size = _check(src, index, dim, dim_size)
    total = scatter_sum_unchecked(src, index, dim, dim_size)
    count = scatter_count(index, dim_size).clamp_min(1).to(src.dtype)
    shape = [1] * src.ndim
    shape[dim] = -1
    return total / count.view(shape)


def scatter_max(src: Tensor, index: Tensor, dim: int = 0, dim_size: int | None = None) -> Tensor:
    """Element-wise maximum of the rows of ``src`` per group; an empty group gives 0.

    Gradients flow to the maximal entries (split evenly between ties, as ``amax`` does).
    Shapes as :func:`scatter_sum`.
    """
    dim, dim_size = _check(src, index, dim, dim_size)
    flags = src.dtype == torch.bool
    if flags:  # no CUDA kernel reduces bool: reduce in uint8
        src = src.to(torch.uint8)
    shape = list(src.shape)
    shape[dim] = dim_size
    out = src.new_zeros(shape)
    # include_self=False: the zeros only show through in groups that receive no row.
    out = out.scatter_reduce(dim, _broadcast(index, src, dim), src, reduce="amax",
                             include_self=False)
    return out.bool() if flags else out


def _count_where(flags: Tensor, index: Tensor, dim_size: int) -> Tensor:
    """``[G]`` number of True ``flags [R]`` per group (``index [R]``), long."""
    if flags.shape != index.shape or index.ndim != 1:
        raise ValueError(f"scatter: flags and index must be 1-D of equal length, got "
                         f"{tuple(flags.shape)} and {tuple(index.shape)}")
    out = torch.zeros(dim_size, dtype=torch.long, device=index.device)
    return out.index_add_(0, index.long(), flags.to(torch.long))


def scatter_all(flags: Tensor, index: Tensor, dim_size: int) -> Tensor:
    """``[G]`` bool: every flag of the group is True (True for an empty group).

    ``flags [R]`` (bool, or anything nonzero-is-true), ``index [R]`` group of each row. Counted
    in ``long``: CUDA has no ``amin`` scatter kernel for bool tensors.
    """
    return _count_where(~flags.bool(), index, dim_size) == 0


def scatter_any(flags: Tensor, index: Tensor, dim_size: int) -> Tensor:
    """``[G]`` bool: some flag of the group is True (False for an empty group); as
    :func:`scatter_all`."""
    return _count_where(flags.bool(), index, dim_size) > 0

"""Failures only a GPU shows, caught on the CPU.

The averaging, refinement, evaluation and training paths run here with torch's ops wrapped
to fail where CUDA fails:

* ops without a CUDA kernel for a dtype: scatter and index reductions of ``bool`` tensors
  (``"cuda_scatter_gather_base_kernel_func" not implemented for 'Bool'``);
* ops without a deterministic CUDA kernel, which raise under
  ``torch.use_deterministic_algorithms(True)`` (Lightning's ``deterministic=True``):
  ``median`` with indices, floating ``cumsum``, weighted ``bincount``, ``histc``, ``put_``,
  ``scatter_reduce(reduce="prod")``, ``nll_loss`` / ``cross_entropy``;
* answers that hang on round-off, so that the GPU's different arithmetic gives another
  answer: the inputs are moved by far less than a float32 network's device difference and the
  outputs must follow by about as little.

Every path runs under deterministic algorithms, so both kinds raise here as on a GPU. The
CUDA tests themselves (``tests/test_cuda.py``) need a GPU.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import torch
from device_cases import (
    ADAPTIVE,
    backend_variants,
    net_graphs,
    save_learned_sync,
    sync_graphs,
    translation_weights,
)

from posernet import GraphBatch, PoserNet
from posernet.sync import available_backends, get_backend

#: Tensor methods / torch functions that reduce into ``self`` (or ``input``): none may see a
#: bool tensor
_REDUCING_METHODS = ("scatter", "scatter_", "scatter_add", "scatter_add_", "scatter_reduce",
                     "scatter_reduce_", "index_add", "index_add_", "index_reduce",
                     "index_reduce_")
_REDUCING_FUNCTIONS = ("scatter", "scatter_add", "scatter_reduce", "index_add",
                       "index_reduce")


class CudaOnlyFailure(RuntimeError):
    """What the wrapped ops raise where CUDA would."""


def _tensors(args: tuple[Any, ...], kwargs: dict[str, Any]) -> list[torch.Tensor]:
    return [a for a in (*args, *kwargs.values()) if isinstance(a, torch.Tensor)]


def _arg(args: tuple[Any, ...], kwargs: dict[str, Any], pos: int, name: str,
         default: Any = None) -> Any:
    return args[pos] if len(args) > pos else kwargs.get(name, default)


def _deterministic() -> bool:
    return torch.are_deterministic_algorithms_enabled()


def _reducing(name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` raising on a bool operand, and on ``reduce="prod"`` under deterministic mode."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        if any(t.dtype == torch.bool for t in _tensors(args, kwargs)):
            raise CudaOnlyFailure(f"{name} of a bool tensor: no CUDA kernel for Bool")
        if "scatter_reduce" in name and _deterministic() and \
                _arg(args, kwargs, 4, "reduce") == "prod":
            raise CudaOnlyFailure(f"{name}(reduce='prod'): no deterministic CUDA kernel")
        return fn(*args, **kwargs)

    return wrapper


def _index_put(name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    """``index_put(_)``: an accumulating put into or of a bool tensor raises."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        values = _arg(args, kwargs, 2, "values")
        if _arg(args, kwargs, 3, "accumulate", False) and (
                args[0].dtype == torch.bool or getattr(values, "dtype", None) == torch.bool):
            raise CudaOnlyFailure(f"{name}(accumulate=True) of a bool tensor")
        return fn(*args, **kwargs)

    return wrapper


def _nondeterministic(name: str, fn: Callable[..., Any],
                      when: Callable[[tuple[Any, ...], dict[str, Any]], bool]
                      ) -> Callable[..., Any]:
    """``fn`` raising under deterministic mode where ``when(args, kwargs)``."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        if _deterministic() and when(args, kwargs):
            raise CudaOnlyFailure(f"{name}: no deterministic CUDA kernel (raises under "
                                  "torch.use_deterministic_algorithms(True) on a GPU)")
        return fn(*args, **kwargs)

    return wrapper


def _floating(t: Any) -> bool:
    return isinstance(t, torch.Tensor) and (t.is_floating_point() or t.is_complex())


_NONDETERMINISTIC: dict[str, Callable[[tuple[Any, ...], dict[str, Any]], bool]] = {
    # values and indices: the indices have no deterministic CUDA kernel
    "median": lambda a, k: _arg(a, k, 1, "dim") is not None,
    "cumsum": lambda a, k: _floating(a[0]) or k.get("dtype") in (torch.float32, torch.float64),
    "bincount": lambda a, k: _arg(a, k, 1, "weights") is not None,
    "histc": lambda a, k: True,
    "put_": lambda a, k: True,
}


@pytest.fixture
def cuda_semantics(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Ops wrapped to fail where CUDA fails, under deterministic algorithms."""
    for name in _REDUCING_METHODS:
        monkeypatch.setattr(torch.Tensor, name, _reducing(name, getattr(torch.Tensor, name)))
    for name in _REDUCING_FUNCTIONS:
        monkeypatch.setattr(torch, name, _reducing(name, getattr(torch, name)))
    for name in ("index_put", "index_put_"):
        monkeypatch.setattr(torch.Tensor, name, _index_put(name, getattr(torch.Tensor, name)))
    for name, when in _NONDETERMINISTIC.items():
        if hasattr(torch.Tensor, name):
            monkeypatch.setattr(torch.Tensor, name,
                                _nondeterministic(name, getattr(torch.Tensor, name), when))
        if hasattr(torch, name):
            monkeypatch.setattr(torch, name, _nondeterministic(name, getattr(torch, name), when))
    F = torch.nn.functional
    for name in ("nll_loss", "cross_entropy"):
        monkeypatch.setattr(F, name, _nondeterministic(name, getattr(F, name),
                                                       lambda a, k: True))
    was = (torch.are_deterministic_algorithms_enabled(),
           torch.is_deterministic_algorithms_warn_only_enabled())
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(was[0], warn_only=was[1])


@pytest.fixture(scope="module")
def learned_ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save_learned_sync(tmp_path_factory.mktemp("learned") / "learned.ckpt")


@pytest.fixture(scope="module")
def input_stats() -> dict[str, Any]:
    """Training-input statistics for the guard (computed outside the wrapped ops: training
    computes them on the CPU, from the data module's graphs)."""
    from posernet.guard import input_statistics

    return input_statistics(net_graphs())


# --------------------------------------------------------------------------- tests


def test_the_wrappers_raise_where_cuda_does(cuda_semantics: None) -> None:
    idx = torch.tensor([0, 0, 1])
    flags = torch.tensor([True, False, True])
    with pytest.raises(CudaOnlyFailure, match="bool"):
        torch.ones(2, dtype=torch.bool).scatter_reduce_(0, idx, flags, reduce="amin")
    with pytest.raises(CudaOnlyFailure, match="bool"):
        torch.zeros(2, dtype=torch.bool).index_add_(0, idx, flags)
    with pytest.raises(CudaOnlyFailure, match="deterministic"):
        torch.rand(3).median(dim=0)
    with pytest.raises(CudaOnlyFailure, match="deterministic"):
        torch.cumsum(torch.rand(3), 0)
    # what the package does instead: reduce in an integer dtype
    out = torch.ones(2, dtype=torch.uint8).scatter_reduce_(0, idx, flags.to(torch.uint8),
                                                           reduce="amin").bool()
    assert out.tolist() == [False, True]
    assert torch.cumsum(idx, 0).tolist() == [0, 0, 1] and torch.rand(3).median().ndim == 0


@pytest.mark.parametrize("name", available_backends())
def test_every_sync_backend(name: str, learned_ckpt: Path, cuda_semantics: None) -> None:
    batch = GraphBatch.from_graphs(sync_graphs())
    w = translation_weights(batch.edge_index.shape[1])
    for options in backend_variants(name, learned_ckpt):
        be = get_backend(name, **options, **({"device": "cpu"} if name == "learned" else {}))
        for weights in (None, w):
            res = be.solve_with_info(batch, batch.edge_pose, edge_weight=weights)
            assert torch.isfinite(res.poses).all(), (name, options)
            assert not bool(res.solved[batch.ptr[1] + 8]), (name, options)  # isolated camera


def test_refine_and_evaluate(input_stats: dict[str, Any], cuda_semantics: None) -> None:
    from posernet.evaluation import evaluate_result, result_tables
    from posernet.guard import refinement_check
    from posernet.refinement import refine_graphs

    gs = net_graphs()
    torch.manual_seed(0)
    plain, adaptive = PoserNet(depth=2), PoserNet(depth=2, **ADAPTIVE)
    for model, backend, extra in (
            (plain, "eig_se3", {}),
            (adaptive, "rotation_translation", {"guard": True, "weighted": True}),
            (adaptive, "eig_se3", {"edge_weight": [torch.ones(g.num_edges, 2) for g in gs]})):
        res = refine_graphs(model, gs, backend=get_backend(backend), progress=False,
                            batch_size=2, **extra)
        ev = evaluate_result(res)
        assert set(result_tables(ev)) == {"relative", "absolute"}
        _, record = refinement_check(input_stats, gs, res.edge_pose)
        assert set(record["cycle_deg"]) == {"initial", "refined"} and record["training_stats"]


@pytest.mark.parametrize("kind", ["posernet", "adaptive", "end_to_end", "learned_sync"])
def test_training_and_validation_steps(kind: str, cuda_semantics: None) -> None:
    from posernet.lit import LearnedSyncModule, PoserNetModule

    torch.manual_seed(0)
    module = {
        "posernet": lambda: PoserNetModule(net={"depth": 2}),
        "adaptive": lambda: PoserNetModule(net={"depth": 2, **ADAPTIVE},
                                           loss={"raw": 0.5, "confidence": 0.1,
                                                 "correction": 0.1, "harm": 1.0}),
        "end_to_end": lambda: PoserNetModule(net={"depth": 2},
                                             loss={"end_to_end": True}),
        "learned_sync": lambda: LearnedSyncModule(net={"hidden": 8, "rounds": 2}),
    }[kind]()
    module.log = lambda *a, **k: None  # type: ignore[method-assign]
    batch = GraphBatch.from_graphs(net_graphs(4))
    loss = module.training_step(batch, 0)
    loss.backward()
    assert torch.isfinite(loss)
    with torch.no_grad():
        assert torch.isfinite(module.validation_step(batch, 0))
    module.on_validation_epoch_end()


# --------------------------------------------------------------------------- round-off


def _gauge_free(poses: torch.Tensor, component: torch.Tensor) -> torch.Tensor:
    """``M_i M_a^{-1}`` (``a`` the first camera of ``i``'s component) of ``poses [N, 4, 4]``."""
    first = {int(c): int((component == c).nonzero()[0]) for c in component.unique()}
    anchor = torch.stack([poses[first[int(c)]] for c in component])
    return poses.double() @ torch.linalg.inv(anchor.double())


def test_positions_a_graph_leaves_free_do_not_hang_on_round_off() -> None:
    # Graph 1 of sync_graphs has a 4-camera component with one camera on a single edge: the
    # directions do not fix its distance. The answer is the ridge's choice, not one that the
    # refinement against the unridged system drifts to by round-off / ridge (a 1e-15 move of
    # the input once moved the positions by 0.036, and CUDA answered 0.036 away).
    batch = GraphBatch.from_graphs(sync_graphs())
    be = get_backend("rotation_translation")
    a = be.solve_with_info(batch, batch.edge_pose)
    assert a.info["parallel_rigid"].tolist() == [True, False, True]
    gen = torch.Generator().manual_seed(1)
    for eps in (1e-15, 1e-13, 1e-11):
        moved = batch.edge_pose + eps * torch.randn(batch.edge_pose.shape, generator=gen,
                                                    dtype=batch.edge_pose.dtype)
        b = be.solve_with_info(batch, moved)
        diff = (_gauge_free(a.poses, a.component) - _gauge_free(b.poses, b.component)).abs()
        assert float(diff.max()) < 1e-4, eps


def test_guarded_refinement_does_not_hang_on_round_off() -> None:
    # The guarded, weighted refinement with rotation_translation on small random graphs, some
    # of them not parallel rigid: an input moved by float32's round-off (what CUDA's
    # arithmetic does to the network's confidence weights) once moved cameras by 1.5.
    from posernet.refinement import refine_graphs

    torch.manual_seed(0)
    model = PoserNet(depth=2, **ADAPTIVE)
    ref = refine_graphs(model, net_graphs(6), backend=get_backend("rotation_translation"),
                        progress=False, batch_size=4, guard=True, weighted=True)
    for seed, eps in ((1, 1e-7), (3, 1e-7), (1, 1e-6)):
        gen = torch.Generator().manual_seed(seed)
        moved = net_graphs(6)
        for g in moved:
            g.edge_pose = g.edge_pose + eps * torch.randn(g.edge_pose.shape, generator=gen)
            g.estimates = {"kp": g.edge_pose, "bb": g.edge_pose}
        out = refine_graphs(model, moved, backend=get_backend("rotation_translation"),
                            progress=False, batch_size=4, guard=True, weighted=True)
        for stage in ("initial", "refined"):
            for k in range(6):
                diff = (_gauge_free(ref.absolute[stage][k], ref.component[stage][k])
                        - _gauge_free(out.absolute[stage][k], out.component[stage][k])).abs()
                assert float(diff.max()) < 1e-3, (seed, eps, stage, k)


def test_direction_pruning_waits_for_positions_the_edges_fix() -> None:
    # Graph 2 of net_graphs(5) (the graphs of the refine command's CUDA comparison) keeps 10
    # edges after rotation pruning, too few to fix 8 positions. The robust residuals there
    # measure one arbitrary choice among many, so pruning by them dropped different edges
    # under float32 round-off (cameras 1.6 apart, and 1.9 between CPU and CUDA).
    batch = GraphBatch.from_graphs(net_graphs(5))
    be = get_backend("rotation_translation")
    a = be.solve_with_info(batch, batch.edge_pose)
    assert not bool(a.info["parallel_rigid"][2])
    gen = torch.Generator().manual_seed(0)
    for _ in range(6):
        moved = batch.edge_pose * (1 + 1e-7 * torch.randn(batch.edge_pose.shape, generator=gen))
        b = be.solve_with_info(batch, moved)
        diff = (_gauge_free(a.poses, a.component) - _gauge_free(b.poses, b.component)).abs()
        assert float(diff.max()) < 1e-3

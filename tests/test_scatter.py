"""Scatter reductions against a dense (one-hot matrix) reference."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from posernet.scatter import (
    scatter_all,
    scatter_any,
    scatter_count,
    scatter_max,
    scatter_mean,
    scatter_sum,
)


def dense_reference(src: torch.Tensor, index: torch.Tensor, G: int, reduce: str) -> torch.Tensor:
    """Per-group reduction by looping over groups with a boolean mask (obviously correct)."""
    out = torch.zeros((G, *src.shape[1:]), dtype=src.dtype)
    for g in range(G):
        rows = src[index == g]
        if rows.shape[0] == 0:
            continue
        if reduce == "sum":
            out[g] = rows.sum(0)
        elif reduce == "mean":
            out[g] = rows.mean(0)
        else:
            out[g] = rows.max(0).values
    return out


@settings(max_examples=40, deadline=None)
@given(
    rows=st.integers(0, 30),
    groups=st.integers(1, 8),
    feat=st.integers(1, 3),
    seed=st.integers(0, 2**16),
)
def test_against_dense_reference(rows: int, groups: int, feat: int, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    src = torch.randn(rows, feat, generator=g, dtype=torch.float64)
    index = torch.randint(0, groups, (rows,), generator=g)
    for fn, name in ((scatter_sum, "sum"), (scatter_mean, "mean"), (scatter_max, "max")):
        got = fn(src, index, dim_size=groups)
        torch.testing.assert_close(got, dense_reference(src, index, groups, name))
    # One-hot matrix product is a second, independent reference for the sum.
    onehot = torch.nn.functional.one_hot(index, groups).to(src.dtype)  # [R, G]
    torch.testing.assert_close(scatter_sum(src, index, dim_size=groups), onehot.T @ src)
    torch.testing.assert_close(scatter_count(index, groups), onehot.sum(0).long())


def test_empty_groups_give_zero_not_nan() -> None:
    src = torch.tensor([[1.0, -2.0], [3.0, -4.0]])
    index = torch.tensor([0, 0])
    for fn in (scatter_sum, scatter_mean, scatter_max):
        out = fn(src, index, dim_size=4)
        assert out.shape == (4, 2)
        assert torch.isfinite(out).all()
        assert (out[1:] == 0).all()
    torch.testing.assert_close(scatter_mean(src, index, dim_size=4)[0], torch.tensor([2.0, -3.0]))
    # Max of all-negative rows must be the negative max, not the zero fill value.
    torch.testing.assert_close(scatter_max(src, index, dim_size=4)[0], torch.tensor([3.0, -2.0]))


def test_no_rows_at_all() -> None:
    src = torch.zeros(0, 3)
    index = torch.zeros(0, dtype=torch.long)
    assert scatter_mean(src, index, dim_size=5).abs().sum() == 0
    assert scatter_sum(src, index).shape == (0, 3)


def test_other_dim_and_default_size() -> None:
    src = torch.arange(12.0).reshape(2, 6)
    index = torch.tensor([0, 1, 0, 1, 2, 2])
    out = scatter_sum(src, index, dim=1)
    assert out.shape == (2, 3)
    torch.testing.assert_close(out, torch.tensor([[2.0, 4.0, 9.0], [14.0, 16.0, 21.0]]))
    torch.testing.assert_close(scatter_mean(src, index, dim=-1), out / 2)
    torch.testing.assert_close(scatter_max(src, index, dim=1),
                               torch.tensor([[2.0, 3.0, 5.0], [8.0, 9.0, 11.0]]))


def test_index_must_be_1d_and_in_range() -> None:
    src = torch.randn(4, 2)
    with pytest.raises(ValueError, match="1-D"):
        scatter_sum(src, torch.zeros(2, 2, dtype=torch.long))
    with pytest.raises(ValueError, match="4 rows"):
        scatter_mean(src, torch.zeros(3, dtype=torch.long))
    with pytest.raises(TypeError, match="integer"):
        scatter_sum(src, torch.zeros(4))
    with pytest.raises(IndexError, match=r"\[0, 2\)"):
        scatter_sum(src, torch.tensor([0, 1, 2, 0]), dim_size=2)


def test_gradients() -> None:
    g = torch.Generator().manual_seed(0)
    src = torch.randn(7, 3, generator=g, dtype=torch.float64, requires_grad=True)
    index = torch.tensor([0, 2, 2, 0, 3, 3, 3])
    for fn in (scatter_sum, scatter_mean, scatter_max):
        assert torch.autograd.gradcheck(lambda s, fn=fn: fn(s, index, dim_size=5), (src,))


def test_flags_reduce_without_a_bool_scatter() -> None:
    # scatter_all / scatter_any and scatter_max of flags: per-group all / any, empty groups
    # True / False; computed in integer dtypes (CUDA has no bool scatter_reduce kernel)
    flags = torch.tensor([True, False, True, True, False])
    index = torch.tensor([0, 0, 1, 1, 2])
    assert scatter_all(flags, index, 4).tolist() == [False, True, False, True]
    assert scatter_any(flags, index, 4).tolist() == [True, True, False, False]
    out = scatter_max(flags, index, dim_size=4)
    assert out.dtype == torch.bool and out.tolist() == [True, True, False, False]
    assert scatter_all(flags.long(), index, 3).tolist() == [False, True, False]
    with pytest.raises(ValueError, match="equal length"):
        scatter_any(flags, index[:4], 3)

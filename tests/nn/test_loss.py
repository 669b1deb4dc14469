"""PoserNet loss: values at known angles, sign invariance, safe gradients, alpha weighting."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from posernet.nn import PoserNetLoss, posernet_loss

IDENTITY = [1.0, 0.0, 0.0, 0.0]


def rot_x(deg: float) -> list[float]:
    h = math.radians(deg) / 2
    return [math.cos(h), math.sin(h), 0.0, 0.0]


def pose(q: list[float], t: list[float]) -> torch.Tensor:
    return torch.tensor([q + t], dtype=torch.float64)


@pytest.mark.parametrize("deg", [0.0, 30.0, 90.0, 179.0, 180.0])
def test_orientation_term_at_known_angles(deg: float) -> None:
    out = posernet_loss(pose(rot_x(deg), [0, 0, 1]), pose(IDENTITY, [0, 0, 5]))
    assert out.orient.item() == pytest.approx(math.radians(deg), abs=1e-7)
    assert out.tr_dir.item() == pytest.approx(0.0, abs=1e-7)  # direction only: 5 vs 1 is 0 deg


@pytest.mark.parametrize(("t", "deg"), [([1, 0, 0], 0.0), ([0, 1, 0], 90.0),
                                        ([1, 1, 0], 45.0), ([-1, 0, 0], 180.0)])
def test_translation_term_at_known_angles(t: list[float], deg: float) -> None:
    out = posernet_loss(pose(IDENTITY, t), pose(IDENTITY, [3, 0, 0]))
    assert out.tr_dir.item() == pytest.approx(math.radians(deg), abs=1e-7)
    assert out.orient.item() == pytest.approx(0.0, abs=1e-7)


def test_sign_invariance_and_norm_terms() -> None:
    q = rot_x(40.0)
    neg = [-v for v in q]
    a = posernet_loss(pose([2 * v for v in q], [0, 0, 3]), pose(IDENTITY, [0, 0, 1]), alpha=0.5)
    b = posernet_loss(pose([2 * v for v in neg], [0, 0, 3]), pose(IDENTITY, [0, 0, 1]), alpha=0.5)
    assert a.orient.item() == pytest.approx(math.radians(40.0), abs=1e-7)
    torch.testing.assert_close(a.orient, b.orient)
    assert a.q_norm.item() == pytest.approx(1.0)  # |2 - 1|
    assert a.t_norm.item() == pytest.approx(2.0)  # |3 - 1|
    expected = a.orient + a.tr_dir + 0.5 * (a.q_norm + a.t_norm)
    torch.testing.assert_close(a.loss, expected)
    # Default alpha is the paper's 0.1.
    c = posernet_loss(pose([2 * v for v in q], [0, 0, 3]), pose(IDENTITY, [0, 0, 1]))
    torch.testing.assert_close(c.loss, c.orient + c.tr_dir + 0.1 * 3.0)
    assert PoserNetLoss().alpha == 0.1


@pytest.mark.parametrize("deg", [0.0, 180.0])
def test_gradients_finite_at_0_and_180_degrees(deg: float) -> None:
    pred = pose(rot_x(deg), [0, 0, 1]).requires_grad_(True)
    target = pose(IDENTITY, [0, 0, 1] if deg == 0 else [0, 0, -1])
    posernet_loss(pred, target).loss.backward()
    assert torch.isfinite(pred.grad).all()


def test_zero_outputs_have_finite_gradients() -> None:
    pred = torch.zeros(2, 7, dtype=torch.float64, requires_grad=True)
    target = torch.tensor([[*IDENTITY, 0, 0, 1]] * 2, dtype=torch.float64)
    posernet_loss(pred, target).loss.backward()
    assert torch.isfinite(pred.grad).all()


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_loss_is_mean_of_per_edge_losses(seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    pred = torch.randn(5, 7, generator=g, dtype=torch.float64)
    target = torch.randn(5, 7, generator=g, dtype=torch.float64)
    whole = posernet_loss(pred, target).loss
    parts = torch.stack([posernet_loss(pred[i:i + 1], target[i:i + 1]).loss for i in range(5)])
    torch.testing.assert_close(whole, parts.mean())
    w = torch.tensor([1.0, 0, 0, 0, 0], dtype=torch.float64)
    torch.testing.assert_close(posernet_loss(pred, target, weight=w).loss, parts[0])


def test_empty_and_bad_inputs() -> None:
    pred = torch.zeros(0, 7, requires_grad=True)
    out = posernet_loss(pred, torch.zeros(0, 7))
    assert out.loss.item() == 0.0
    out.loss.backward()
    with pytest.raises(ValueError, match=r"\[E, 7\]"):
        posernet_loss(torch.zeros(3, 6), torch.zeros(3, 6))
    with pytest.raises(ValueError, match="weight"):
        posernet_loss(torch.zeros(3, 7), torch.zeros(3, 7), weight=torch.ones(2))


def test_relative_objective_adds_only_the_terms_it_is_given() -> None:
    from posernet.geometry import quaternion_angle
    from posernet.nn.loss import posernet_loss, relative_objective

    g = torch.Generator().manual_seed(0)
    pred, gt, inp = (torch.randn(12, 7, generator=g) for _ in range(3))
    total, out, terms = relative_objective(pred, gt, inp, None, {"alpha": 0.5})
    assert terms == {} and torch.equal(total, posernet_loss(pred, gt, 0.5).loss)
    assert torch.equal(out.loss, total)
    total, _, terms = relative_objective(pred, gt, inp, None,
                                         {"alpha": 0.5, "correction": 0.2, "harm": 0.0})
    corr = quaternion_angle(pred[:, :4], inp[:, :4]).mean()
    assert set(terms) == {"correction"} and torch.allclose(terms["correction"], corr)
    assert torch.allclose(total, posernet_loss(pred, gt, 0.5).loss + 0.2 * corr)

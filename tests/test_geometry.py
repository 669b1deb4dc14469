"""Geometry core: conventions, round trips, algebraic identities, gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from posernet import geometry as G

finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
quat_arrays = arrays(np.float64, (4,), elements=finite).filter(lambda q: np.linalg.norm(q) > 0.1)
vec3 = arrays(np.float64, (3,), elements=st.floats(-5, 5, allow_nan=False))


def rand_quat(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return G.quaternion_normalize(torch.randn(n, 4, generator=g, dtype=torch.float64))


def rand_pose_vec(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed + 1)
    return torch.cat((rand_quat(n, seed), torch.randn(n, 3, generator=g, dtype=torch.float64)), -1)


# --------------------------------------------------------------------------- conventions


def test_quaternion_order_is_scalar_first():
    eye = G.quaternion_to_rotation_matrix(torch.tensor([1.0, 0, 0, 0]))
    assert torch.allclose(eye, torch.eye(3))
    half_z = G.quaternion_to_rotation_matrix(torch.tensor([0.0, 0, 0, 1]))
    assert torch.allclose(half_z, torch.diag(torch.tensor([-1.0, -1.0, 1.0])), atol=1e-7)
    # 90 degrees about x: (cos 45, sin 45, 0, 0) maps y to z.
    s = math.sqrt(0.5)
    Rx = G.quaternion_to_rotation_matrix(torch.tensor([s, s, 0, 0]))
    assert torch.allclose(Rx @ torch.tensor([0.0, 1, 0]), torch.tensor([0.0, 0, 1]), atol=1e-6)


def test_relative_pose_maps_camera_i_points_to_camera_j():
    g = torch.Generator().manual_seed(3)
    R = G.axis_angle_to_rotation_matrix(torch.randn(2, 3, generator=g, dtype=torch.float64))
    t = torch.randn(2, 3, generator=g, dtype=torch.float64)
    T = G.make_se3(R, t)
    X = torch.randn(3, generator=g, dtype=torch.float64)
    x_i = R[0] @ X + t[0]
    x_j = R[1] @ X + t[1]
    T_ij = G.relative_pose(T[0], T[1])
    assert torch.allclose(T_ij[:3, :3] @ x_i + T_ij[:3, 3], x_j)
    # R_ij = R_j R_i^T and t_ij = t_j - R_ij t_i
    assert torch.allclose(T_ij[:3, :3], R[1] @ R[0].T)
    assert torch.allclose(T_ij[:3, 3], t[1] - T_ij[:3, :3] @ t[0])
    # A transposed relative rotation does not map the points (guards the convention).
    assert not torch.allclose(T_ij[:3, :3].T @ x_i + T_ij[:3, 3], x_j, atol=1e-3)


def test_camera_to_world_round_trip():
    T = G.pose_vec_to_matrix(rand_pose_vec(5))
    c2w = G.camera_to_world(T)
    assert torch.allclose(c2w @ T, torch.eye(4, dtype=T.dtype).expand(5, 4, 4), atol=1e-12)
    assert torch.allclose(G.world_to_camera(c2w), T, atol=1e-12)
    # The camera centre is the translation of the camera-to-world pose.
    centre = c2w[:, :3, 3]
    assert torch.allclose((T[:, :3, :3] @ centre[..., None]).squeeze(-1) + T[:, :3, 3],
                          torch.zeros(5, 3, dtype=T.dtype), atol=1e-12)


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("branch", ["w", "x", "y", "z"])
def test_matrix_to_quaternion_each_branch(branch):
    # Rotations near pi about each axis pick a different Shepperd branch.
    axis = {"w": [0.3, 0.2, 0.1], "x": [math.pi - 0.01, 0, 0], "y": [0, math.pi - 0.01, 0],
            "z": [0, 0, math.pi - 0.01]}[branch]
    R = G.axis_angle_to_rotation_matrix(torch.tensor(axis, dtype=torch.float64))
    q = G.rotation_matrix_to_quaternion(R)
    assert q[0] >= 0
    assert torch.allclose(G.quaternion_to_rotation_matrix(q), R, atol=1e-12)


def test_exact_half_turns():
    for R in (torch.diag(torch.tensor([1.0, -1, -1])), torch.diag(torch.tensor([-1.0, 1, -1])),
              torch.diag(torch.tensor([-1.0, -1, 1]))):
        q = G.rotation_matrix_to_quaternion(R.double())
        assert torch.allclose(q.norm(), torch.tensor(1.0, dtype=torch.float64))
        assert torch.allclose(G.quaternion_to_rotation_matrix(q), R.double(), atol=1e-12)
        assert math.isclose(float(G.rotation_angle(R.double())), math.pi, abs_tol=1e-9)


@given(quat_arrays)
@settings(max_examples=200, deadline=None)
def test_quaternion_matrix_round_trip(qn):
    q = G.quaternion_canonical(G.quaternion_normalize(torch.from_numpy(qn)))
    back = G.rotation_matrix_to_quaternion(G.quaternion_to_rotation_matrix(q))
    # A w = 0 quaternion is canonical up to sign; compare rotations then.
    assert torch.allclose(G.quaternion_to_rotation_matrix(back),
                          G.quaternion_to_rotation_matrix(q), atol=1e-10)
    if q[0] > 1e-6:
        assert torch.allclose(back, q, atol=1e-10)


@given(quat_arrays)
@settings(max_examples=100, deadline=None)
def test_rotation_matrix_is_orthonormal(qn):
    R = G.quaternion_to_rotation_matrix(torch.from_numpy(qn))
    assert torch.allclose(R @ R.T, torch.eye(3, dtype=R.dtype), atol=1e-12)
    assert math.isclose(float(torch.linalg.det(R)), 1.0, abs_tol=1e-12)


@given(quat_arrays, quat_arrays)
@settings(max_examples=100, deadline=None)
def test_quaternion_product_matches_matrix_product(a, b):
    qa = G.quaternion_normalize(torch.from_numpy(a))
    qb = G.quaternion_normalize(torch.from_numpy(b))
    lhs = G.quaternion_to_rotation_matrix(G.quaternion_multiply(qa, qb))
    rhs = G.quaternion_to_rotation_matrix(qa) @ G.quaternion_to_rotation_matrix(qb)
    assert torch.allclose(lhs, rhs, atol=1e-12)


@given(quat_arrays, vec3)
@settings(max_examples=100, deadline=None)
def test_quaternion_rotate_matches_matrix(qn, v):
    q, v = torch.from_numpy(qn), torch.from_numpy(v)
    expected = G.quaternion_to_rotation_matrix(q) @ v
    assert torch.allclose(G.quaternion_rotate(G.quaternion_normalize(q), v), expected, atol=1e-10)


@given(quat_arrays)
@settings(max_examples=50, deadline=None)
def test_q_and_minus_q_same_rotation(qn):
    q = torch.from_numpy(qn)
    assert torch.allclose(G.quaternion_to_rotation_matrix(q), G.quaternion_to_rotation_matrix(-q))
    assert float(G.quaternion_angle(q, -q)) < 1e-6


def test_axis_angle_round_trip_and_angle():
    v = torch.randn(200, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    v = v / v.norm(dim=-1, keepdim=True) * torch.linspace(0, math.pi - 1e-6, 200)[:, None]
    R = G.axis_angle_to_rotation_matrix(v)
    assert torch.allclose(G.rotation_matrix_to_axis_angle(R), v, atol=1e-7)
    assert torch.allclose(G.rotation_angle(R), v.norm(dim=-1), atol=1e-9)


# --------------------------------------------------------------------------- SE(3)


def test_pose_vec_inverse_and_composition():
    a, b = rand_pose_vec(50, 1), rand_pose_vec(50, 2)
    Ta, Tb = G.pose_vec_to_matrix(a), G.pose_vec_to_matrix(b)
    assert torch.allclose(G.pose_vec_to_matrix(G.compose_pose_vec(a, b)), Ta @ Tb, atol=1e-12)
    assert torch.allclose(G.pose_vec_to_matrix(G.invert_pose_vec(a)), G.invert_se3(Ta),
                          atol=1e-12)
    ident = G.compose_pose_vec(a, G.invert_pose_vec(a))
    assert torch.allclose(ident, torch.tensor([1.0, 0, 0, 0, 0, 0, 0], dtype=a.dtype).expand(50, 7),
                          atol=1e-12)
    # (a b)^-1 = b^-1 a^-1
    lhs = G.invert_pose_vec(G.compose_pose_vec(a, b))
    rhs = G.compose_pose_vec(G.invert_pose_vec(b), G.invert_pose_vec(a))
    assert torch.allclose(lhs, rhs, atol=1e-12)


def test_matrix_pose_vec_round_trip_is_canonical():
    p = rand_pose_vec(30)
    back = G.matrix_to_pose_vec(G.pose_vec_to_matrix(p))
    assert bool((back[:, 0] >= 0).all())
    assert torch.allclose(back, torch.cat((G.quaternion_canonical(p[:, :4]), p[:, 4:]), -1),
                          atol=1e-12)


def test_relative_pose_vec_of_the_reverse_edge_is_the_inverse():
    T = G.pose_vec_to_matrix(rand_pose_vec(2, 5))
    fwd = G.relative_pose_vec(T[0], T[1])
    bwd = G.relative_pose_vec(T[1], T[0])
    assert torch.allclose(G.invert_pose_vec(fwd), bwd, atol=1e-12)


def test_batch_shapes():
    p = rand_pose_vec(6).reshape(2, 3, 7)
    assert G.pose_vec_to_matrix(p).shape == (2, 3, 4, 4)
    assert G.matrix_to_pose_vec(G.pose_vec_to_matrix(p)).shape == (2, 3, 7)
    assert G.rotation_error_deg(p[..., :4], p[..., :4]).shape == (2, 3)


@pytest.mark.parametrize(
    "fn,arg",
    [(G.quaternion_to_rotation_matrix, torch.zeros(3)),
     (G.rotation_matrix_to_quaternion, torch.zeros(3, 4)),
     (G.invert_pose_vec, torch.zeros(6)),
     (G.invert_se3, torch.zeros(3, 3))],
)
def test_bad_shapes_raise_clear_errors(fn, arg):
    with pytest.raises(ValueError, match="must have shape"):
        fn(arg)


# --------------------------------------------------------------------------- errors


def test_rotation_error_at_known_angles():
    for deg in (0.0, 1.0, 45.0, 90.0, 179.0, 180.0):
        R = G.axis_angle_to_rotation_matrix(torch.tensor([0.0, 0.0, math.radians(deg)],
                                                         dtype=torch.float64))
        q = G.rotation_matrix_to_quaternion(R)
        ident = torch.tensor([1.0, 0, 0, 0], dtype=torch.float64)
        assert math.isclose(float(G.rotation_error_deg(q, ident)), deg, abs_tol=1e-6)
        assert math.isclose(float(G.rotation_error_deg(-q, ident)), deg, abs_tol=1e-6)


def test_translation_direction_error():
    a = torch.tensor([[1.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0], [0, 2.0, 0]])
    b = torch.tensor([[3.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0], [0, 0.5, 0.5]])
    err = G.translation_direction_error_deg(a, b)
    assert torch.allclose(err, torch.tensor([0.0, 90.0, 180.0, 45.0]), atol=1e-4)


def test_gradients_are_finite_at_zero_and_half_turn():
    ident = torch.tensor([1.0, 0, 0, 0], dtype=torch.float64)
    for q0 in ([1.0, 0, 0, 0], [0.0, 0, 0, 1], [-1.0, 0, 0, 0]):
        q = torch.tensor(q0, dtype=torch.float64, requires_grad=True)
        G.quaternion_angle(q, ident).backward()
        assert torch.isfinite(q.grad).all()
    for t0 in ([1.0, 0, 0], [-1.0, 0, 0]):
        t = torch.tensor(t0, dtype=torch.float64, requires_grad=True)
        G.angle_between_vectors(t, torch.tensor([1.0, 0, 0], dtype=torch.float64)).backward()
        assert torch.isfinite(t.grad).all()


def test_gradcheck():
    q = rand_quat(4, 7).requires_grad_()
    q_gt = rand_quat(4, 8)
    assert torch.autograd.gradcheck(lambda x: G.quaternion_angle(x, q_gt), (q,))
    t = torch.randn(4, 3, dtype=torch.float64, requires_grad=True)
    t_gt = torch.randn(4, 3, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: G.angle_between_vectors(x, t_gt), (t,))
    p = rand_pose_vec(3, 9).requires_grad_()
    assert torch.autograd.gradcheck(G.pose_vec_to_matrix, (p,))
    assert torch.autograd.gradcheck(G.invert_pose_vec, (p,))
    R = G.quaternion_to_rotation_matrix(rand_quat(3, 10)).requires_grad_()
    # Gradient w.r.t. a rotation matrix is only meaningful along the manifold, but the formula
    # must still be differentiable almost everywhere.
    assert torch.autograd.gradcheck(G.rotation_matrix_to_quaternion, (R,))


def test_project_to_so3_matches_the_svd_projection():
    gen = torch.Generator().manual_seed(0)
    A = torch.randn(200, 3, 3, generator=gen, dtype=torch.float64)
    A[:5] = -A[:5].abs()  # some with det <= 0 take the SVD fallback
    R = G.project_to_so3(A)
    U, _, Vh = torch.linalg.svd(A)
    d = torch.sign(torch.linalg.det(U @ Vh))
    U = torch.cat((U[..., :2], U[..., 2:] * d[:, None, None]), dim=-1)
    torch.testing.assert_close(R, U @ Vh, atol=1e-9, rtol=0)
    torch.testing.assert_close(R @ R.mT, torch.eye(3, dtype=R.dtype).expand_as(R), atol=1e-12,
                               rtol=0)
    torch.testing.assert_close(G.det3(R), torch.ones(200, dtype=R.dtype))
    assert G.project_to_so3(A[:0].reshape(0, 3, 3)).shape == (0, 3, 3)


def test_raw_pose_inverse_and_symmetric_mean_live_in_geometry():
    gen = torch.Generator().manual_seed(1)
    a, b = torch.randn(2, 6, 7, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(G.invert_pose_raw(G.invert_pose_raw(a)), a)
    m = G.symmetric_pose_mean(a, b, a)
    torch.testing.assert_close(G.symmetric_pose_mean(b, a, a), m)

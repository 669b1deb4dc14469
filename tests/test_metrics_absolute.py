"""Absolute-pose metrics: Umeyama alignment and per-graph rotation/position errors."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from posernet.geometry import (
    axis_angle_to_rotation_matrix,
    invert_se3,
    make_se3,
    umeyama_alignment,
)
from posernet.metrics import absolute_pose_errors, absolute_pose_errors_per_camera, threshold_row
from posernet.testing import random_absolute_poses

F64 = torch.float64
vec3 = st.lists(st.floats(-3, 3, allow_nan=False), min_size=3, max_size=3)


def similarity(rotvec, trans, scale):
    R = axis_angle_to_rotation_matrix(torch.tensor(rotvec, dtype=F64))
    return R, torch.tensor(trans, dtype=F64), float(scale)


def transform_poses(P, R, t, s):
    """World-to-camera poses of the same cameras after the world moves by X' = s R X + t."""
    Rc, tc = P[:, :3, :3], P[:, :3, 3]
    c = -(Rc.mT @ tc[..., None]).squeeze(-1)
    c2 = s * (R @ c[..., None]).squeeze(-1) + t
    R2 = Rc @ R.mT
    return make_se3(R2, -(R2 @ c2[..., None]).squeeze(-1))


@settings(max_examples=25, deadline=None)
@given(vec3, vec3, st.floats(0.1, 10.0), st.integers(3, 12), st.integers(0, 10_000))
def test_umeyama_recovers_a_similarity(rotvec, trans, scale, k, seed):
    g = torch.Generator().manual_seed(seed)
    src = torch.randn(k, 3, generator=g, dtype=F64)
    R, t, s = similarity(rotvec, trans, scale)
    dst = s * src @ R.T + t
    s_, R_, t_ = umeyama_alignment(src, dst)
    assert abs(float(s_) - s) < 1e-8 * s
    torch.testing.assert_close(R_, R, atol=1e-8, rtol=0)
    torch.testing.assert_close(t_, t, atol=1e-7, rtol=0)
    s1, _, _ = umeyama_alignment(src, dst, with_scale=False)
    assert float(s1) == 1.0


def test_umeyama_batched_with_mask_equals_unbatched():
    g = torch.Generator().manual_seed(0)
    src = torch.randn(4, 7, 3, generator=g, dtype=F64)
    dst = torch.randn(4, 7, 3, generator=g, dtype=F64)
    mask = torch.rand(4, 7, generator=g) > 0.3
    mask[:, :3] = True
    s, R, t = umeyama_alignment(src, dst, mask=mask)
    for b in range(4):
        sb, Rb, tb = umeyama_alignment(src[b][mask[b]], dst[b][mask[b]])
        torch.testing.assert_close((s[b], R[b], t[b]), (sb, Rb, tb))
    assert torch.allclose(torch.linalg.det(R), torch.ones(4, dtype=F64))
    with pytest.raises(ValueError, match=r"\[..., K, 3\]"):
        umeyama_alignment(src[..., :2], dst[..., :2])


@settings(max_examples=20, deadline=None)
@given(vec3, vec3, st.floats(0.2, 5.0), st.integers(0, 10_000))
def test_gauge_invariance_of_errors(rotvec, trans, scale, seed):
    """Moving the ground truth's world by any similarity changes nothing after similarity
    alignment (and any rigid motion nothing after rigid alignment)."""
    g = torch.Generator().manual_seed(seed)
    gt = random_absolute_poses(12, g, F64)
    noise = make_se3(axis_angle_to_rotation_matrix(0.05 * torch.randn(12, 3, generator=g,
                                                                      dtype=F64)),
                     0.1 * torch.randn(12, 3, generator=g, dtype=F64))
    est = noise @ gt
    batch = torch.tensor([0] * 5 + [1] * 7)
    R, t, s = similarity(rotvec, trans, scale)
    base = absolute_pose_errors(est, gt, batch, 2, "similarity")
    moved = absolute_pose_errors(est, transform_poses(gt, R, t, s), batch, 2, "similarity")
    # Position errors scale with the world: compare after undoing the scale.
    torch.testing.assert_close(moved[0], base[0], atol=1e-7, rtol=0)
    torch.testing.assert_close(moved[1] / s, base[1], atol=1e-9, rtol=1e-7)
    rigid = absolute_pose_errors(est, transform_poses(gt, R, t, 1.0), batch, 2, "rigid")
    torch.testing.assert_close(rigid, absolute_pose_errors(est, gt, batch, 2, "rigid"),
                               atol=1e-7, rtol=0)
    # The estimate's own gauge does not matter either.
    est_moved = transform_poses(est, R, t, s)
    torch.testing.assert_close(absolute_pose_errors(est_moved, gt, batch, 2), base,
                               atol=1e-7, rtol=1e-7)


def test_known_errors_and_rigid_vs_similarity():
    g = torch.Generator().manual_seed(1)
    gt = random_absolute_poses(6, g, F64)
    est = transform_poses(gt, torch.eye(3, dtype=F64), torch.zeros(3, dtype=F64), 2.0)
    batch = torch.zeros(6, dtype=torch.long)
    rot, pos = absolute_pose_errors(est, gt, batch, 1, "similarity")
    assert float(rot[0]) < 1e-9 and float(pos[0]) < 1e-12
    _, pos_rigid = absolute_pose_errors(est, gt, batch, 1, "rigid")
    assert float(pos_rigid[0]) > 0.1
    # One camera rotated by 10 degrees about its own centre: with the centres' alignment its
    # rotation error is 10 deg (the rotation gauge would spread part of it over the others).
    est = gt.clone()
    est[0] = make_se3(axis_angle_to_rotation_matrix(torch.tensor([0, 0, math.radians(10)],
                                                                 dtype=F64)),
                      torch.zeros(3, dtype=F64)) @ gt[0]
    r, p = absolute_pose_errors_per_camera(est, gt, batch, 1, "rigid", rotation_gauge="centres")
    assert abs(float(r[0]) - 10.0) < 1e-6 and float(r[1:].max()) < 1e-6
    assert float(p.max()) < 1e-9


def test_degenerate_centres_use_rotations_for_alignment():
    """Two cameras (or collinear ones) do not fix the rotation about their baseline; the
    rotation is then aligned from the cameras' rotations, so exact estimates stay exact."""
    g = torch.Generator().manual_seed(2)
    gt = random_absolute_poses(3, g, F64)
    c = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [2.5, 0, 0]], dtype=F64)
    R = gt[:, :3, :3]
    gt = make_se3(R, -(R @ c[..., None]).squeeze(-1))
    T = make_se3(axis_angle_to_rotation_matrix(torch.tensor([0.3, -1.0, 0.2], dtype=F64)),
                 torch.tensor([1.0, 2.0, 3.0], dtype=F64))
    est = gt @ invert_se3(T)
    for idx in (slice(0, 2), slice(0, 3)):
        n = len(range(3)[idx])
        r, p = absolute_pose_errors(est[idx], gt[idx], torch.zeros(n, dtype=torch.long), 1,
                                    "similarity")
        assert float(r[0]) < 1e-6 and float(p[0]) < 1e-9


def test_components_valid_mask_and_nan_handling():
    g = torch.Generator().manual_seed(3)
    gt = random_absolute_poses(8, g, F64)
    T = make_se3(axis_angle_to_rotation_matrix(torch.tensor([0.5, 0.1, -0.3], dtype=F64)),
                 torch.tensor([3.0, 0, 1], dtype=F64))
    est = gt.clone()
    est[4:8] = gt[4:8] @ T  # second component in its own gauge
    est[7] = torch.eye(4, dtype=F64)  # an isolated, unlocalised camera
    batch = torch.zeros(8, dtype=torch.long)
    comp = torch.tensor([0, 0, 0, 0, 1, 1, 1, 2])
    valid = torch.tensor([True] * 7 + [False])
    rot, pos = absolute_pose_errors(est, gt, batch, 1, "rigid", component=comp, valid=valid)
    assert float(rot[0]) < 1e-6 and float(pos[0]) < 1e-9
    rot_w, _ = absolute_pose_errors(est, gt, batch, 1, "rigid", valid=valid)
    assert float(rot_w[0]) > 1.0  # one alignment for the whole graph cannot fit both parts
    r, _ = absolute_pose_errors_per_camera(est, gt, comp, 3, valid=valid)
    assert torch.isnan(r[7]) and not torch.isnan(r[:7]).any()
    none_valid = absolute_pose_errors(est, gt, batch, 1, valid=torch.zeros(8, dtype=torch.bool))
    assert torch.isnan(none_valid[0]).all()
    assert threshold_row(none_valid[0]).count == 0


def test_bad_inputs():
    gt = random_absolute_poses(4, torch.Generator().manual_seed(4), F64)
    b = torch.zeros(4, dtype=torch.long)
    with pytest.raises(ValueError, match="alignment="):
        absolute_pose_errors(gt, gt, b, 1, alignment="affine")
    with pytest.raises(ValueError, match=r"\[N, 4, 4\]"):
        absolute_pose_errors(gt[:3], gt, b, 1)
    bad = gt.clone()
    bad[1, 0, 3] = float("nan")
    with pytest.raises(ValueError, match="pose_est has a NaN"):
        absolute_pose_errors(bad, gt, b, 1)


def test_rotation_gauge_rotations_ignores_bad_positions():
    # Exact rotations but scrambled camera centres: the centre alignment turns the rotation
    # error large, the rotation gauge measures the rotations alone (zero error).
    from posernet.metrics import absolute_pose_errors

    gen = torch.Generator().manual_seed(0)
    gt = random_absolute_poses(8, gen, torch.float64)
    Q = make_se3(torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))[0],
                 torch.zeros(3, dtype=torch.float64))
    Q[:3, :3] *= torch.sign(torch.linalg.det(Q[:3, :3]))
    est = gt @ Q  # same cameras in a rotated world frame
    est[:, :3, 3] = torch.randn(8, 3, generator=gen, dtype=torch.float64) * 3  # bad positions
    nb = torch.zeros(8, dtype=torch.long)
    rot_c, _ = absolute_pose_errors(est, gt, nb, 1, rotation_gauge="centres")
    rot_r, pos_r = absolute_pose_errors(est, gt, nb, 1)  # default: rotations
    assert float(rot_r[0]) < 1e-6
    assert float(rot_c[0]) > 5.0
    assert float(pos_r[0]) > 0.1
    with pytest.raises(ValueError, match="rotation_gauge"):
        absolute_pose_errors(est, gt, nb, 1, rotation_gauge="mean")


@pytest.mark.parametrize("gauge", ["rotations", "centres"])
@pytest.mark.parametrize("alignment", ["similarity", "rigid"])
@pytest.mark.parametrize("n", [8, 2])  # 2: centres cannot fix the rotation (degenerate path)
def test_aligned_poses_show_the_errors_the_metrics_report(gauge: str, alignment: str, n: int):
    from posernet.geometry import rotation_angle
    from posernet.metrics import align_to_ground_truth

    gen = torch.Generator().manual_seed(3)
    gt = random_absolute_poses(n, gen, F64)
    R, t, s = similarity([0.4, -1.0, 2.0], [1.0, -2.0, 0.5], 1.7)
    noise = random_absolute_poses(n, gen, F64)
    noise[:, :3, :3] = torch.linalg.matrix_exp(0.1 * (noise[:, :3, :3] - noise[:, :3, :3].mT))
    noise[:, :3, 3] *= 0.05
    est = noise @ transform_poses(gt, R, t, s)  # another frame, noisy cameras
    aligned = align_to_ground_truth(est, gt, rotation_gauge=gauge, alignment=alignment)
    rot = torch.rad2deg(rotation_angle(gt[:, :3, :3] @ aligned[:, :3, :3].mT))
    pos = (invert_se3(aligned)[:, :3, 3] - invert_se3(gt)[:, :3, 3]).norm(dim=-1)
    want_rot, want_pos = absolute_pose_errors_per_camera(
        est, gt, torch.zeros(n, dtype=torch.long), 1, alignment=alignment, rotation_gauge=gauge)
    torch.testing.assert_close(rot, want_rot)
    torch.testing.assert_close(pos, want_pos)
    assert float(rot.max()) > 0.5  # the noise shows, nothing was aligned away

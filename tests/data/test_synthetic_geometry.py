"""Simulator geometry: boxes contain their objects, occlusion, GT poses, 5-point on clean points."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from posernet.data.synthetic import SceneWorld, load_preset, simulate_graphs
from posernet.data.synthetic.camera import (
    cuboid_corners,
    intrinsics,
    look_at,
    project,
    projected_boxes,
    rotation_z,
)
from posernet.data.synthetic.scenes import OBJECT, Scene
from posernet.data.synthetic.visibility import observe
from posernet.frontend.relpose import five_point
from posernet.geometry import (
    make_se3,
    matrix_to_pose_vec,
    pose_vec_to_matrix,
    relative_pose_vec,
    rotation_error_deg,
    translation_direction_error_deg,
)

K = intrinsics(585.0, 640, 480)


def _pose(centre, target, roll=0.0):
    return look_at(np.asarray([centre], float), np.asarray([target], float), np.array([roll]))[0]


@settings(max_examples=40, deadline=None)
@given(
    cx=st.floats(-1.5, 1.5),
    cy=st.floats(-1.5, 1.5),
    cz=st.floats(-0.3, 4.0),
    hx=st.floats(0.05, 1.0),
    hy=st.floats(0.05, 1.0),
    hz=st.floats(0.05, 1.0),
    yaw=st.floats(-3.1, 3.1),
    seed=st.integers(0, 1000),
)
def test_projected_box_contains_every_visible_part(cx, cy, cz, hx, hy, hz, yaw, seed):
    # camera at the origin looking along +z of the world (world = camera frame here)
    centre = np.array([[cx, cy, cz]])
    half = np.array([[hx, hy, hz]])
    R = rotation_z(np.array([yaw]))
    corners = cuboid_corners(centre, half, R)
    near = 0.1
    box, valid = projected_boxes(corners, K, 640, 480, near)
    # random points inside the cuboid (surface and volume) in front of the near plane
    rng = np.random.default_rng(seed)
    local = rng.uniform(-1, 1, size=(500, 3)) * half
    pts = local @ R[0].T + centre
    front = pts[:, 2] > near
    uv = project(pts[front], K)
    inside_img = (uv[:, 0] >= 0) & (uv[:, 0] <= 640) & (uv[:, 1] >= 0) & (uv[:, 1] <= 480)
    uv = uv[inside_img]
    if uv.size:
        assert valid[0]
        b = box[0]
        tol = 1e-6
        assert (uv[:, 0] >= b[0] - tol).all() and (uv[:, 0] <= b[2] + tol).all()
        assert (uv[:, 1] >= b[1] - tol).all() and (uv[:, 1] <= b[3] + tol).all()
    if valid[0]:
        assert 0 <= box[0, 0] < box[0, 2] <= 640 and 0 <= box[0, 1] < box[0, 3] <= 480


def test_box_behind_camera_is_invalid():
    corners = cuboid_corners(
        np.array([[0.0, 0.0, -2.0]]), np.array([[0.3, 0.3, 0.3]]), rotation_z(np.zeros(1))
    )
    _, valid = projected_boxes(corners, K, 640, 480, 0.1)
    assert not valid[0]


def test_look_at_is_a_rigid_pose_facing_the_target():
    T = _pose([1.0, -2.0, 1.5], [2.0, 1.0, 0.5], roll=0.1)
    R = T[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    target_cam = T[:3, :3] @ np.array([2.0, 1.0, 0.5]) + T[:3, 3]
    np.testing.assert_allclose(target_cam[:2], 0.0, atol=1e-9)  # on the optical axis
    assert target_cam[2] > 0
    T0 = _pose([0, 0, 1.0], [0, 2.0, 1.0])
    up = T0[:3, :3] @ np.array([0, 0, 1.0])
    assert up[1] < -0.99  # world up is image up (camera -y)


def _two_box_scene() -> Scene:
    """A small box right in front of a larger one, seen along +y."""
    centre = np.array([[0.0, 2.0, 1.0], [0.0, 4.0, 1.0]])
    half = np.array([[0.2, 0.2, 0.2], [0.5, 0.5, 0.5]])
    yaw = np.zeros(2)
    # one keypoint at the centre of each box's face that looks at the camera (-y)
    kp = np.array([[0.0, 1.8, 1.0], [0.0, 3.5, 1.0], [0.45, 3.5, 1.45]])
    normal = np.tile([0.0, -1.0, 0.0], (3, 1))
    return Scene(
        name="two",
        room=np.array([4.0, 6.0, 3.0]),
        capture_lo=np.zeros(3),
        capture_hi=np.ones(3),
        centre=centre,
        half=half,
        yaw=yaw,
        kind=np.array([OBJECT, OBJECT]),
        kp_xyz=kp,
        kp_normal=normal,
        kp_owner=np.array([0, 1, 1]),
        kp_twin=np.full(3, -1),
        twin_of=np.full(2, -1),
    )


def test_occluded_keypoints_are_hidden():
    scene = _two_box_scene()
    T = _pose([0.0, 0.0, 1.0], [0.0, 4.0, 1.0])
    v = observe(scene, T, K, 640, 480, 0.1, 10.0)
    # keypoint 1 (centre of the far box) is behind the near box; keypoint 2 peeks out
    assert list(v.kp_ids) == [0, 2]
    assert v.obj_visible[0] == 1.0 and v.obj_visible[1] == pytest.approx(0.5)
    # seen from the side, the far box's centre is visible again
    T2 = _pose([1.5, 0.5, 1.0], [0.0, 3.5, 1.0])
    assert 1 in observe(scene, T2, K, 640, 480, 0.1, 10.0).kp_ids


@pytest.fixture(scope="module")
def tiny_graphs():
    opts = load_preset("tiny")
    return simulate_graphs(opts, scene="chess", split="test", size="small", count=2, seed=1)


def test_ground_truth_relative_poses_agree_with_absolute_poses(tiny_graphs):
    for g in tiny_graphs:
        g.validate()
        T = g.pose_gt.double()
        R = T[:, :3, :3]
        eye = torch.eye(3, dtype=torch.float64).expand_as(R)
        assert torch.allclose(R @ R.transpose(1, 2), eye, atol=1e-5)
        expect = relative_pose_vec(T[g.edge_index[0]], T[g.edge_index[1]])
        gt = g.edge_pose_gt.double()
        assert rotation_error_deg(gt[:, :4], expect[:, :4]).max() < 1e-2
        assert torch.allclose(gt[:, 4:], expect[:, 4:], atol=1e-5)
        # x_j = R_ij x_i + t_ij maps a world point seen from camera i into camera j
        X = torch.tensor([0.3, 2.5, 0.8], dtype=torch.float64)
        e = 0
        i, j = g.edge_index[:, e]
        xi = T[i, :3, :3] @ X + T[i, :3, 3]
        xj = T[j, :3, :3] @ X + T[j, :3, 3]
        Tij = pose_vec_to_matrix(gt[e])
        assert torch.allclose(Tij[:3, :3] @ xi + Tij[:3, 3], xj, atol=1e-4)


def test_estimates_are_unit_finite_and_edge_pose_is_kp(tiny_graphs):
    for g in tiny_graphs:
        assert set(g.estimates) == {"kp", "bb"}
        for est in g.estimates.values():
            assert torch.isfinite(est).all()
            assert torch.allclose(est[:, 4:].norm(dim=-1), torch.ones(g.num_edges), atol=1e-5)
        assert torch.equal(g.edge_pose, g.estimates["kp"])
        assert g.image_size.tolist()[0] == [640.0, 480.0]
        assert g.K[0, 0, 0] == 585.0 and g.K[0, 0, 2] == 320.0 and g.K[0, 1, 2] == 240.0
        assert {"name", "scene", "split", "size"} <= set(g.meta)


def test_five_point_on_noise_free_keypoints_recovers_the_true_pose():
    opts = load_preset("tiny")
    world = SceneWorld(opts, "chess", seed=0)
    checked = 0
    frames = world.pools["train"].frames
    for a in frames[::7]:
        b = a + 4  # same sequence, a few frames later: a real baseline, lots of overlap
        if b not in frames:
            continue
        fa, fb = world.frame(a), world.frame(b)
        common, ia, ib = np.intersect1d(fa.kp_ids, fb.kp_ids, return_indices=True)
        Tij = relative_pose_vec(torch.from_numpy(fa.w2c), torch.from_numpy(fb.w2c))
        if common.size < 30 or float(Tij[4:].norm()) < 0.05:
            continue
        est = five_point(fa.kp_uv_true[ia], fb.kp_uv_true[ib], world.K, threshold=0.5, seed=int(a))
        assert est is not None
        R, t = est
        q = matrix_to_pose_vec(make_se3(torch.from_numpy(R), torch.from_numpy(t)))
        assert float(rotation_error_deg(q[:4], Tij[:4])) < 0.2
        assert float(translation_direction_error_deg(q[4:], Tij[4:])) < 1.0
        checked += 1
        if checked == 4:
            break
    assert checked >= 2


def test_five_point_failure_is_none_not_nan():
    rng = np.random.default_rng(0)
    p = rng.uniform(0, 640, size=(4, 2))
    assert five_point(p, p + 1.0, K) is None  # fewer than five points
    same = rng.uniform(0, 640, size=(20, 2))
    out = five_point(same, same, K)  # no motion at all: degenerate
    assert out is None or (np.isfinite(out[0]).all() and np.isfinite(out[1]).all())


def test_detections_follow_the_detector_rules():
    opts = load_preset("tiny")
    world = SceneWorld(opts, "chess", seed=0)
    W, H = opts.camera.width, opts.camera.height
    for fid in world.pools["train"].frames[:20:4]:
        det = world.frame(fid).det
        b = det.boxes
        assert len(b) <= opts.detector.max_boxes
        assert (b[:, 0] >= 0).all() and (b[:, 2] <= W).all()
        assert (b[:, 1] >= 0).all() and (b[:, 3] <= H).all()
        area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
        assert (area <= opts.detector.max_area * W * H + 1e-6).all()
        assert (np.diff(det.score) <= 0).all()  # best first

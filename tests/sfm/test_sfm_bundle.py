"""Robust bundle adjustment and the SfM orchestrator on synthetic scenes."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from posernet.metrics import absolute_pose_errors_per_camera
from posernet.sfm import (
    BundleOptions,
    bundle_adjust,
    bundle_adjust_reconstruction,
    gauge_cameras,
    triangulate_tracks,
)
from posernet.sfm.bundle import _Problem
from posernet.sfm.synthetic import make_scene, perturb_poses


def _pose_errors(est: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    """Largest rotation (deg) and position error after a similarity alignment (the metrics')."""
    g = torch.zeros(est.shape[0], dtype=torch.long)
    rot, pos = absolute_pose_errors_per_camera(torch.from_numpy(est), torch.from_numpy(gt), g, 1)
    return float(rot.max()), float(pos.max())


def _with_outliers(xy: np.ndarray, frac: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    out = rng.uniform(size=len(xy)) < frac
    xy = xy.copy()
    xy[out] += rng.uniform(15, 60, (out.sum(), 2)) * rng.choice([-1, 1], (out.sum(), 2))
    return xy, out


@pytest.fixture(scope="module")
def scene():
    return make_scene(num_cameras=8, num_points=300, noise_px=0.5, seed=11)


def test_jacobian_matches_finite_differences(scene) -> None:
    w0 = perturb_poses(scene.w2c, 2.0, 0.05, seed=1)
    for focal in ("none", "shared", "per_camera"):
        prob = _Problem(w0, scene.points, scene.K, scene.xy[:400], scene.obs_image[:400],
                        scene.obs_point[:400], np.array([0]), focal)
        x = prob.x0() + np.random.default_rng(0).normal(0, 1e-2, prob.n_params)
        J = prob.jacobian(x).toarray()
        eps = 1e-6
        cols = np.random.default_rng(1).choice(prob.n_params, 40, replace=False)
        for k in cols:
            d = np.zeros_like(x)
            d[k] = eps
            num = (prob.residuals(x + d) - prob.residuals(x - d)) / (2 * eps)
            np.testing.assert_allclose(J[:, k], num, atol=1e-4 * max(1.0, np.abs(num).max()))


@pytest.mark.parametrize("loss", ["cauchy", "huber", "soft_l1"])
def test_ba_recovers_perturbed_poses_with_outliers(scene, loss: str) -> None:
    w0 = perturb_poses(scene.w2c, 3.0, 0.10, seed=2)
    xy, out = _with_outliers(scene.xy, 0.10, seed=3)
    tri = triangulate_tracks(xy, scene.obs_point, scene.obs_image, 300, scene.K, w0,
                             max_reproj_px=np.inf, min_angle_deg=0.0)
    assert _pose_errors(w0, scene.w2c)[0] > 2.0
    res = bundle_adjust(w0, tri.points, scene.K, xy, scene.obs_image, scene.obs_point,
                        BundleOptions(loss=loss, f_scale=2.0))
    assert res.converged and res.accepted, res.message
    rot, pos = _pose_errors(res.w2c, scene.w2c)
    assert rot < 0.1 and pos < 0.02, (rot, pos)  # cameras ~4 units from the scene centre
    assert np.median(res.errors[~out]) < 0.7  # the noise level (0.5 px per axis)
    assert res.final_cost < res.initial_cost
    assert res.median_error_after < res.median_error_before
    assert res.fixed_cameras.size == 1
    # The gauge camera did not move.
    g = res.fixed_cameras[0]
    np.testing.assert_allclose(res.w2c[g], w0[g], atol=1e-12)
    assert "global scale" in "\n".join(res.lines())


def test_ba_stops_when_the_cameras_no_longer_move() -> None:
    """``camera_tol``: once a step lowers the cost by < 10 x irls_tol and moves no camera by
    more than camera_tol, the adjustment stops; it takes fewer steps than the cost rule alone
    and ends where that rule ends, far inside the pose error (0.08 deg). A start that slides
    (cameras still moving) does not stop: see test_positioning_start_undoes_a_collapse."""
    sc = make_scene(num_cameras=16, num_points=600, noise_px=1.0, seed=11)
    w0 = perturb_poses(sc.w2c, 3.0, 0.10, seed=2)
    tri = triangulate_tracks(sc.xy, sc.obs_point, sc.obs_image, 600, sc.K, w0,
                             max_reproj_px=np.inf, min_angle_deg=0.0)
    res = {tol: bundle_adjust(w0, tri.points, sc.K, sc.xy, sc.obs_image, sc.obs_point,
                              BundleOptions(camera_tol=tol)) for tol in (0.0, 1e-4)}
    assert all(r.converged and r.accepted for r in res.values())
    assert res[1e-4].iterations < res[0.0].iterations
    np.testing.assert_allclose(res[1e-4].w2c, res[0.0].w2c, atol=1e-4)
    for r in res.values():
        rot, pos = _pose_errors(r.w2c, sc.w2c)
        assert rot < 0.15 and pos < 0.02, (rot, pos)


def test_ba_observation_order_does_not_matter(scene) -> None:
    w0 = perturb_poses(scene.w2c, 1.0, 0.02, seed=4)
    perm = np.random.default_rng(0).permutation(len(scene.xy))
    opts = BundleOptions(loss="huber")
    a = bundle_adjust(w0, scene.points, scene.K, scene.xy, scene.obs_image, scene.obs_point,
                      opts)
    b = bundle_adjust(w0, scene.points, scene.K, scene.xy[perm], scene.obs_image[perm],
                      scene.obs_point[perm], opts)
    assert a.accepted and b.accepted
    np.testing.assert_allclose(b.errors, a.errors[perm], atol=1e-6)
    np.testing.assert_allclose(b.w2c, a.w2c, atol=1e-8)


def test_ba_refines_shared_focal(scene) -> None:
    K_bad = scene.K.copy()
    K_bad[:, :2, :2] *= 1.04
    res = bundle_adjust(scene.w2c, scene.points, K_bad, scene.xy, scene.obs_image,
                        scene.obs_point, BundleOptions(refine_focal="shared", loss="linear"))
    assert res.accepted, res.message
    np.testing.assert_allclose(res.K[:, 0, 0], scene.K[:, 0, 0], rtol=5e-3)
    np.testing.assert_allclose(res.K[:, :2, 2], scene.K[:, :2, 2])


def test_ba_failures_keep_input(scene) -> None:
    w0 = perturb_poses(scene.w2c, 3.0, 0.10, seed=2)
    pts = scene.points
    args = (scene.K, scene.xy, scene.obs_image, scene.obs_point)
    empty = bundle_adjust(w0, pts, scene.K, np.zeros((0, 2)), np.zeros(0, int),
                          np.zeros(0, int))
    assert not empty.accepted and not empty.converged and "no observations" in empty.message
    np.testing.assert_array_equal(empty.w2c, w0)
    bad = w0.copy()
    bad[3, 0, 3] = np.nan
    nan = bundle_adjust(bad, pts, *args)
    assert not nan.accepted and "non-finite" in nan.message
    np.testing.assert_array_equal(nan.w2c[[0, 1, 2, 4]], w0[[0, 1, 2, 4]])
    bad_pts = pts.copy()
    bad_pts[5] = np.inf
    assert "non-finite" in bundle_adjust(w0, bad_pts, *args).message
    short = bundle_adjust(w0, pts, *args, BundleOptions(max_nfev=2))
    assert not short.converged and not short.accepted and "max_nfev" in short.message
    np.testing.assert_array_equal(short.w2c, w0)
    np.testing.assert_array_equal(short.points, pts)
    assert short.iterations <= 3
    # Opting in keeps the improved but unconverged solution.
    loose = bundle_adjust(w0, pts, *args, BundleOptions(max_nfev=4, accept_unconverged=True))
    assert loose.accepted and not loose.converged
    assert loose.final_cost < loose.initial_cost
    with pytest.raises(ValueError, match="out of range"):
        bundle_adjust(w0, pts, scene.K, scene.xy, scene.obs_image, scene.obs_point + 1000)
    with pytest.raises(ValueError, match="loss"):
        BundleOptions(loss="l2")


def test_gauge_one_camera_per_component() -> None:
    # Cameras 0,1 share point 0; cameras 2,3 share point 1; camera 4 sees nothing.
    img = np.array([0, 1, 1, 2, 3, 3])
    pt = np.array([0, 0, 0, 1, 1, 1])
    assert gauge_cameras(img, pt, 5, 2, "first").tolist() == [0, 2]
    assert gauge_cameras(img, pt, 5, 2, "max_degree").tolist() == [1, 3]


def _distort(scene, dist: np.ndarray) -> list[np.ndarray]:
    """The scene's keypoints as a camera with distortion ``dist`` would have detected them."""
    out = []
    Kinv = np.linalg.inv(scene.K[0])
    for u in scene.uv:
        pc = np.c_[u, np.ones(len(u))] @ Kinv.T
        d, _ = cv2.projectPoints(pc, np.zeros(3), np.zeros(3), scene.K[0], dist)
        out.append(d.reshape(-1, 2))
    return out


def test_reconstruction_orchestrator() -> None:
    scene = make_scene(num_cameras=10, num_points=400, noise_px=0.5, seed=5)
    N = 10
    w0 = perturb_poses(scene.w2c, 3.0, 0.10, seed=6)
    dist = np.array([-0.15, 0.03, 0.0, 0.0, 0.0])
    uv = _distort(scene, dist)
    rng = np.random.default_rng(7)
    for u in uv:  # 10 % gross outliers among the keypoints
        bad = rng.uniform(size=len(u)) < 0.10
        u[bad] += rng.uniform(20, 60, (bad.sum(), 2))
    matches = dict(scene.pair_matches)
    # Camera 9 is weak: it keeps only a handful of matches, to camera 8.
    for key in list(matches):
        if 9 in key:
            del matches[key]
    matches[(8, 9)] = scene.pair_matches[(8, 9)][:6]
    placed = np.ones(N, bool)
    placed[7] = False  # not placed by motion averaging: untouched
    w0[7] = np.eye(4)
    res = bundle_adjust_reconstruction(uv, matches, scene.K, [dist] * N, w0, placed,
                                       BundleOptions(rounds=2))
    ok = placed & ~res.weak
    assert res.weak.tolist() == [False] * 9 + [True]
    assert res.refined.tolist() == ok.tolist()
    np.testing.assert_array_equal(res.w2c[7], w0[7])
    rot, pos = _pose_errors(res.w2c[ok], scene.w2c[ok])
    assert rot < 0.1 and pos < 0.02, (rot, pos)
    assert res.stats["median_error_after"] < 0.7 < res.stats["median_error_before"]
    assert len(res.bundles) == 2 and all(b.accepted for b in res.bundles)
    # Outliers were filtered: every kept observation reprojects within the threshold.
    assert res.bundles[-1].errors.max() <= 6.0
    assert res.points.shape == (res.point_track.size, 3)
    assert res.obs_point.max() < res.points.shape[0]
    assert res.observations_per_image[7] == 0 and res.observations_per_image[9] == 0
    assert (res.observations_per_image[ok] >= 15).all()
    # The weak camera keeps its input pose (moved into the adjusted frame: ~ unchanged).
    assert _pose_errors(res.w2c[[0, 1, 2, 9]], w0[[0, 1, 2, 9]])[0] < 5.0
    text = "\n".join(res.lines())
    assert "tracks:" in text and "seconds:" in text


def test_reconstruction_without_tracks_keeps_input() -> None:
    w0 = np.repeat(np.eye(4)[None], 3, 0)
    K = np.repeat(np.eye(3)[None], 3, 0)
    uv = [np.zeros((4, 2))] * 3
    w0[1, 0, 3] = np.nan  # a "placed" camera with a broken pose is treated as not placed
    res = bundle_adjust_reconstruction(uv, {(0, 1): np.array([[0, 0]])}, K, None, w0,
                                       np.ones(3, bool))
    assert "no tracks" in res.message and res.points.shape == (0, 3)
    np.testing.assert_array_equal(res.w2c, w0)
    assert res.placed.tolist() == [True, False, True]
    assert res.stats["invalid_placed_poses"] == 1
    with pytest.raises(ValueError, match="K must be"):
        bundle_adjust_reconstruction(uv, {}, K[:2], None, w0, np.ones(3, bool))


def test_summary_lines_of_a_failed_adjustment() -> None:
    """No adjustment accepted: the summary says so instead of failing on missing numbers."""
    from posernet.sfm import bundle_adjust_reconstruction

    scene = make_scene(num_cameras=5, num_points=120, seed=4)
    start = perturb_poses(scene.w2c, 2.0, 0.05, seed=1)
    res = bundle_adjust_reconstruction(scene.uv, scene.pair_matches, scene.K, None, start,
                                       np.ones(5, bool), BundleOptions(max_nfev=1))
    assert not res.refined.any() and np.allclose(res.w2c, start)
    lines = res.lines()
    assert "input poses kept" in lines[-1]
    assert not any("reprojection error" in ln for ln in lines)


@pytest.mark.parametrize("focal", ["none", "shared", "per_camera"])
@pytest.mark.parametrize("dense", [True, False])
def test_schur_step_is_the_damped_gauss_newton_step(focal: str, dense: bool) -> None:
    """The reduced-camera-system step (dense or block-sparse product) equals solving the full
    damped normal equations ``(J^T J + lam diag(J^T J)) dx = -J^T r``."""
    from posernet.sfm.bundle import _Schur

    sc = make_scene(num_cameras=6, num_points=200, noise_px=0.5, seed=1)
    prob = _Problem(sc.w2c, sc.points + 0.01, sc.K * 1.01, sc.xy, sc.obs_image, sc.obs_point,
                    np.array([0]), focal)
    x = prob.x0()
    r = prob.residuals(x)
    J = prob.jacobian(x).toarray()
    lam = 1e-3
    H = J.T @ J
    H[np.diag_indices_from(H)] += lam * np.maximum(np.diag(J.T @ J), 1e-9)
    ref = np.linalg.solve(H, -J.T @ r)
    system = _Schur(prob, *prob.blocks(x), r)
    if not dense:
        system.dense = False
    assert system.dense == dense  # a 6-camera problem picks the dense product by itself
    dc, dp = system.step(lam)
    n6 = 6 * system.nc
    dx = np.concatenate([dc[:n6], dp.ravel(), dc[n6:]])
    np.testing.assert_allclose(dx, ref, rtol=0, atol=1e-9 * np.abs(ref).max())


@pytest.mark.parametrize("chunk", [1, 7, 64, 10**6])
def test_per_camera_normal_blocks_in_slices_are_the_same_sums(monkeypatch, chunk: int) -> None:
    """The cameras' 6x6 blocks summed slice by slice (memory bounded) equal the one-shot
    segment sums bit for bit, whatever the slice length (shorter than a camera's
    observations included)."""
    import posernet.sfm.bundle as B

    rng = np.random.default_rng(chunk)
    counts = rng.integers(1, 30, 40)
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    A = rng.normal(size=(int(counts.sum()), 2, 6))
    monkeypatch.setattr(B, "_GRAM_CHUNK", chunk)
    np.testing.assert_array_equal(B._segment_grams(A, starts),
                                  np.add.reduceat(B._gram(A, A), starts, axis=0))


@pytest.mark.parametrize("cameras", [5, 70, 300])
def test_the_grouped_symmetric_product_is_the_whole_product(cameras: int) -> None:
    """``W V^-1 W^T`` from the camera groups ``i <= j`` (mirrored, ``Y = W V^-1`` one group
    at a time), subtracted in place, equals the whole block product, for one group (few
    cameras) and several (uneven ones included)."""
    from scipy.sparse import bsr_matrix

    from posernet.sfm.bundle import _subtract_upper_product

    rng = np.random.default_rng(cameras)
    npt = 3 * cameras
    cam = np.repeat(np.arange(cameras), 9)
    pt = (cam * 3 + rng.integers(0, 40, cam.size)) % npt  # nearby cameras share points
    pt[::17] = rng.integers(0, npt, pt[::17].size)  # and a few far ones
    key = np.unique(cam * npt + pt)  # one observation per camera and point
    cam, pt = key // npt, key % npt
    W = rng.normal(size=(cam.size, 6, 3))
    A = rng.normal(size=(npt, 3, 3))
    Vinv = A @ A.transpose(0, 2, 1)
    Y = np.matmul(W, Vinv[pt])
    indptr = np.searchsorted(cam, np.arange(cameras + 1))
    shape = (6 * cameras, 3 * npt)
    whole = (bsr_matrix((Y, pt, indptr), shape=shape)
             @ bsr_matrix((W, pt, indptr), shape=shape).T).toarray()
    start = rng.normal(size=whole.shape)
    got = start.copy()
    _subtract_upper_product(got, W, Vinv, pt, indptr, npt)
    np.testing.assert_allclose(start - got, whole, rtol=0, atol=1e-12 * np.abs(whole).max())
    for threads in (2, 3):  # the products shared between threads: the same bits
        again = start.copy()
        _subtract_upper_product(again, W, Vinv, pt, indptr, npt, threads=threads)
        np.testing.assert_array_equal(again, got)


@pytest.mark.parametrize("focal", ["none", "shared", "per_camera"])
def test_pcg_schur_step_equals_the_direct_step(focal: str) -> None:
    """Conjugate gradients on the implicit reduced camera system (``iterative=True``) reach
    the direct (Cholesky) step to the solver's tolerance, focal parameters included."""
    from posernet.sfm.bundle import _Schur

    sc = make_scene(num_cameras=10, num_points=400, noise_px=0.5, seed=2)
    prob = _Problem(sc.w2c, sc.points + 0.01, sc.K * 1.01, sc.xy, sc.obs_image, sc.obs_point,
                    np.array([0]), focal)
    x = prob.x0()
    r = prob.residuals(x)
    for lam in (1e-4, 1e-1):
        dc, dp = _Schur(prob, *prob.blocks(x), r).step(lam)
        pcg = _Schur(prob, *prob.blocks(x), r, iterative=True)
        dc2, dp2 = pcg.step(lam)
        assert pcg.iterative and 0 < pcg.pcg_iterations[0] < pcg.pcg_maxiter
        np.testing.assert_allclose(dc2, dc, rtol=0, atol=1e-6 * np.abs(dc).max())
        np.testing.assert_allclose(dp2, dp, rtol=0, atol=1e-6 * np.abs(dp).max())
        # the passes over the observations shared between threads by rows: the same bits
        for threads in (2, 3):
            dc3, dp3 = _Schur(prob, *prob.blocks(x), r, iterative=True,
                              threads=threads).step(lam)
            np.testing.assert_array_equal(dc3, dc2)
            np.testing.assert_array_equal(dp3, dp2)


def test_row_blocks_cover_the_rows_on_views() -> None:
    """The row ranges of a CSR matrix: contiguous, covering every row once (empty rows and
    more parts than rows included), each block the rows of the matrix itself."""
    from scipy.sparse import random as sparse_random

    from posernet.sfm.bundle import _row_blocks

    A = sparse_random(37, 20, density=0.2, format="csr", random_state=3)
    A[5:9] = 0  # a run of empty rows
    A.eliminate_zeros()
    for parts in (1, 2, 3, 50):
        blocks = _row_blocks(A, parts)
        assert blocks[0][0] == 0 and blocks[-1][1] == A.shape[0]
        assert all(a[1] == b[0] for a, b in itertools.pairwise(blocks))
        for r0, r1, B in blocks:
            np.testing.assert_array_equal(B.toarray(), A[r0:r1].toarray())


def test_bundle_adjust_with_pcg_matches_the_direct_solver() -> None:
    """The whole adjustment with the iterative reduced solve (``pcg_min_cameras=0``) ends
    where the direct one does: same cameras, same errors to well below a pixel."""
    sc = make_scene(num_cameras=10, num_points=500, noise_px=0.5, seed=4)
    start = perturb_poses(sc.w2c, 2.0, 0.05, seed=5, keep=(0,))
    pts = sc.points + np.random.default_rng(6).normal(0, 0.02, sc.points.shape)
    out = [bundle_adjust(start, pts, sc.K, sc.xy, sc.obs_image, sc.obs_point,
                         BundleOptions(pcg_min_cameras=m)) for m in (10**9, 0)]
    assert all(o.accepted and o.converged for o in out)
    np.testing.assert_allclose(out[1].w2c, out[0].w2c, atol=1e-6)
    np.testing.assert_allclose(out[1].errors, out[0].errors, atol=1e-4)
    with pytest.raises(ValueError, match="pcg_min_cameras"):
        BundleOptions(pcg_min_cameras=-1)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-4.0, 4.0, allow_nan=False), min_size=3, max_size=3),
       st.sampled_from([1.0, 1e-3, 1e-6, 1e-9, 0.0]))
def test_rotvec_to_matrix_is_rodrigues(v, scale) -> None:
    """The solver's rotation-vector map equals OpenCV's Rodrigues, near zero too, and is a
    rotation (orthonormal, determinant 1)."""
    from posernet.sfm.bundle import _rotvec_to_matrix

    w = np.asarray(v, np.float64) * scale
    R = _rotvec_to_matrix(w[None])[0]
    np.testing.assert_allclose(R, cv2.Rodrigues(w)[0], atol=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)

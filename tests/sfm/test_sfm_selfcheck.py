"""The self-check: every placed camera held against its verified pairs and its 3D points."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posernet.sfm.selfcheck import CheckOptions, PairEvidence, check_reconstruction
from posernet.sfm.synthetic import make_sparse_scene, perturb_poses


@pytest.fixture(scope="module")
def ring():
    return make_sparse_scene("ring", num_cameras=12, num_points=2400, noise_px=0.3)


def evidence(sc, drop_matches: bool = False) -> PairEvidence:
    """Verified pairs from the ground truth: relative poses, inlier matches (normalised)."""
    pairs = np.array(sorted(sc.pair_matches), np.int64)
    a, b = pairs[:, 0], pairs[:, 1]
    R = sc.w2c[b, :3, :3] @ sc.w2c[a, :3, :3].transpose(0, 2, 1)
    t = sc.w2c[b, :3, 3] - np.einsum("eij,ej->ei", R, sc.w2c[a, :3, 3])
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    K = sc.K[0]
    norm = [(u - K[:2, 2]) / np.diag(K)[:2] for u in sc.uv]
    m = [sc.pair_matches[(int(i), int(j))] for i, j in pairs]
    extra = {} if drop_matches else dict(
        match_pair=np.concatenate([np.full(len(x), e) for e, x in enumerate(m)]),
        x_a=np.concatenate([norm[i][x[:, 0]] for (i, _), x in zip(pairs, m, strict=True)]),
        x_b=np.concatenate([norm[j][x[:, 1]] for (_, j), x in zip(pairs, m, strict=True)]),
        focal=np.full(len(pairs), K[0, 0]))
    return PairEvidence(pairs=pairs, R=R, t=t, rotation_only=np.zeros(len(pairs), bool),
                        weight=np.array([len(x) for x in m], np.float64), **extra)


def structure(sc):
    """The scene's points with their observations (as a bundle adjustment would keep them)."""
    return sc.points, sc.obs_image, sc.obs_point


def test_a_right_reconstruction_passes(ring) -> None:
    out = check_reconstruction(ring.w2c, np.ones(12, bool), evidence(ring), *structure(ring))
    assert out.passed.all() and out.verified and not any(out.reason)
    assert np.nanmax(out.rotation_error_deg) < 1e-6 and np.nanmin(out.inlier_share) > 0.95
    assert (out.points > 100).all() and (out.triangulation_deg > 5).all()
    assert out.line() == "self-check: all 12 placed cameras agree with their evidence"


def test_a_planted_collapse_fails(ring) -> None:
    """Three neighbours moved onto camera 3's centre (rotations kept): translation averaging's
    collapse. They, and only they, fail."""
    w = ring.w2c.copy()
    c3 = -w[3, :3, :3].T @ w[3, :3, 3]
    for i in (4, 5, 6):
        w[i, :3, 3] = -w[i, :3, :3] @ c3
    out = check_reconstruction(w, np.ones(12, bool), evidence(ring))
    assert out.failed.tolist() == [i in (4, 5, 6) for i in range(12)]
    assert all(out.reason[i] for i in (4, 5, 6))
    assert "3 of 12 placed cameras failed" in out.line()


def test_coinciding_centres_are_named(ring) -> None:
    w = ring.w2c.copy()
    c3 = -w[3, :3, :3].T @ w[3, :3, 3]
    w[4, :3, 3] = -w[4, :3, :3] @ c3
    out = check_reconstruction(w, np.ones(12, bool), evidence(ring),
                               options=CheckOptions(min_agreeing_share=0.0))
    # the pair check off: which of the two is wrong is not known, so neither is placed
    assert out.failed.tolist() == [i in (3, 4) for i in range(12)]
    assert "coincides with camera 4" in out.reason[3]
    assert "coincides with camera 3" in out.reason[4]


def test_a_planted_wrong_camera_fails_alone(ring) -> None:
    """One camera turned 10 deg: its pairs no longer fit their matches; its neighbours, whose
    other pairs still agree, pass."""
    w = perturb_poses(ring.w2c, 10.0, 0.0, seed=3, keep=tuple(i for i in range(12) if i != 7))
    out = check_reconstruction(w, np.ones(12, bool), evidence(ring))
    assert out.failed.tolist() == [i == 7 for i in range(12)]
    assert "disagrees with its verified image pairs" in out.reason[7]


def test_a_planted_wrong_edge_does_not_fail_its_cameras(ring) -> None:
    """One verified pair's matches are wrong (a repeated structure): the two cameras keep
    their other, agreeing pairs."""
    ev = evidence(ring)
    e = int(np.argmin(ev.weight))  # a pair of second neighbours
    sel = ev.match_pair == e
    ev.x_b[sel] = np.random.default_rng(0).uniform(-0.3, 0.3, (int(sel.sum()), 2))
    out = check_reconstruction(ring.w2c, np.ones(12, bool), ev)
    assert out.passed.all()
    assert out.inlier_share[e] < 0.2


def test_pairs_without_matches_use_rotation_and_direction(ring) -> None:
    ev = evidence(ring, drop_matches=True)
    w = perturb_poses(ring.w2c, 10.0, 0.0, seed=3, keep=tuple(i for i in range(12) if i != 7))
    out = check_reconstruction(w, np.ones(12, bool), ev)
    assert out.failed.tolist() == [i == 7 for i in range(12)]
    assert np.isnan(out.inlier_share).all()


def test_thin_support_and_rotation_alone(ring) -> None:
    """A camera resting on one weak pair fails (two-view ambiguity); cameras whose points are
    seen only under tiny angles are explained by rotation alone."""
    ev = evidence(ring)
    out = check_reconstruction(ring.w2c, np.ones(12, bool), ev,
                               options=CheckOptions(min_single_pair_inliers=10**6))
    # on a ring every camera has two or more agreeing pairs: none rests on one
    assert out.passed.all()
    keep = (ev.pairs == 0).any(1) & (ev.pairs[:, 1] != 1) & (ev.pairs[:, 0] != 0)
    keep |= ~(ev.pairs == 0).any(1)
    keep[np.flatnonzero((ev.pairs == 0).any(1))[0]] = True  # camera 0 keeps one pair
    thin = PairEvidence(ev.pairs[keep], ev.R[keep], ev.t[keep], ev.rotation_only[keep],
                        ev.weight[keep])
    out = check_reconstruction(ring.w2c, np.ones(12, bool), thin,
                               options=CheckOptions(min_single_pair_inliers=10**6))
    assert out.failed[0] and "rests on one verified image pair" in out.reason[0]
    # points pushed far away: every ray meets the others at a tiny angle
    far = ring.points * 1e4
    out = check_reconstruction(ring.w2c, np.ones(12, bool), ev, far, ring.obs_image,
                               ring.obs_point)
    assert not out.verified and not out.passed.any()
    assert "rotation alone" in out.reason[0]
    assert "could not verify" in out.line()


def single_pair(ev: PairEvidence, planar: np.ndarray | None = None) -> PairEvidence:
    """``ev`` with camera 0 left with its first pair only (``planar``: per kept pair)."""
    mine = (ev.pairs == 0).any(1)
    keep = ~mine
    keep[np.flatnonzero(mine)[0]] = True
    sel = np.isin(ev.match_pair, np.flatnonzero(keep))
    remap = np.cumsum(keep) - 1
    return PairEvidence(ev.pairs[keep], ev.R[keep], ev.t[keep], ev.rotation_only[keep],
                        ev.weight[keep], remap[ev.match_pair[sel]], ev.x_a[sel], ev.x_b[sel],
                        ev.focal[keep], planar=planar)


def test_a_single_pair_whose_matches_do_not_join_the_points_fails(ring) -> None:
    """Camera 0 rests on one agreeing pair: it passes while the points it sees account for
    that pair's inliers, and fails when most of them did not join the 3D points (a wrong
    two-view geometry fits its own matches, not the other cameras' points)."""
    thin = single_pair(evidence(ring))
    w0 = int(thin.weight[(thin.pairs == 0).any(1)][0])
    pts, img, pid = structure(ring)
    seen = np.flatnonzero(img == 0)
    assert len(seen) >= w0  # camera 0 sees at least its one pair's inliers
    # the open ring's first pairs share no point with a third camera: their distances are
    # free (the tied-scale check would fail cameras 0 and 1); this test is about the pair
    opts = CheckOptions(scale_links=0)
    out = check_reconstruction(ring.w2c, np.ones(12, bool), thin, pts, img, pid, options=opts)
    assert out.passed.all()
    # keep 40 % of the pair's inliers as camera 0's observations
    drop = seen[int(0.4 * w0):]
    kept = np.ones(len(img), bool)
    kept[drop] = False
    out = check_reconstruction(ring.w2c, np.ones(12, bool), thin, pts, img[kept], pid[kept],
                               options=opts)
    assert out.failed.tolist() == [i == 0 for i in range(12)]
    assert "join the 3D points" in out.reason[0]
    loose = CheckOptions(min_single_pair_kept=0.3, scale_links=0)
    out = check_reconstruction(ring.w2c, np.ones(12, bool), thin, pts, img[kept], pid[kept],
                               options=loose)
    assert out.passed.all()


def test_a_camera_resting_on_one_planar_pair_fails(ring) -> None:
    """Camera 0 rests on one agreeing pair: it passes while that pair is not planar, fails
    when a homography explains its inliers (two relative poses fit a plane's matches), and a
    planar pair among several does not fail its cameras."""
    ev = evidence(ring)
    base = single_pair(ev)

    def thin(planar: np.ndarray) -> PairEvidence:
        return single_pair(ev, planar)

    single = (base.pairs == 0).any(1)
    out = check_reconstruction(ring.w2c, np.ones(12, bool), thin(np.zeros(len(single), bool)))
    assert out.passed.all()
    out = check_reconstruction(ring.w2c, np.ones(12, bool), thin(single))
    assert out.failed.tolist() == [i == 0 for i in range(12)]
    assert "homography" in out.reason[0]
    off = CheckOptions(single_planar_fails=False)
    assert check_reconstruction(ring.w2c, np.ones(12, bool), thin(single),
                                options=off).passed.all()
    # every pair planar, but each camera has several: nobody rests on one
    every = PairEvidence(ev.pairs, ev.R, ev.t, ev.rotation_only, ev.weight, ev.match_pair,
                         ev.x_a, ev.x_b, ev.focal, planar=np.ones(len(ev.pairs), bool))
    assert check_reconstruction(ring.w2c, np.ones(12, bool), every).passed.all()


def test_unplaced_cameras_are_left_alone(ring) -> None:
    placed = np.ones(12, bool)
    placed[[2, 9]] = False
    w = ring.w2c.copy()
    w[2] = np.nan
    out = check_reconstruction(w, placed, evidence(ring))
    assert not out.placed[[2, 9]].any() and not out.passed[[2, 9]].any()
    assert out.reason[2] == out.reason[9] == ""
    assert out.passed[placed].all()


@settings(max_examples=15, deadline=None)
@given(st.floats(0.2, 5.0), st.floats(-3, 3), st.integers(0, 2**31 - 1))
def test_passes_are_unchanged_by_a_similarity(scale: float, shift: float, seed: int) -> None:
    """The check reads only relative geometry: moving the world by a similarity changes no
    verdict."""
    from scipy.spatial.transform import Rotation

    sc = make_sparse_scene("ring", num_cameras=8, num_points=1200, seed=1)
    w = perturb_poses(sc.w2c, 8.0, 0.0, seed=4, keep=tuple(range(1, 8)))
    Q = Rotation.random(random_state=seed).as_matrix()
    # the world moved by X' = scale Q X + shift: R' = R Q^T, t' = scale t - R' shift
    moved = w.copy()
    moved[:, :3, :3] = w[:, :3, :3] @ Q.T
    moved[:, :3, 3] = scale * w[:, :3, 3] - np.einsum("nij,j->ni", moved[:, :3, :3],
                                                      np.full(3, shift))
    ev = evidence(sc)
    a = check_reconstruction(w, np.ones(8, bool), ev)
    b = check_reconstruction(moved, np.ones(8, bool), ev)
    assert a.passed.tolist() == b.passed.tolist()
    np.testing.assert_allclose(a.inlier_share, b.inlier_share)


def test_options_are_checked() -> None:
    with pytest.raises(ValueError, match="min_agreeing_share"):
        CheckOptions(min_agreeing_share=2)
    with pytest.raises(ValueError, match="max_epipolar_px"):
        CheckOptions(max_epipolar_px=0)


def _two_view_tracks(sc):
    """The scene's observations with every point cut to its first two views (points of
    views matched by different matchers never join)."""
    pts, img, pid = structure(sc)
    order = np.lexsort((img, pid))
    img, pid = img[order], pid[order]
    first = np.r_[True, pid[1:] != pid[:-1]]
    rank = np.arange(pid.size) - np.maximum.accumulate(np.where(first, np.arange(pid.size), 0))
    keep = rank < 2
    return pts, img[keep], pid[keep]


def _blocks_are_pairs(out, ev) -> None:
    """Every split-off block is two cameras joined by a verified pair; a camera left out
    fails because each camera it has a pair with is already in a block."""
    pairs = {tuple(sorted(p)) for p in ev.pairs.tolist()}
    for k in range(1, int(out.part.max()) + 1):
        cams = np.flatnonzero(out.part == k)
        assert cams.size == 2 and tuple(cams) in pairs
    for i in np.flatnonzero(~out.passed):
        assert "distance to the other cameras is not fixed" in out.reason[i]
        assert all(out.passed[j] for p in pairs if i in p for j in p if j != i)


def test_cameras_whose_distance_nothing_ties_split_off(ring) -> None:
    """On the ring (pairs between neighbours only, no triangle) the 3D points tie the pairs'
    distances together: every camera passes in one block, including the two at an untied
    joint (their pairs into the block cross). Cut every point to two views and no pair is
    tied to another: the pair with the most inliers is the component's block, every further
    pair of cameras not yet in a block is a component of its own, and a camera left alone
    fails with the reason; the check off (scale_links=0) passes them all in one."""
    ev = evidence(ring)
    out = check_reconstruction(ring.w2c, np.ones(12, bool), ev, *structure(ring))
    assert out.passed.all() and (out.part == 0).all() and not out.split.any()
    two = _two_view_tracks(ring)
    assert np.bincount(two[2]).max() == 2
    out = check_reconstruction(ring.w2c, np.ones(12, bool), ev, *two)
    best = ev.pairs[np.argmax(ev.weight)]
    assert np.flatnonzero(out.part == 0).tolist() == sorted(best.tolist())
    assert out.split.sum() >= 8 and out.passed.sum() == (out.part >= 0).sum()
    _blocks_are_pairs(out, ev)
    assert "component(s) of their own" in out.line()
    assert set(out.to_dict([str(i) for i in range(12)])["split"]) == {
        str(i) for i in np.flatnonzero(out.split)}
    out = check_reconstruction(ring.w2c, np.ones(12, bool), ev, *two,
                               options=CheckOptions(scale_links=0))
    assert out.passed.all() and (out.part == 0).all()
    # inside a block of its own the thin-support rule holds again: a pair of 30 inliers is
    # not enough for a component of two (across the ring each camera had two pairs)
    weak = dataclasses.replace(ev, weight=np.where(np.arange(len(ev.weight)) ==
                                                   np.argmax(ev.weight), ev.weight, 30.0))
    out = check_reconstruction(ring.w2c, np.ones(12, bool), weak, *two)
    assert np.flatnonzero(out.part == 0).tolist() == sorted(best.tolist())
    assert not out.split.any() and out.passed.sum() == 2
    thin = [i for i in range(12) if "component of its own" in out.reason[i]]
    assert len(thin) >= 6 and all("30 inliers (< 50)" in out.reason[i] for i in thin)
    assert all(i in thin or "not fixed" in out.reason[i] for i in np.flatnonzero(~out.passed))


def test_a_triangle_or_crossing_pairs_tie_cameras_without_shared_points(ring) -> None:
    """Two-view points only: a pair closing a triangle ties its three cameras' distances, and
    a camera with pairs to two of them (not parallel) is fixed where the lines meet."""
    ev = evidence(ring)
    extra = [(0, 2)]  # closes the triangle 0-1-2
    pairs = np.concatenate([ev.pairs, np.array(extra)])
    R = np.concatenate([ev.R, [ring.w2c[2, :3, :3] @ ring.w2c[0, :3, :3].T]])
    t = ring.w2c[2, :3, 3] - R[-1] @ ring.w2c[0, :3, 3]
    tri = PairEvidence(pairs=pairs, R=R, t=np.concatenate([ev.t, [t / np.linalg.norm(t)]]),
                       rotation_only=np.zeros(len(pairs), bool),
                       weight=np.concatenate([ev.weight, [1000.0]]))
    out = check_reconstruction(ring.w2c, np.ones(12, bool), tri, *_two_view_tracks(ring))
    # the block {0, 1, 2}; camera 11 (pairs to 0 only) and 3 (to 2 only) hang on one line:
    # not in it (the chain 3 ... 11 splits into components of two)
    assert (out.part == 0).tolist() == [i in (0, 1, 2) for i in range(12)]
    _blocks_are_pairs(out, tri)
    # camera 3 with a second pair into the block, to camera 1: it sits where the lines meet
    pairs4 = np.concatenate([pairs, [(1, 3)]])
    R13 = ring.w2c[3, :3, :3] @ ring.w2c[1, :3, :3].T
    t13 = ring.w2c[3, :3, 3] - R13 @ ring.w2c[1, :3, 3]
    cross = PairEvidence(pairs=pairs4, R=np.concatenate([R, [R13]]),
                         t=np.concatenate([tri.t, [t13 / np.linalg.norm(t13)]]),
                         rotation_only=np.zeros(len(pairs4), bool),
                         weight=np.concatenate([tri.weight, [1000.0]]))
    out = check_reconstruction(ring.w2c, np.ones(12, bool), cross, *_two_view_tracks(ring))
    assert (out.part == 0).tolist() == [i in (0, 1, 2, 3) for i in range(12)]
    _blocks_are_pairs(out, cross)


def _brute_triangulation(w2c, points, obs_image, obs_point, n):
    """Per camera the median over its observations of the largest angle to another view's
    ray to the same point, pair by pair."""
    centre = np.stack([-T[:3, :3].T @ T[:3, 3] for T in w2c])
    per = [[] for _ in range(n)]
    for o in range(obs_image.size):
        p, i = obs_point[o], obs_image[o]
        r = points[p] - centre[i]
        angles = []
        for q in np.flatnonzero(obs_point == p):
            if q != o:
                s = points[p] - centre[obs_image[q]]
                c = r @ s / np.linalg.norm(r) / np.linalg.norm(s)
                angles.append(np.degrees(np.arccos(np.clip(c, -1, 1))))
        if angles:
            per[i].append(max(angles))
    return np.array([np.median(a) if a else np.nan for a in per])


def test_triangulation_angle_is_the_widest_pair_of_rays() -> None:
    """Cameras on an arc (rays of a point spread along one direction): the angles equal the
    pair-by-pair largest angle, and the middle one of three views at equal angles either
    side gets the angle to them, not the ~0 to their mean ray."""
    from posernet.sfm.selfcheck import triangulation_angles

    rng = np.random.default_rng(3)
    n = 7
    a = np.radians(np.linspace(-45, 45, n))
    w2c = []
    for t in a:
        c = np.array([4 * np.sin(t), 0.0, -4 * np.cos(t)])
        z = -c / np.linalg.norm(c)
        x = np.cross([0.0, -1.0, 0.0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        w2c.append(np.block([[R, (-R @ c)[:, None]], [np.zeros((1, 3)), 1]]))
    w2c = np.stack(w2c)
    points = rng.uniform(-0.5, 0.5, (60, 3)) * [1, 1, 0.01]  # near the plane of the arc
    obs_image, obs_point = [], []
    for p in range(60):
        start = rng.integers(0, n - 1)
        views = np.arange(start, min(n, start + rng.integers(2, 5)))
        obs_image += views.tolist()
        obs_point += [p] * views.size
    obs_image, obs_point = np.array(obs_image), np.array(obs_point)
    counts, med = triangulation_angles(w2c, points, obs_image, obs_point, n)
    np.testing.assert_array_equal(counts, np.bincount(obs_image, minlength=n))
    np.testing.assert_allclose(med, _brute_triangulation(w2c, points, obs_image, obs_point, n),
                               atol=0.05)
    # three views 15 deg apart, the point seen by all three: the middle one's angle is 15
    three = np.array([2, 3, 4])
    _, med = triangulation_angles(w2c, np.zeros((1, 3)), three, np.zeros(3, np.int64), n)
    np.testing.assert_allclose(med[three], [30, 15, 30], atol=0.01)
    assert np.isnan(med[[0, 1, 5, 6]]).all()

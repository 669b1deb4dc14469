"""Keypoint and box matching rules (15 keypoints, 30% span, 5 boxes) and graph connectivity."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from posernet.data.synthetic import SceneWorld, load_preset, simulate_graphs
from posernet.data.synthetic.config import KeypointOptions, MatchOptions
from posernet.data.synthetic.matching import match_keypoints, reassign_wrong
from posernet.frontend.assembly import is_connected
from posernet.frontend.boxmatch import boxes_contain, match_boxes

BOX_A = np.array([[100.0, 100.0, 200.0, 200.0]])
BOX_B = np.array([[300.0, 50.0, 400.0, 150.0]])


def _grid(box: np.ndarray, n: int, frac: float) -> np.ndarray:
    """``n`` points spread over the top-left ``frac`` of ``box`` (side fraction)."""
    x1, y1, x2, y2 = box
    s = np.linspace(0, 1, int(np.ceil(np.sqrt(n))))
    g = np.stack(np.meshgrid(s, s), -1).reshape(-1, 2)[:n]
    return np.stack((x1 + g[:, 0] * (x2 - x1) * frac, y1 + g[:, 1] * (y2 - y1) * frac), 1)


def test_box_pair_needs_fifteen_keypoints():
    ua, ub = _grid(BOX_A[0], 15, 1.0), _grid(BOX_B[0], 15, 1.0)
    ia, ib, cnt = match_boxes(ua, ub, BOX_A, BOX_B, 15, 0.3)
    assert ia.tolist() == [0] and ib.tolist() == [0] and cnt.tolist() == [15]
    ia, _, _ = match_boxes(ua[:14], ub[:14], BOX_A, BOX_B, 15, 0.3)
    assert ia.size == 0


def test_box_pair_needs_keypoints_spanning_thirty_percent_in_both_images():
    # keypoints in the top-left 50% x 50% = 25% of box A: not enough span
    ua, ub = _grid(BOX_A[0], 25, 0.5), _grid(BOX_B[0], 25, 1.0)
    assert match_boxes(ua, ub, BOX_A, BOX_B, 15, 0.3)[0].size == 0
    # 60% x 60% = 36% span in A, full in B: matched
    ua = _grid(BOX_A[0], 25, 0.6)
    assert match_boxes(ua, ub, BOX_A, BOX_B, 15, 0.3)[0].size == 1
    # and the rule applies to image b as well
    ub = _grid(BOX_B[0], 25, 0.5)
    assert match_boxes(ua, ub, BOX_A, BOX_B, 15, 0.3)[0].size == 0


def test_keypoints_outside_the_boxes_do_not_count():
    ua, ub = _grid(BOX_A[0], 30, 1.0), _grid(BOX_B[0], 30, 1.0)
    ub[10:] += 500.0  # 20 of them land outside box B
    assert match_boxes(ua, ub, BOX_A, BOX_B, 15, 0.3)[0].size == 0


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    m=st.integers(0, 200),
    ba=st.integers(1, 8),
    bb=st.integers(1, 8),
    kmin=st.integers(1, 20),
    span=st.floats(0.0, 0.6),
)
def test_match_boxes_agrees_with_brute_force(seed, m, ba, bb, kmin, span):
    rng = np.random.default_rng(seed)

    def boxes(n):
        lo = rng.uniform(0, 400, size=(n, 2))
        return np.concatenate((lo, lo + rng.uniform(10, 240, size=(n, 2))), 1)

    A, B = boxes(ba), boxes(bb)
    ua, ub = rng.uniform(0, 640, size=(m, 2)), rng.uniform(0, 640, size=(m, 2))
    ia, ib, cnt = match_boxes(ua, ub, A, B, kmin, span)
    got = set(zip(ia.tolist(), ib.tolist(), strict=True))
    want = set()
    for a in range(ba):
        for b in range(bb):
            inside = boxes_contain(A[a : a + 1], ua)[:, 0] & boxes_contain(B[b : b + 1], ub)[:, 0]
            if inside.sum() < kmin:
                continue
            ok = True
            for uv, box in ((ua[inside], A[a]), (ub[inside], B[b])):
                area = (box[2] - box[0]) * (box[3] - box[1])
                ext = np.ptp(uv[:, 0]) * np.ptp(uv[:, 1])
                ok &= ext / area >= span
            if ok:
                want.add((a, b))
    assert got == want
    assert (cnt >= kmin).all()


def test_reassign_wrong_rates():
    ia, ib = np.arange(6), np.arange(6)
    rng = np.random.default_rng(0)
    a, b, w = reassign_wrong(ia, ib, 10, 0.0, rng)
    assert a.tolist() == ia.tolist() and b.tolist() == ib.tolist() and not w.any()
    a, b, w = reassign_wrong(ia, ib, 10, 1.0, rng)
    assert w.all() and (b != a).all()


@settings(max_examples=40, deadline=None)
@given(n=st.integers(1, 12), seed=st.integers(0, 1000), p=st.floats(0.0, 0.6))
def test_is_connected_matches_scipy(n, seed, p):
    rng = np.random.default_rng(seed)
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n) if rng.random() < p]
    ei = np.array(pairs, dtype=np.int64).T.reshape(2, -1)
    adj = coo_matrix((np.ones(ei.shape[1]), (ei[0], ei[1])), shape=(n, n))
    k, _ = connected_components(adj, directed=False)
    assert is_connected(n, ei) == (k == 1)


def test_clean_keypoint_matches_are_the_same_3d_points():
    opts = load_preset("tiny")
    world = SceneWorld(opts, "chess", seed=0)
    fa, fb = world.frame(10), world.frame(13)
    clean = KeypointOptions(
        outlier_rate=0.0,
        confusion=0.0,
        match_prob=1.0,
        max_view_angle=179.0,
        max_scale_change=100.0,
    )
    sc = world.scene
    m = match_keypoints(
        sc.kp_xyz,
        sc.kp_owner,
        sc.kp_twin,
        fa.kp_ids,
        fa.kp_uv_true,
        fa.centre,
        fb.kp_ids,
        fb.kp_uv_true,
        fb.centre,
        clean,
        np.random.default_rng(0),
    )
    common = np.intersect1d(fa.kp_ids, fb.kp_ids)
    assert m.ids.tolist() == common.tolist() and not m.outlier.any()
    # the matched pixels are the projections of the same 3D points in both images
    for f, uv in ((fa, m.uv_a), (fb, m.uv_b)):
        X = sc.kp_xyz[m.ids]
        xc = X @ f.w2c[:3, :3].T + f.w2c[:3, 3]
        proj = xc[:, :2] / xc[:, 2:] * 585.0 + np.array([320.0, 240.0])
        np.testing.assert_allclose(uv, proj, atol=1e-6)
    # outliers and confusion are flagged
    noisy = KeypointOptions(
        outlier_rate=0.5,
        confusion=0.0,
        match_prob=1.0,
        max_view_angle=179.0,
        max_scale_change=100.0,
    )
    m2 = match_keypoints(
        sc.kp_xyz,
        sc.kp_owner,
        sc.kp_twin,
        fa.kp_ids,
        fa.kp_uv_true,
        fa.centre,
        fb.kp_ids,
        fb.kp_uv_true,
        fb.centre,
        noisy,
        np.random.default_rng(0),
    )
    assert 0.3 < m2.outlier.mean() < 0.7


@pytest.fixture(scope="module")
def graphs():
    opts = load_preset("tiny")
    small = simulate_graphs(opts, scene="fire", split="train", size="small", count=3, seed=2)
    large = simulate_graphs(opts, scene="chess", split="test", size="large", count=1, seed=2)
    return opts, small, large


def test_edges_have_at_least_five_matched_boxes_and_small_graphs_are_connected(graphs):
    opts, small, large = graphs
    for g in small + large:
        g.validate()
        per_edge = torch.bincount(g.pair_edge, minlength=g.num_edges)
        assert (per_edge >= opts.matching.min_boxes).all()
        # a detection is paired at most once per edge and direction
        key = g.pair_edge * g.num_dets + g.pair_src
        assert key.unique().numel() <= key.numel()
    for g in small:
        assert g.num_nodes == opts.small.graph_size
        assert is_connected(g.num_nodes, g.edge_index.numpy())
    assert large[0].num_nodes == opts.large.graph_size
    assert large[0].meta["size"] == "large"


def test_every_matched_image_pair_of_a_graph_is_an_edge(graphs):
    """No pair with enough matched boxes and two estimates is left out of a graph."""
    opts, small, _ = graphs
    world = SceneWorld(opts, "fire", seed=2)
    for g in small:
        frames = [int(f) for f in g.meta["frames"].split(",")]
        edges = {tuple(sorted(e)) for e in g.edge_index.T.tolist()}
        for a in range(len(frames)):
            for b in range(a + 1, len(frames)):
                assert world.pair(frames[a], frames[b]).is_edge == ((a, b) in edges)


def test_kp_boxes_feeds_only_the_best_matched_box_pairs_to_the_kp_five_point():
    """``matching.kp_boxes`` keeps the KP input to the box pairs sharing the most matches and
    leaves the box matching and the BB estimate untouched; 0 (the default) keeps them all."""
    import dataclasses

    assert MatchOptions().kp_boxes == 0
    for name in ("easy", "tiny"):
        assert load_preset(name).matching.kp_boxes == 0
    for name in ("paper", "demo"):  # the demo uses the paper's noise model
        assert load_preset(name).matching.kp_boxes == 1
    base = load_preset("tiny")
    one = dataclasses.replace(base, matching=dataclasses.replace(base.matching, kp_boxes=1))
    w0, w1 = SceneWorld(base, "chess", seed=0), SceneWorld(one, "chess", seed=0)
    checked = 0
    for a, b in [(i, i + d) for i in range(0, 120, 7) for d in (2, 5)]:
        r0, r1 = w0.pair(a, b), w1.pair(a, b)
        assert r0.status == r1.status or "failed" in r0.status + r1.status
        assert r0.box_a.tolist() == r1.box_a.tolist() and r0.box_b.tolist() == r1.box_b.tolist()
        if r0.status != "edge" or r1.status != "edge":
            continue
        np.testing.assert_array_equal(r0.bb[0], r1.bb[0])
        # the single best pair holds at least min_keypoints and fewer than all matched pairs
        assert base.matching.min_keypoints <= r1.n_kp < r0.n_kp
        checked += 1
    assert checked >= 3

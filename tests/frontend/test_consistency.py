"""Checks of the verified pairs against each other: triangles found once each, loop errors,
a planted wrong edge rejected while the right ones stay, chains and lone triangles left alone,
crowded inliers rejected and spread ones kept, and the rejections booked like any other."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posernet.frontend.assembly import PairResult
from posernet.frontend.consistency import (
    cycle_errors,
    loop_outliers,
    screen_edges,
    triangles,
)
from posernet.frontend.features import Features
from posernet.frontend.images import ImageRecord
from posernet.frontend.pipeline import ImageFrontend
from posernet.frontend.verify import VerifyRules, inlier_spread

W, H = 640, 480


def _random_graph(n: int, p: float, rng: np.random.Generator) -> np.ndarray:
    """Edges ``(E, 2)`` of a random graph, each stored in a random direction."""
    pairs = [(a, b) for a, b in itertools.combinations(range(n), 2) if rng.random() < p]
    return np.array([(b, a) if rng.random() < 0.5 else (a, b) for a, b in pairs],
                    np.int64).reshape(-1, 2)


def _relative(R_abs: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Relative rotations camera i -> camera j of world-to-camera rotations ``R_abs``."""
    return np.stack([R_abs[j] @ R_abs[i].T for i, j in edges])


def _noisy(R: np.ndarray, deg: float, rng: np.random.Generator) -> np.ndarray:
    return Rotation.from_rotvec(rng.normal(0, np.radians(deg), (len(R), 3))).as_matrix() @ R


@pytest.mark.parametrize("seed", range(6))
def test_triangles_are_every_triangle_once(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 25))
    edges = _random_graph(n, float(rng.uniform(0.1, 0.9)), rng)
    tri = triangles(edges, n)
    ids = {frozenset(e): k for k, e in enumerate(map(tuple, edges.tolist()))}
    want = set()
    for a, b, c in itertools.combinations(range(n), 3):
        sides = [frozenset((a, b)), frozenset((b, c)), frozenset((a, c))]
        if all(s in ids for s in sides):
            want.add(frozenset(ids[s] for s in sides))
    assert len(tri) == len(want)
    assert {frozenset(t) for t in tri.tolist()} == want


def test_loop_error_is_zero_for_consistent_rotations_whatever_the_edge_direction():
    rng = np.random.default_rng(1)
    n = 12
    edges = _random_graph(n, 0.6, rng)
    R_abs = Rotation.random(n, random_state=1).as_matrix()
    tri = triangles(edges, n)
    assert len(tri) > 20
    assert cycle_errors(_relative(R_abs, edges), edges, tri).max() < 1e-4
    # one edge turned by 20 degrees: exactly its triangles are off by 20 degrees
    R = _relative(R_abs, edges)
    R[0] = Rotation.from_rotvec([0, np.radians(20), 0]).as_matrix() @ R[0]
    err = cycle_errors(R, edges, tri)
    on = (tri == 0).any(axis=1)
    assert np.allclose(err[on], 20, atol=1e-4) and err[~on].max() < 1e-4


@pytest.mark.parametrize("seed", range(4))
def test_planted_wrong_edges_in_a_triangle_rich_graph_are_rejected_right_ones_stay(seed):
    rng = np.random.default_rng(seed)
    n = 16
    # a camera ring: each image overlaps its three neighbours on either side
    edges = np.array([(i, (i + d) % n) for i in range(n) for d in (1, 2, 3)], np.int64)
    R_abs = Rotation.random(n, random_state=seed).as_matrix()
    R = _noisy(_relative(R_abs, edges), 0.7, rng)  # right edges: ~1 degree off
    wrong = rng.choice(len(edges), 4, replace=False)
    R[wrong] = Rotation.from_rotvec(rng.normal(size=(4, 3))).as_matrix() @ R[wrong]
    weight = rng.integers(40, 400, len(edges)).astype(float)
    weight[wrong] = 400.0  # as strong as any: the triangles, not the counts, decide
    chk = loop_outliers(edges, R, weight, n, max_deg=6.0)
    assert set(np.flatnonzero(chk.rejected)) == set(wrong.tolist())
    assert (chk.triangles > 0).all()


def test_a_chain_keeps_every_edge():
    rng = np.random.default_rng(0)
    n = 10
    edges = np.array([(i, i + 1) for i in range(n - 1)], np.int64)
    R = _relative(Rotation.random(n, random_state=0).as_matrix(), edges)
    R[4] = Rotation.from_rotvec([np.pi / 2, 0, 0]).as_matrix() @ R[4]  # wrong, but unjudgeable
    chk = loop_outliers(edges, R, rng.integers(20, 200, n - 1), n)
    assert len(chk.tri) == 0 and not chk.rejected.any()
    assert np.isnan(chk.share).all()


def test_a_lone_inconsistent_triangle_names_no_edge():
    """One broken triangle says that one of its edges is wrong, not which."""
    edges = np.array([(0, 1), (1, 2), (0, 2), (2, 3)], np.int64)
    R = _relative(Rotation.random(4, random_state=3).as_matrix(), edges)
    R[1] = Rotation.from_rotvec([0, 0, 1.0]).as_matrix() @ R[1]
    chk = loop_outliers(edges, R, np.array([500.0, 20, 500, 50]), 4)
    assert chk.inconsistent[:3].tolist() == [1, 1, 1]
    assert not chk.rejected.any()


def test_a_right_edge_sharing_triangles_with_wrong_ones_is_cleared_once_they_go():
    n = 8
    edges = np.array(list(itertools.combinations(range(n), 2)), np.int64)
    R = _relative(Rotation.random(n, random_state=5).as_matrix(), edges)
    # two wrong edges at camera 0: the triangle (0, 1, 2) is broken twice over, (1, 2) is not
    bad = [int(np.flatnonzero((edges == (0, 1)).all(1))[0]),
           int(np.flatnonzero((edges == (0, 2)).all(1))[0])]
    for k, ang in zip(bad, (0.8, -1.1), strict=True):
        R[k] = Rotation.from_rotvec([ang, 0.3, 0]).as_matrix() @ R[k]
    chk = loop_outliers(edges, R, np.full(len(edges), 100.0), n)
    assert set(np.flatnonzero(chk.rejected)) == set(bad)


def test_inlier_spread_tells_crowded_from_spread_matches():
    rng = np.random.default_rng(0)
    spread = rng.uniform([0, 0], [W, H], (300, 2))
    crowded = rng.normal([500, 100], 8, (300, 2))
    assert inlier_spread(spread, (W, H)) > 0.5
    assert inlier_spread(crowded, (W, H)) < 0.01
    # a few stray matches across the image do not make a crowd look spread
    stray = np.concatenate([crowded, rng.uniform([0, 0], [W, H], (10, 2))])
    assert inlier_spread(stray, (W, H)) < 0.01
    assert inlier_spread(stray, (W, H), keep=1.0) > 0.3
    assert inlier_spread(crowded[:2], (W, H)) == 0.0


# ---------------------------------------------------------------- on a front end's pairs


#: the keypoints of every image of the hand-made front ends below
UV = np.random.default_rng(0).uniform([0, 0], [W, H], (400, 2))


def _edges(poses: list[np.ndarray], pairs: dict[tuple[int, int], np.ndarray],
           inliers: dict[tuple[int, int], np.ndarray]) -> dict[tuple[int, int], PairResult]:
    """Verified keypoint edges with relative rotations ``pairs`` (directions from ``poses``)
    and inlier keypoint indices ``inliers``."""
    none = np.zeros(0, np.int64)
    out = {}
    for (a, b), R in pairs.items():
        t = poses[b][:3, 3] - R @ poses[a][:3, 3]
        out[(a, b)] = PairResult(a, b, none, none, np.zeros(0, bool), 400, 0,
                                 (R, t / np.linalg.norm(t)), None, "edge",
                                 inliers=inliers[(a, b)], info={"inliers": 100})
    return out


def _frontend(n: int, poses: list[np.ndarray], pairs: dict[tuple[int, int], np.ndarray],
              inliers: dict[tuple[int, int], np.ndarray]) -> ImageFrontend:
    """A front end whose images and evaluated pairs are given (no image is read)."""
    feats = [Features(UV, np.zeros((400, 1), np.float32), (W, H)) for _ in range(n)]
    return ImageFrontend.from_evaluated(_records(n), feats,
                                        _edges(poses, pairs, inliers).values())


def _records(n: int) -> list[ImageRecord]:
    K = np.array([[500.0, 0, W / 2], [0, 500.0, H / 2], [0, 0, 1]])
    return [ImageRecord(Path(f"img{i}.png"), f"img{i}.png", K, size=(W, H)) for i in range(n)]


def test_a_front_end_from_evaluated_pairs_names_what_does_not_fit():
    poses, _, pairs, inliers = _planted()
    feats = [Features(UV, np.zeros((400, 1), np.float32), (W, H))] * 4
    edges = [e for e in _edges(poses, pairs, inliers).values() if e.b < 4]
    fe = ImageFrontend.from_evaluated(_records(4), feats, edges)
    assert fe.summary.pairs["edge"] == len(edges) and fe.pair(0, 1) is edges[0]
    assert fe.features(2).keypoints is UV and not fe.summary.boxes
    with pytest.raises(ValueError, match="3 feature sets for 4 images"):
        ImageFrontend.from_evaluated(_records(4), feats[:3], edges)
    with pytest.raises(ValueError, match=r"pair \(0, 1\) given twice"):
        ImageFrontend.from_evaluated(_records(4), feats, [edges[0], edges[0]])
    with pytest.raises(ValueError, match=r"pair \(0, 1\) is not two images a < b of the 1"):
        ImageFrontend.from_evaluated(_records(1), feats[:1], edges[:1])


def _planted(n: int = 7) -> tuple[list, list, dict, dict]:
    """``n`` cameras, every pair an edge: (2, 5) 109 deg wrong, (0, 6) right but with every
    inlier on one small patch of the first image. Returns poses, pairs, rotations, inliers."""
    R_abs = Rotation.random(n, random_state=7).as_matrix()
    poses = []
    for i in range(n):
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R_abs[i], [np.cos(i), np.sin(i), 3.0]
        poses.append(M)
    keys = list(itertools.combinations(range(n), 2))
    pairs = {(a, b): R_abs[b] @ R_abs[a].T for a, b in keys}
    pairs[(2, 5)] = Rotation.from_rotvec([0, 1.9, 0]).as_matrix() @ pairs[(2, 5)]  # wrong
    everywhere = np.stack([np.arange(400)] * 2, axis=1)
    inliers = {k: everywhere for k in keys}
    patch = np.flatnonzero((np.abs(UV[:, 0] - 100) < 30) & (np.abs(UV[:, 1] - 100) < 30))
    inliers[(0, 6)] = np.stack([patch, patch], axis=1)
    return poses, keys, pairs, inliers


def test_screen_edges_names_the_crowded_and_the_loop_breaking_edge_and_changes_nothing():
    # on plain pair results: no front end
    poses, _, pairs, inliers = _planted()
    edges = _edges(poses, pairs, inliers)
    found = screen_edges(list(edges.values()), lambda i: UV, [(W, H)] * 7, "kp", VerifyRules())
    assert [((p.a, p.b), r) for p, r in found.rejected] == [((0, 6), "crowded"),
                                                            ((2, 5), "loop")]
    assert found.counts() == {"crowded": 1, "loop": 1, "triangles": found.triangles}
    assert found.triangles == 30  # C(7, 3) = 35 less the 5 through the crowded edge
    assert all(p.is_edge and p.inliers is not None for p in edges.values())
    assert edges[(2, 5)].info["loop_inconsistent"] == 5 and edges[(0, 6)].info["spread"] < 0.015
    # images of unknown size: no spread test, the loop check still runs
    found = screen_edges(list(_edges(poses, pairs, inliers).values()), lambda i: UV,
                         [None] * 7, "kp", VerifyRules())
    assert [((p.a, p.b), r) for p, r in found.rejected] == [((2, 5), "loop")]


def test_screen_edges_books_crowded_and_loop_rejections_like_other_rejections():
    n = 7
    poses, keys, pairs, inliers = _planted(n)
    fe = _frontend(n, poses, pairs, inliers)
    out = fe.screen(keys, VerifyRules())
    assert out["crowded"] == 1 and out["loop"] == 1
    rejected = {(r["source"], r["target"]): r for r in fe.rejected_pairs()}
    assert set(rejected) == {("img0.png", "img6.png"), ("img2.png", "img5.png")}
    assert rejected[("img2.png", "img5.png")]["reason"] == "loop"
    assert rejected[("img2.png", "img5.png")]["loop_inconsistent"] == 5
    assert rejected[("img0.png", "img6.png")]["reason"] == "crowded"
    assert rejected[("img0.png", "img6.png")]["spread"] < 0.015
    for k in ((2, 5), (0, 6)):
        p = fe.pair(*k)
        assert not p.is_edge and p.inliers is None  # nor do its matches feed the tracks
    assert fe.pair(0, 1).is_edge and fe.pair(0, 1).info["loop_inconsistent"] == 0
    assert fe.verified_matches().keys() == set(keys) - {(2, 5), (0, 6)}
    s = fe.summary
    assert s.pairs["edge"] == len(keys) - 2 and s.pairs["unmatched"] == 2
    assert dict(s.rejected) == {"kp:crowded": 1, "kp:loop": 1}
    lines = "\n".join(s.lines())
    assert f"{len(keys)} checked, {len(keys) - 2} edges" in lines
    assert "2 rejected by two-view verification" in lines
    assert "kp:crowded 1, kp:loop 1" in lines
    graph, _ = fe.graph(range(n), pairs=keys)
    assert graph.num_edges == len(keys) - 2


def test_screen_edges_off_keeps_every_edge():
    n = 5
    R_abs = Rotation.random(n, random_state=2).as_matrix()
    poses = [np.block([[R_abs[i], np.array([[i], [1.0], [2.0]])], [np.zeros((1, 3)), 1]])
             for i in range(n)]
    keys = list(itertools.combinations(range(n), 2))
    pairs = {(a, b): R_abs[b] @ R_abs[a].T for a, b in keys}
    pairs[(1, 3)] = Rotation.from_rotvec([1.0, 0, 0]).as_matrix() @ pairs[(1, 3)]
    inliers = {k: np.stack([np.arange(3)] * 2, axis=1) for k in keys}
    fe = _frontend(n, poses, pairs, inliers)
    out = fe.screen(keys, VerifyRules(min_spread=0.0, max_loop_deg=0.0))
    assert out == {"crowded": 0, "loop": 0, "triangles": 0}
    assert all(fe.pair(*k).is_edge for k in keys)
    assert not fe.summary.rejected


def test_rules_ranges():
    with pytest.raises(ValueError, match="min_spread"):
        VerifyRules(min_spread=1.5)
    with pytest.raises(ValueError, match="max_loop_share"):
        VerifyRules(max_loop_share=-0.1)
    with pytest.raises(ValueError, match="max_loop_deg"):
        VerifyRules(max_loop_deg=float("nan"))


def test_ordinary_rendered_pairs_all_pass(tmp_path):
    """A textured rendered sequence: every verified edge keeps its place (no crowd, no broken
    triangle), and each one records what was measured."""
    from posernet.data.render import render_sevenscenes
    from posernet.frontend.features import SiftMatcher
    from posernet.frontend.images import records_for_images

    seq = render_sevenscenes(tmp_path, "chess", seed=4, train_sequences=0, test_sequences=1,
                             frames_per_sequence=6, width=320, height=240, focal=292.5,
                             progress=False)
    folder = next(p for p in seq.rglob("seq-*") if p.is_dir())
    records = records_for_images(folder, "292.5,292.5,160,120", "*.color.png", "none")
    fe = ImageFrontend(records, None, SiftMatcher(), edge_rule="verified")
    keys = list(itertools.combinations(range(len(records)), 2))
    fe.evaluate_pairs(keys, progress=False)
    edges = [k for k in keys if fe.pair(*k).is_edge]
    out = fe.screen(keys)
    assert len(edges) >= 8 and out["triangles"] >= 4
    assert out["crowded"] == 0 and out["loop"] == 0
    assert all(fe.pair(*k).is_edge and fe.pair(*k).info["spread"] > 0.05 for k in edges)


@pytest.mark.parametrize(("override", "ok"), [
    ("verify.min_spread=0.05", True), ("verify.min_spread=1.5", False),
    ("verify.max_loop_deg=0", True), ("verify.max_loop_deg=200", False),
    ("verify.max_loop_share=0.7", True), ("verify.max_loop_share=-1", False),
    ("verify.max_loop_deg=abc", False),
])
def test_config_check_knows_the_screening_options(override, ok, tmp_path):
    from hydra import compose, initialize_config_dir

    from posernet.cli import CONFIG_DIR
    from posernet.cli.validation import ConfigValueError, check_config

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("reconstruct", overrides=["images=photos", "intrinsics='1,1,1,1'",
                                                f"out_dir={tmp_path / 'out'}", override])
    if ok:
        check_config(cfg, "reconstruct")
    else:
        with pytest.raises(ConfigValueError, match=f"^{override.split('=')[0]}"):
            check_config(cfg, "reconstruct")

"""Each stage's typed result built by hand and consumed alone: no images, no ImageFrontend.

A small synthetic scene (cameras on an arc around a cloud of points, exact projections) gives
the front end's results directly (:mod:`posernet.frontend.results`); the stages after it
(averaging, bundle adjustment, self-check, outputs) and the ground-truth helpers
(:mod:`posernet.ground_truth`) run on them.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import MappingProxyType

import cv2
import numpy as np
import pytest
import torch

from posernet.frontend.features import Matches
from posernet.frontend.images import ImageRecord
from posernet.frontend.pairs import PairSelection
from posernet.frontend.results import (
    FrontendResult,
    ImageFeatures,
    MatchResult,
    PairMatches,
    TwoViewGeometry,
    assemble_frontend_result,
)
from posernet.ground_truth import align_cameras, trajectory_table
from posernet.reconstruction import (
    bundle_stage,
    poses_json,
    solve_view_graph,
    stage_choice_line,
    trajectory_errors_table,
    write_camera_view,
)
from posernet.refinement import refine_graphs
from posernet.sync import get_backend

N, P, W, H = 5, 120, 320, 240
K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])


def _look_at(centre: np.ndarray) -> np.ndarray:
    """World-to-camera (4, 4) of a camera at ``centre`` looking at the origin (y down)."""
    z = -centre / np.linalg.norm(centre)
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, -R @ centre
    return T


def _scene(seed: int = 0) -> tuple[list[np.ndarray], np.ndarray, list[np.ndarray]]:
    """``N`` world-to-camera poses, ``(P, 3)`` points and each camera's ``(P, 2)`` pixels."""
    rng = np.random.default_rng(seed)
    angles = np.linspace(-0.5, 0.5, N)
    w2c = [_look_at(np.array([4 * np.sin(a), 0.3 * np.cos(3 * a), -4 * np.cos(a)]))
           for a in angles]
    pts = rng.uniform(-1, 1, (P, 3))
    uv = []
    for T in w2c:
        x = pts @ T[:3, :3].T + T[:3, 3]
        p = x @ K.T
        uv.append(p[:, :2] / p[:, 2:] + rng.normal(0, 0.2, (P, 2)))
        assert (x[:, 2] > 0).all() and (uv[-1] > 0).all() and (uv[-1] < [W, H]).all()
    return w2c, pts, uv


def _hand_made(folder: Path | None = None) -> tuple[FrontendResult, list[np.ndarray]]:
    """The front end's result of the synthetic scene, every pair an edge whose inliers are
    every point (keypoint ``k`` of each image is point ``k``); with ``folder``, small image
    files for the records (the point colours are read from them)."""
    w2c, _, uv = _scene()
    records = []
    for i, T in enumerate(w2c):
        path = Path(f"cam{i}.png")
        if folder is not None:
            path = folder / path
            cv2.imwrite(str(path), np.full((H, W, 3), 40 * i, np.uint8))
        records.append(ImageRecord(path=path, key=path.name, K=K.copy(), size=(W, H),
                                   c2w=np.linalg.inv(T)))
    images = tuple(ImageFeatures(u, (W, H)) for u in uv)
    idx = np.arange(P)
    pairs = {}
    for a in range(N):
        for b in range(a + 1, N):
            T = w2c[b] @ np.linalg.inv(w2c[a])  # camera a -> camera b
            t = T[:3, 3] / np.linalg.norm(T[:3, 3])
            geo = TwoViewGeometry(a, b, "edge", kp=(T[:3, :3], t),
                                  inliers=np.stack([idx, idx], 1),
                                  info=MappingProxyType({"inliers": P}))
            pairs[(a, b)] = PairMatches(geo, Matches(uv[a], uv[b], np.ones(P), idx, idx))
    selection = PairSelection(sorted(pairs), "exhaustive", 1, N, [], 0.0)
    view = assemble_frontend_result(records, MatchResult(images, pairs), selection,
                                    meta={"name": "synthetic"})
    return view, w2c


def test_typed_results_are_frozen_and_assemble_into_the_graph() -> None:
    view, _ = _hand_made()
    assert view.graph.num_edges == N * (N - 1) // 2 and view.graph.pose_gt is not None
    assert view.graph.meta["camera_ids"] == [f"cam{i}.png" for i in range(N)]
    with pytest.raises(dataclasses.FrozenInstanceError):
        view.pair(0, 1).status = "unmatched"  # type: ignore[misc]
    assert view.pair(3, 1) is view.pair(1, 3)
    assert set(view.verified_matches()) == set(view.matches.pairs)
    assert view.rejected_pairs() == []
    assert len(view.matches.pairs[(0, 1)].verified()) == P


def test_bundle_stage_from_hand_made_matches() -> None:
    """Averaging, then the bundle stage on nothing but the hand-made matches result."""
    view, w2c = _hand_made()
    result = refine_graphs(None, [view.graph], backend=get_backend("rotation_translation"),
                           batch_size=1, progress=False)
    runs = bundle_stage(view, result, "initial")
    assert "initial+ba" in result.absolute and len(runs) == 1
    run = runs[0]
    assert run.points.shape[0] >= 0.9 * P and run.refined.all()
    assert run.stats["median_error_after"] < 0.5
    # positions up to a similarity: against the ground truth
    est = {str(i): np.linalg.inv(result.absolute["initial+ba"][0][i].double().numpy())
           for i in range(N)}
    gt = {str(i): np.linalg.inv(T) for i, T in enumerate(w2c)}
    moved = align_cameras(est, gt)
    assert moved is not None
    err = [np.linalg.norm(moved.cameras[k][:3, 3] - gt[k][:3, 3]) for k in gt]
    assert max(err) < 0.01


def test_stages_after_the_front_end_run_on_its_result_alone(tmp_path) -> None:
    view, _ = _hand_made(tmp_path)
    rec = solve_view_graph(view, None, get_backend("rotation_translation"))
    assert rec.stage == "initial+ba" and rec.check is not None and rec.check.verified
    assert rec.graph is view.graph and rec.pairs is view.selection
    record = poses_json(rec)
    assert all(c["solved"] for c in record["cameras"].values())
    assert all(e["track_matches"] == P for e in record["edges"])
    page = write_camera_view(tmp_path / "cameras.html", rec, record)
    assert page is not None and '"units":"ground-truth units' in page.read_text()
    table = trajectory_errors_table(rec, record)
    assert table is not None and f"{N} cameras in name order" in table
    json.dumps(record)  # JSON-ready


class _Refiner(torch.nn.Module):
    """A stand-in refiner: the input edge poses, or with ``scramble`` random ones."""

    def __init__(self, scramble: bool) -> None:
        super().__init__()
        self.scramble = scramble

    def forward(self, batch) -> torch.Tensor:
        pose = batch.edge_pose.clone()
        if self.scramble:
            g = torch.Generator().manual_seed(0)
            pose = torch.nn.functional.normalize(
                torch.randn(pose.shape, generator=g, dtype=pose.dtype), dim=-1)
            pose[:, 4:] = torch.nn.functional.normalize(pose[:, 4:], dim=-1)
        return pose


@pytest.mark.parametrize("scramble", [False, True])
def test_the_refined_stage_is_final_only_where_it_passes_the_check(scramble: bool) -> None:
    """A refiner whose poses fail the self-check where the unrefined ones pass gives way to
    them; one that passes as many is kept."""
    view, _ = _hand_made()
    rec = solve_view_graph(view, _Refiner(scramble), get_backend("rotation_translation"),
                           bundle_adjust=False)
    assert rec.stage_checks is not None and rec.stage_checks["initial"] == N
    if scramble:
        assert rec.stage_checks["refined"] < N and rec.stage == "initial"
    else:
        assert rec.stage_checks["refined"] == N and rec.stage == "refined"
    assert rec.check is not None and int(rec.check.passed.sum()) == N
    record = poses_json(rec)
    assert record["stage"] == rec.stage and record["stage_checks"] == rec.stage_checks
    assert all(c["solved"] for c in record["cameras"].values())
    line = stage_choice_line(rec)
    assert line is not None and ("unrefined" in line) == scramble


def test_a_graph_without_edges_is_refused() -> None:
    view, _ = _hand_made()
    none = dataclasses.replace(view.graph, edge_index=view.graph.edge_index[:, :0])
    with pytest.raises(ValueError, match="no edge"):
        solve_view_graph(dataclasses.replace(view, graph=none), None,
                         get_backend("rotation_translation"))


def _similar(c2w: dict[str, np.ndarray], s: float, R: np.ndarray,
             t: np.ndarray) -> dict[str, np.ndarray]:
    """Camera-to-world poses ``c2w`` seen in a frame where ``x -> s R x + t`` maps back."""
    out = {}
    for k, m in c2w.items():
        e = np.eye(4)
        e[:3, :3] = R.T @ m[:3, :3]
        e[:3, 3] = R.T @ (m[:3, 3] - t) / s
        out[k] = e
    return out


def test_ground_truth_alignment_from_plain_poses() -> None:
    w2c, pts, _ = _scene()
    gt = {f"c{i}": np.linalg.inv(T) for i, T in enumerate(w2c)}
    a = 0.7
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    t = np.array([1.0, -2.0, 0.5])
    est = _similar(gt, 2.5, R, t)
    est_pts = (pts - t) @ R / 2.5
    moved = align_cameras({k: v.tolist() for k, v in est.items()}, gt, est_pts)
    assert moved is not None and moved.scale == pytest.approx(2.5)
    np.testing.assert_allclose(moved.R, R, atol=1e-9)
    for k in gt:
        np.testing.assert_allclose(moved.cameras[k], gt[k], atol=1e-9)
    np.testing.assert_allclose(moved.points, pts, atol=1e-9)
    # undetermined: fewer than 3 cameras, or one without ground truth
    assert align_cameras({k: est[k] for k in ("c0", "c1")}, gt) is None
    assert align_cameras(est, {k: v for k, v in gt.items() if k != "c2"}) is None


def test_trajectory_table_from_plain_poses() -> None:
    w2c, _, _ = _scene()
    gt = {f"c{i}": np.linalg.inv(T) for i, T in enumerate(w2c)}
    text = trajectory_table(_similar(gt, 0.5, np.eye(3), np.zeros(3)), gt)
    assert text is not None and "scale 0.5)" in text
    rows = [ln for ln in text.splitlines() if ln.startswith("| APE")]
    assert rows and float(rows[0].split("|")[2]) == pytest.approx(0.0, abs=1e-6)
    assert trajectory_table({k: gt[k] for k in ("c0", "c1")}, gt) is None


def test_a_block_nothing_ties_to_the_rest_is_a_component_of_its_own_everywhere(tmp_path):
    """Cameras 0-2 tied by a triangle of pairs; camera 3 joined to them by one pair whose
    points no third camera sees, and camera 4 to camera 3 by another: the pair (3, 4) is a
    block of its own. The self-check splits it off into a component (not unsolved), and the
    split shows the same way in poses.json, the COLMAP models and the one-line summary."""
    from posernet.reconstruction import write_colmap_models
    from posernet.sfm.selfcheck import CheckOptions

    view, _ = _hand_made(tmp_path)
    keep = {(0, 1): range(0, 60), (1, 2): range(0, 60), (0, 2): range(0, 60),
            (2, 3): range(60, 90), (3, 4): range(90, 120)}
    pairs = {}
    for k, pm in view.matches.pairs.items():
        if k in keep:
            idx = np.asarray(keep[k])
            geo = dataclasses.replace(pm.geometry, inliers=np.stack([idx, idx], 1))
            pairs[k] = PairMatches(geo, pm.matches.subset(idx))
    view = assemble_frontend_result(view.records, MatchResult(view.matches.images, pairs),
                                    PairSelection(sorted(pairs), "exhaustive", 1, N, [], 0.0))
    rec = solve_view_graph(view, None, get_backend("rotation_translation"),
                           check=CheckOptions(min_single_pair_inliers=20))
    check = rec.check
    assert check.passed.all() and check.split.tolist() == [False] * 3 + [True] * 2
    assert "2 of them in 1 component(s) of their own" in check.line()
    record = poses_json(rec)
    comps = [c["component"] for c in record["cameras"].values()]
    assert comps[:3] == [comps[0]] * 3 and comps[3] == comps[4] != comps[0]
    assert all("component of its own" in c["note"] for c in list(record["cameras"].values())[3:])
    assert record["self_check"]["split"] == {"cam3.png": 1, "cam4.png": 1}
    models = write_colmap_models(tmp_path / "sparse", rec)
    assert len(models) == 2
    images = [(m / "images.txt").read_text() for m in models]
    assert "cam0.png" in images[0] and "cam3.png" not in images[0]
    assert "cam3.png" in images[1] and "cam4.png" in images[1] and "cam2.png" not in images[1]
    points = [sum(1 for ln in (m / "points3D.txt").read_text().splitlines()
                  if ln and not ln.startswith("#")) for m in models]
    assert points[1] == 30  # the pair's own points, seen by both of its cameras

"""Tracks from dense keypoints whose matches slide to a neighbour (XFeat on weak texture)."""

from __future__ import annotations

import numpy as np

from posernet.sfm import BundleOptions, build_tracks, bundle_adjust_reconstruction
from posernet.sfm.synthetic import make_scene
from posernet.sfm.triangulation import project


def test_one_slid_pair_keeps_every_track() -> None:
    """Five pairs match keypoint i to keypoint i, one pair slides it to i + 1: the slides chain
    every keypoint into one component, yet the consistent matches still make every track."""
    n = 20
    same = np.stack([np.arange(n), np.arange(n)], 1)
    matches = {(0, 1): same, (0, 2): same, (1, 2): same, (1, 3): same, (2, 3): same,
               (0, 3): np.stack([np.arange(n - 1), np.arange(1, n)], 1)}
    tracks = build_tracks(matches, [n] * 4)
    assert tracks.num_tracks == n
    assert (tracks.length == 4).all()
    for t in range(n):  # track t is keypoint k of every image
        assert len(set(tracks.keypoint[tracks.track == t].tolist())) == 1


def _edge_scene(slide: float, seed: int = 0) -> tuple:
    """Points packed along 3D segments (a weakly textured scene's edges), seen by a ring of
    cameras; each pair's match of a point goes to its neighbour on the segment with
    probability ``slide`` (about a pixel off: geometrically still right)."""
    sc = make_scene(num_cameras=8, num_points=10, seed=seed)
    rng = np.random.default_rng(seed)
    per, segs = 60, 8
    a, b = rng.uniform(-1, 1, (segs, 3)), rng.uniform(-1, 1, (segs, 3))
    s = np.linspace(0, 1, per)
    pts = (a[:, None] * (1 - s[None, :, None]) + b[:, None] * s[None, :, None]).reshape(-1, 3)
    n_cam, n_pts = sc.w2c.shape[0], pts.shape[0]
    uv = []
    for i in range(n_cam):
        pix, _ = project(pts, np.repeat(sc.K[i : i + 1], n_pts, 0),
                         np.repeat(sc.w2c[i : i + 1], n_pts, 0))
        uv.append(pix + rng.normal(0, 0.3, pix.shape))
    along = np.arange(n_pts) % per
    matches = {}
    for i in range(n_cam):
        for j in range(i + 1, n_cam):
            shift = np.where(rng.uniform(size=n_pts) < slide, rng.choice([-1, 1], n_pts), 0)
            tgt = np.clip(along + shift, 0, per - 1) - along + np.arange(n_pts)
            matches[(i, j)] = np.stack([np.arange(n_pts), tgt], 1)
    return sc, uv, matches, n_pts


def test_bundle_adjustment_keeps_points_of_slid_matches() -> None:
    """A third of the matches slid: tracks still form and bundle adjustment keeps most points
    (a track per connected component lost nearly all of them)."""
    sc, uv, matches, n_pts = _edge_scene(slide=0.3)
    res = bundle_adjust_reconstruction(uv, matches, sc.K, None, sc.w2c,
                                       np.ones(len(uv), bool), BundleOptions(start="averaged"))
    assert res.refined.all()
    assert len(res.points) > 0.5 * n_pts

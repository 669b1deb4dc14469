"""Bundle adjustment against the number of cameras: the reduced-camera-system solve (dense
Cholesky against conjugate gradients) and the whole BA stage, on sequence-like problems.

Problem (one per size, :func:`sweep_scene`): a video-like sweep, ``N`` cameras on a circle
of radius 4 around a room-sized box of points, looking at its centre, going round 1.5 times
(the second half lap sees again what the first saw: loop closures, as in the rendered room
sequences); a point is seen by the cameras within a small angle of its own direction (about
8 consecutive frames per lap, 12 views per track), 40 points per camera, 0.5 px noise, 5% gross
outlier observations (15-60 px); matches between the images sharing at least 15 points; poses
perturbed by 1 deg and 1% of their distance to the centre (camera 0 kept), as motion
averaging leaves them. Every camera shares points with cameras far along the sequence, so the
reduced camera system is nearly dense, as on the rendered 512-frame sequence (98% of its
6x6 blocks).

Tables:

* ``solve``: one Levenberg-Marquardt system (the first, ``lam=1e-4``) of
  :func:`posernet.sfm.bundle_adjust` on the observations at the start (points triangulated
  there), solved by the dense Cholesky factorisation of the reduced camera system and by
  conjugate gradients on the implicit reduced system (block-Jacobi preconditioner); the
  seconds of each (fastest of ``--repeat``, building the system included), the conjugate
  gradient iterations and the relative difference of the two camera steps;
* ``stage``: :func:`posernet.sfm.bundle_adjust_reconstruction` (tracks, triangulation, two
  rounds of BA with filtering; default options) from the matches and perturbed poses: wall
  time, its parts, the LM evaluations and the median / largest rotation and position errors
  against the ground truth after a similarity alignment; with ``--stage-direct-max`` the same
  stage with the direct solve (``pcg_min_cameras`` above the size) up to that size.

    python benchmarks/bench_ba_scale.py                  # 256, 512, 1024 cameras
    python benchmarks/bench_ba_scale.py --quick          # 64, 128 (results/quick/)
    python benchmarks/bench_ba_scale.py --sizes 64 128 256 --stage-direct-max 256

Writes ``benchmarks/results/ba_scale.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import table, write_results

from posernet.metrics import absolute_pose_errors_per_camera
from posernet.pinhole import look_at
from posernet.sfm import BundleOptions, bundle_adjust_reconstruction
from posernet.sfm.bundle import _Problem, _Schur
from posernet.sfm.synthetic import SyntheticScene, _pair_matches, perturb_poses
from posernet.sfm.triangulation import triangulate_tracks

NEVER = 10**9  # pcg_min_cameras that keeps the direct solve


def sweep_scene(n: int, points_per_camera: int = 40, views_per_lap: int = 8,
                laps: float = 1.5, seed: int = 0) -> SyntheticScene:
    """The sweep of the module docstring: ``n`` cameras, ``points_per_camera * n`` points."""
    rng = np.random.default_rng(seed)
    W, H, f = 640, 480, 500.0
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    P = points_per_camera * n
    pts = rng.uniform(-1, 1, (P, 3)) * np.array([1.5, 1.0, 1.5])
    home = rng.uniform(0, 2 * np.pi, P)  # the direction each point is seen from
    angle = 2 * np.pi * laps * np.arange(n) / n
    half = np.pi * views_per_lap * laps / n  # half the angle a point is seen over, per lap
    up = np.array([0.0, -1.0, 0.0])
    centres = 4.0 * np.stack([np.sin(angle), 0.2 * np.sin(5 * angle), -np.cos(angle)], 1)
    w2c = look_at(centres, np.zeros_like(centres), up=up)
    by_home = np.argsort(home, kind="stable")
    home_sorted = home[by_home]
    uv, kp_point, oi, op, ok = [], [], [], [], []
    for i in range(n):
        a = angle[i] % (2 * np.pi)
        lo, hi = np.searchsorted(home_sorted, (a - half, a + half))
        cand = by_home[lo:hi]
        for shift in (-2 * np.pi, 2 * np.pi):  # the window across 0 / 2 pi
            lo, hi = np.searchsorted(home_sorted, (a + shift - half, a + shift + half))
            cand = np.concatenate((cand, by_home[lo:hi]))
        cand = np.sort(cand)
        pc = pts[cand] @ w2c[i, :3, :3].T + w2c[i, :3, 3]
        pix = pc @ K.T
        pix = pix[:, :2] / pix[:, 2:]
        inside = (pc[:, 2] > 0.1) & (pix[:, 0] >= 0) & (pix[:, 0] < W) & (pix[:, 1] >= 0) & \
            (pix[:, 1] < H)
        sel = rng.permutation(np.flatnonzero(inside))
        uv.append(pix[sel] + rng.normal(0, 0.5, (sel.size, 2)))
        kp_point.append(cand[sel])
        oi.append(np.full(sel.size, i))
        op.append(cand[sel])
        ok.append(np.arange(sel.size))
    return SyntheticScene(K=np.repeat(K[None], n, 0), w2c=w2c, points=pts, uv=uv,
                          kp_point=kp_point, pair_matches=_pair_matches(kp_point, P, 15),
                          obs_image=np.concatenate(oi), obs_point=np.concatenate(op),
                          obs_kp=np.concatenate(ok), xy=np.concatenate(uv), image_size=(W, H))


def problem(n: int, seed: int = 0) -> tuple[SyntheticScene, np.ndarray]:
    """The sweep of ``n`` cameras (observations with outliers) and its perturbed poses."""
    s = sweep_scene(n, seed=seed)
    rng = np.random.default_rng(seed + 2)
    out = rng.uniform(size=len(s.xy)) < 0.05
    k = int(out.sum())
    s.xy[out] += rng.uniform(15, 60, (k, 2)) * rng.choice([-1, 1], (k, 2))
    start = 0
    for i, u in enumerate(s.uv):  # the same outliers in the per-image keypoints
        s.uv[i] = s.xy[start:start + len(u)]
        start += len(u)
    return s, perturb_poses(s.w2c, 1.0, 0.01, seed=seed + 1, keep=(0,))


def solve_row(s: SyntheticScene, w2c0: np.ndarray, repeat: int) -> list[object]:
    """Seconds of one reduced solve, direct and PCG, and how far apart their steps are."""
    tri = triangulate_tracks(s.xy, s.obs_point, s.obs_image, s.points.shape[0], s.K, w2c0,
                             max_reproj_px=np.inf, min_angle_deg=0.0)
    keep = tri.valid[s.obs_point]
    prob = _Problem(w2c0, np.nan_to_num(tri.points), s.K, s.xy[keep], s.obs_image[keep],
                    s.obs_point[keep], np.array([0]), "none")
    x = prob.x0()
    blocks, r = prob.blocks(x), prob.residuals(x)
    out, secs, iters = {}, {}, 0
    for name, it in (("direct", False), ("pcg", True)):
        best = np.inf
        for _ in range(repeat):
            t0 = time.perf_counter()
            sys_ = _Schur(prob, *blocks, r, iterative=it)
            out[name] = sys_.step(1e-4)[0]
            best = min(best, time.perf_counter() - t0)
            iters = sys_.pcg_iterations[-1] if it else iters
        secs[name] = best
    diff = np.linalg.norm(out["pcg"] - out["direct"]) / np.linalg.norm(out["direct"])
    return [prob.var_cam.size, int(keep.sum()), f"{secs['direct']:.2f}", f"{secs['pcg']:.2f}",
            f"{secs['direct'] / secs['pcg']:.1f}", iters, f"{diff:.1e}"]


def stage_row(s: SyntheticScene, w2c0: np.ndarray, pcg_min: int, label: str) -> list[object]:
    """The BA stage from the matches and the perturbed poses; wall, parts and errors."""
    n = w2c0.shape[0]
    opt = dataclasses.replace(BundleOptions(), pcg_min_cameras=pcg_min)
    t0 = time.perf_counter()
    res = bundle_adjust_reconstruction(s.uv, s.pair_matches, s.K, None, w2c0,
                                       np.ones(n, bool), opt)
    wall = time.perf_counter() - t0
    g = torch.zeros(n, dtype=torch.long)
    rot, pos = absolute_pose_errors_per_camera(torch.from_numpy(res.w2c),
                                               torch.from_numpy(s.w2c), g, 1)
    sec = res.stats["seconds"]
    parts = ", ".join(f"{k} {v:.1f}" for k, v in sec.items() if k != "total")
    evals = "+".join(str(b.iterations) for b in res.bundles)
    return [n, label, f"{wall:.1f}", f"{wall / n * 1000:.0f}", parts, evals,
            f"{int(res.refined.sum())}/{n}", f"{float(rot.median()):.4f}",
            f"{float(rot.max()):.4f}", f"{float(pos.median()):.5f}", f"{float(pos.max()):.5f}"]


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", nargs="*", type=int, default=[256, 512, 1024])
    p.add_argument("--repeat", type=int, default=1, help="solves per method (fastest kept)")
    p.add_argument("--stage-direct-max", type=int, default=0,
                   help="also run the stage with the direct solve up to this many cameras")
    p.add_argument("--skip-stage", action="store_true")
    p.add_argument("--quick", action="store_true", help="64 and 128 cameras")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if args.quick:
        args.sizes = [64, 128]
    solves, stages = [], []
    for n in args.sizes:
        s, w2c0 = problem(n)
        solves.append(solve_row(s, w2c0, args.repeat))
        print("solve", solves[-1], flush=True)
        if args.skip_stage:
            continue
        stages.append(stage_row(s, w2c0, BundleOptions().pcg_min_cameras, "default"))
        print("stage", stages[-1], flush=True)
        if n <= args.stage_direct_max:
            stages.append(stage_row(s, w2c0, NEVER, "direct solve"))
            print("stage", stages[-1], flush=True)
    body = [
        "Problems: `sweep_scene` (cameras going 1.5 times round a room-sized box of points, "
        "about 8 consecutive frames per lap seeing a point, so loop closures link the laps; "
        "40 points per camera, 12 views per track), 0.5 px noise, 5% outlier observations "
        "(15-60 px), poses perturbed 1 deg / 1% of their distance (camera 0 kept); one "
        "process, numpy's BLAS threads at their default; a shared 2-core machine, so ratios "
        "within one row are more telling than the seconds.", "",
        "## One reduced-camera-system solve (first LM system, lam = 1e-4)", "",
        "Seconds include forming the system (direct: `S = U - W V^-1 W^T` dense, then "
        "Cholesky; PCG: the block-Jacobi preconditioner, then scipy's `cg` on the implicit "
        f"`S` to a relative residual of {_Schur.pcg_rtol:g}).", "",
        *table(["cameras", "observations", "direct (s)", "PCG (s)", "direct / PCG",
                "PCG iterations", "step difference (rel.)"], solves),
    ]
    if stages:
        body += [
            "", "## The BA stage (`bundle_adjust_reconstruction`, default options)", "",
            f"`default`: PCG from {BundleOptions().pcg_min_cameras} cameras on. Errors against "
            "the ground truth after a similarity alignment (rotation in degrees, position in "
            "scene units; cameras are 4 units from the centre). Evaluations: LM evaluations per BA "
            "round.", "",
            *table(["cameras", "solve", "wall (s)", "ms / camera", "parts (s)",
                    "evaluations", "refined", "rot. median", "rot. max", "pos. median",
                    "pos. max"], stages),
        ]
    write_results("ba_scale", "Bundle adjustment against the number of cameras", body,
                  args.quick, "cpu", args.out)


if __name__ == "__main__":
    main()

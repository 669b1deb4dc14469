"""Benchmark bundle-adjustment solvers on the same synthetic problems.

Problem (one per size): a synthetic scene (:func:`posernet.sfm.synthetic.make_scene`), 0.5 px
pixel noise, a fraction of gross outlier observations (15-60 px), camera poses perturbed by a
few degrees and a share of their distance to the scene (as motion averaging leaves them), 3D
points triangulated (DLT) at the perturbed poses. Every solver gets the same start, the same
Cauchy loss with the same scale (px), one camera's pose held fixed and the scale free.

Solvers:

* ``lm-schur`` -- :func:`posernet.sfm.bundle_adjust`, the default: Levenberg-Marquardt with
  exact Schur-complement steps (dense reduced camera system, scipy Cholesky), the observations
  reweighted every iteration with a graduated loss scale, analytic sparse Jacobian;
  (scipy's trf, reweighted or with its own robust loss, stood beside it until it lost on
  every problem here: ``benchmarks/results/ba.md`` keeps that run);
* ``gtsam`` -- projection factors with a robust Cauchy noise model, Levenberg-Marquardt
  (optional: ``pip install gtsam``);
* ``pycolmap`` -- COLMAP's Ceres bundle adjuster through pycolmap (optional).

Reported per solver (fastest of ``--repeat`` runs): wall time of the solve (and of building
the problem for the libraries that need Python loops to do it), RMS and median reprojection
error over the true inliers (px), and the largest / mean camera rotation error (deg) and
position error (scene units; cameras sit ~4 units from the scene centre) after a similarity
alignment to the ground truth.

Usage::

    python benchmarks/bench_ba.py            # sizes 16x3000, 50x15000 -> results/ba.md
    python benchmarks/bench_ba.py --quick    # 8 cameras x 500 points -> results/quick/ba.md

Threads: the BLAS behind numpy/scipy and Ceres are limited to ``--threads`` (default 1) for a
like-for-like comparison; gtsam uses its own TBB pool.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from importlib import metadata
from pathlib import Path


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", nargs="*", default=["16x3000", "50x15000"],
                   help="problems as CAMERASxPOINTS")
    p.add_argument("--rot-deg", type=float, default=3.0, help="pose rotation perturbation")
    p.add_argument("--trans-frac", type=float, default=0.10, help="pose position perturbation")
    p.add_argument("--outliers", type=float, default=0.10, help="fraction of outlier obs")
    p.add_argument("--f-scale", type=float, default=2.0, help="Cauchy loss scale (px)")
    p.add_argument("--max-iters", type=int, default=200)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--repeat", type=int, default=2,
                   help="runs per solver; the fastest is reported (shared machines are noisy)")
    p.add_argument("--skip", nargs="*", default=[], help="solvers to skip")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quick", action="store_true", help="one small problem")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if args.quick:
        args.sizes = ["8x500"]
    if args.out is None:
        args.out = str(Path(__file__).parent / "results" / ("quick" if args.quick else "")
                       / "ba.md")
    return args


ARGS = parse_args() if __name__ == "__main__" else parse_args([])
if __name__ == "__main__":  # before numpy loads its BLAS; importing the module changes nothing
    for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, str(ARGS.threads))

import numpy as np  # noqa: E402  (after the thread limits)
import torch  # noqa: E402

from posernet.metrics import absolute_pose_errors_per_camera  # noqa: E402
from posernet.sfm import BundleOptions, bundle_adjust, triangulate_tracks  # noqa: E402
from posernet.sfm.synthetic import SyntheticScene, make_scene, perturb_poses  # noqa: E402

try:  # optional solvers
    import gtsam
except ImportError:  # pragma: no cover - depends on the environment
    gtsam = None
try:
    import pycolmap
except ImportError:  # pragma: no cover
    pycolmap = None


class Problem:
    """One benchmark problem: ground truth, start and observations (see the module doc)."""

    def __init__(self, cams: int, pts: int, args: argparse.Namespace) -> None:
        # Visibility chosen so tracks are ~5-8 views long at every size.
        vis = min(0.8, 6.0 / max(cams * 0.55, 1))
        self.scene: SyntheticScene = make_scene(cams, pts, noise_px=0.5, visibility=vis,
                                                seed=args.seed)
        s = self.scene
        self.w2c0 = perturb_poses(s.w2c, args.rot_deg, args.trans_frac, seed=args.seed + 1)
        rng = np.random.default_rng(args.seed + 2)
        self.outlier = rng.uniform(size=len(s.xy)) < args.outliers
        n_out = int(self.outlier.sum())
        self.xy = s.xy.copy()
        self.xy[self.outlier] += rng.uniform(15, 60, (n_out, 2)) * rng.choice([-1, 1],
                                                                               (n_out, 2))
        # Points seen at least twice, triangulated at the perturbed poses.
        tri = triangulate_tracks(self.xy, s.obs_point, s.obs_image, s.points.shape[0], s.K,
                                 self.w2c0, max_reproj_px=np.inf, min_angle_deg=0.0)
        keep = tri.valid[s.obs_point]
        self.obs_image, self.obs_point = s.obs_image[keep], s.obs_point[keep]
        self.xy, self.outlier = self.xy[keep], self.outlier[keep]
        self.points0 = np.nan_to_num(tri.points)
        self.fixed = 0
        self.label = f"{cams} cameras, {int(tri.valid.sum())} points, {keep.sum()} obs"

    def evaluate(self, w2c: np.ndarray, points: np.ndarray) -> dict[str, float]:
        s = self.scene
        g = torch.zeros(w2c.shape[0], dtype=torch.long)
        rot, pos = absolute_pose_errors_per_camera(torch.from_numpy(w2c),
                                                   torch.from_numpy(s.w2c), g, 1)
        R, t = w2c[self.obs_image, :3, :3], w2c[self.obs_image, :3, 3]
        pc = np.einsum("oij,oj->oi", R, points[self.obs_point]) + t
        uv = np.einsum("oij,oj->oi", s.K[self.obs_image], pc)
        err = np.linalg.norm(uv[:, :2] / uv[:, 2:] - self.xy, axis=1)[~self.outlier]
        return {"rms_px": float(np.sqrt(np.mean(err**2))), "med_px": float(np.median(err)),
                "rot_max": float(rot.max()), "rot_mean": float(rot.mean()),
                "pos_max": float(pos.max()), "pos_mean": float(pos.mean())}


def run_posernet(pb: Problem, args: argparse.Namespace) -> dict[str, object]:
    opt = BundleOptions(loss="cauchy", f_scale=args.f_scale, max_nfev=args.max_iters * 5)
    t0 = time.perf_counter()
    res = bundle_adjust(pb.w2c0, pb.points0, pb.scene.K, pb.xy, pb.obs_image, pb.obs_point,
                        opt, fixed_cameras=np.array([pb.fixed]))
    dt = time.perf_counter() - t0
    w2c, pts = (res.w2c, res.points)
    if not res.accepted:  # measure what the solver reached, but say it was not accepted
        return {"build_s": 0.0, "solve_s": dt, "iters": res.iterations,
                "note": f"not accepted: {res.message}", **pb.evaluate(w2c, pts)}
    return {"build_s": 0.0, "solve_s": dt, "iters": res.iterations, "note": res.message,
            **pb.evaluate(w2c, pts)}


def run_gtsam(pb: Problem, args: argparse.Namespace) -> dict[str, object]:
    s = pb.scene
    t0 = time.perf_counter()
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    meas = gtsam.noiseModel.Isotropic.Sigma(2, 1.0)
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(
        args.f_scale), meas)
    N = s.w2c.shape[0]
    cal = [gtsam.Cal3_S2(k[0, 0], k[1, 1], k[0, 1], k[0, 2], k[1, 2]) for k in s.K]

    def X(i: int) -> int:
        return gtsam.symbol("x", i)

    def L(j: int) -> int:
        return gtsam.symbol("l", j)

    for o in range(len(pb.xy)):
        i, j = int(pb.obs_image[o]), int(pb.obs_point[o])
        graph.add(gtsam.GenericProjectionFactorCal3_S2(pb.xy[o], noise, X(i), L(j), cal[i]))
    for i in range(N):
        c2w = np.linalg.inv(pb.w2c0[i])  # gtsam poses are camera-to-world
        initial.insert(X(i), gtsam.Pose3(c2w))
    for j in np.unique(pb.obs_point):
        initial.insert(L(int(j)), gtsam.Point3(*pb.points0[j]))
    # Gauge: hold one camera (a very tight prior), scale free like the others.
    graph.add(gtsam.PriorFactorPose3(X(pb.fixed), gtsam.Pose3(np.linalg.inv(pb.w2c0[pb.fixed])),
                                     gtsam.noiseModel.Isotropic.Sigma(6, 1e-8)))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(args.max_iters)
    params.setRelativeErrorTol(1e-6)
    params.setAbsoluteErrorTol(0.0)
    build = time.perf_counter() - t0
    t0 = time.perf_counter()
    opt = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    try:
        result = opt.optimize()
    except RuntimeError as exc:  # e.g. an indeterminant system
        return {"build_s": build, "solve_s": time.perf_counter() - t0, "iters": opt.iterations(),
                "note": f"failed: {str(exc).splitlines()[0]}",
                **pb.evaluate(pb.w2c0, pb.points0)}
    dt = time.perf_counter() - t0
    w2c = np.stack([np.linalg.inv(result.atPose3(X(i)).matrix()) for i in range(N)])
    pts = pb.points0.copy()
    for j in np.unique(pb.obs_point):
        pts[j] = result.atPoint3(L(int(j)))
    return {"build_s": build, "solve_s": dt, "iters": opt.iterations(), "note": "LM",
            **pb.evaluate(w2c, pts)}


def run_pycolmap(pb: Problem, args: argparse.Namespace) -> dict[str, object]:
    s = pb.scene
    N = s.w2c.shape[0]
    t0 = time.perf_counter()
    rec = pycolmap.Reconstruction()
    W, H = s.image_size
    point2d_index = np.zeros(len(pb.xy), np.int64)
    for i in range(N):
        k = s.K[i]
        cam = pycolmap.Camera(model="PINHOLE", width=W, height=H,
                              params=[k[0, 0], k[1, 1], k[0, 2], k[1, 2]], camera_id=i + 1)
        rec.add_camera_with_trivial_rig(cam)
        rows = np.flatnonzero(pb.obs_image == i)
        point2d_index[rows] = np.arange(rows.size)
        img = pycolmap.Image(name=f"{i}", keypoints=pb.xy[rows], camera_id=i + 1,
                             image_id=i + 1)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pb.w2c0[i][:3, :4]))
    order = np.argsort(pb.obs_point, kind="stable")
    bounds = np.flatnonzero(np.diff(pb.obs_point[order])) + 1
    for grp in np.split(order, bounds):
        track = pycolmap.Track()
        track.add_elements([pycolmap.TrackElement(int(pb.obs_image[o]) + 1,
                                                  int(point2d_index[o])) for o in grp])
        rec.add_point3D(pb.points0[pb.obs_point[grp[0]]], track)
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = False
    opts.refine_principal_point = False
    opts.refine_extra_params = False
    opts.print_summary = False
    opts.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    opts.ceres.loss_function_scale = args.f_scale
    opts.ceres.solver_options.num_threads = args.threads
    opts.ceres.solver_options.max_num_iterations = args.max_iters
    opts.ceres.solver_options.function_tolerance = 1e-6
    config = pycolmap.BundleAdjustmentConfig()
    for i in range(N):
        config.add_image(i + 1)
    config.set_constant_rig_from_world_pose(pb.fixed + 1)
    build = time.perf_counter() - t0
    t0 = time.perf_counter()
    summary = pycolmap.create_default_bundle_adjuster(opts, config, rec).solve()
    dt = time.perf_counter() - t0
    w2c = np.tile(np.eye(4), (N, 1, 1))
    for i in range(N):
        w2c[i, :3, :4] = rec.image(i + 1).cam_from_world().matrix()
    pts = pb.points0.copy()
    for pid, p3d in rec.points3D.items():
        el = p3d.track.elements[0]
        o = np.flatnonzero((pb.obs_image == el.image_id - 1)
                           & (point2d_index == el.point2D_idx))[0]
        pts[pb.obs_point[o]] = p3d.xyz
        del pid
    return {"build_s": build, "solve_s": dt, "iters": -1,
            "note": f"Ceres {str(summary.termination_type).split('.')[-1]}",
            **pb.evaluate(w2c, pts)}


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "absent"


def solvers(args: argparse.Namespace) -> dict[str, object]:
    out: dict[str, object] = {
        "lm-schur": lambda pb: run_posernet(pb, args),
    }
    out["gtsam"] = (lambda pb: run_gtsam(pb, args)) if gtsam is not None else None
    out["pycolmap"] = (lambda pb: run_pycolmap(pb, args)) if pycolmap is not None else None
    return {k: v for k, v in out.items() if k not in args.skip}


def main() -> None:
    args = ARGS
    sys.path.insert(0, str(Path(__file__).parent))
    from _common import atomic_write_text  # the benchmarks' shared writer

    lines = ["# Bundle adjustment solvers", "",
             f"Problem: synthetic scene, 0.5 px noise, {args.outliers:.0%} outlier observations "
             f"(15-60 px), poses perturbed {args.rot_deg} deg / {args.trans_frac:.0%} of the "
             "distance, points triangulated at the perturbed poses; Cauchy loss, scale "
             f"{args.f_scale} px; one camera fixed, scale free; threads {args.threads} "
             "(BLAS, Ceres; gtsam: its own pool); solve times are the fastest of "
             f"{args.repeat} runs. Errors: reprojection over the true inliers; "
             "pose errors after a similarity alignment to the ground truth (positions in scene "
             "units, cameras ~4 units from the centre).", "",
             f"Machine: {os.cpu_count()} CPU cores; numpy {np.__version__}; scipy "
             f"{_version('scipy')}; gtsam {_version('gtsam')}; pycolmap "
             f"{_version('pycolmap')}.", ""]
    header = ("| problem | solver | build s | solve s | iters | RMS px | median px | rot max deg "
              "| rot mean deg | pos max | pos mean | note |")
    lines += [header, "|" + "---|" * 12]
    for size in args.sizes:
        cams, pts = (int(v) for v in size.lower().split("x"))
        pb = Problem(cams, pts, args)
        start = pb.evaluate(pb.w2c0, pb.points0)
        print(f"== {pb.label}")
        print(f"   start: {start}")
        lines.append(f"| {pb.label} | (start) | | | | {start['rms_px']:.3f} | "
                     f"{start['med_px']:.3f} | {start['rot_max']:.3f} | {start['rot_mean']:.3f} | "
                     f"{start['pos_max']:.4f} | {start['pos_mean']:.4f} | |")
        for name, fn in solvers(args).items():
            if fn is None:
                print(f"   {name}: not installed, skipped")
                lines.append(f"| {pb.label} | {name} | | | | | | | | | | not installed |")
                continue
            runs = [fn(pb) for _ in range(max(1, args.repeat))]
            r = min(runs, key=lambda v: float(v["solve_s"]))
            print(f"   {name}: {r}")
            lines.append(
                f"| {pb.label} | {name} | {r['build_s']:.2f} | {r['solve_s']:.2f} | "
                f"{r['iters']} | {r['rms_px']:.3f} | {r['med_px']:.3f} | {r['rot_max']:.4f} | "
                f"{r['rot_mean']:.4f} | {r['pos_max']:.5f} | {r['pos_mean']:.5f} | "
                f"{r['note']} |")
    lines += ["", "Command: `python " + " ".join(["benchmarks/bench_ba.py", *sys.argv[1:]])
              + "`", ""]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, "\n".join(lines))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

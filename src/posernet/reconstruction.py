"""From photos to absolute camera poses: the front end builds one view graph of all images,
PoserNet refines its edges (optional), motion averaging places the cameras.

Used by ``posernet-reconstruct``; usable directly::

    records = records_for_images("photos/", "585,585,320,240")
    fe = ImageFrontend(records, SelectiveSearch(), make_matcher("auto"))
    rec = reconstruct(fe, model=PoserNet.from_checkpoint(default_checkpoint()),
                      backend=get_backend("eig_se3"))
    write_poses_json("out/poses.json", rec)
    write_colmap_models("out/sparse", rec)
    write_camera_view("out/cameras.html", rec)

The front end hands its stages on as typed data (:mod:`posernet.frontend.results`); the
returned :class:`Reconstruction` holds its :class:`~posernet.frontend.results.FrontendResult`
(images, features, matches, verified pairs, the view graph, counts), so every output is
written from it alone. :func:`solve_view_graph` runs the stages after the front end on such a
result built any other way.

No ground truth is needed. Poses are world-to-camera up to the gauge of motion averaging: each
connected component of the view graph is expressed in the frame of its first camera (identity),
and positions are up to one global scale per component (a similarity). Cameras that could not
be placed (no edge, or a component the backend could not solve) are reported with
``solved: false`` and no pose.

With ``bundle`` options (the default of ``posernet-reconstruct``) the averaged poses of every
stage are the start of a final stage ``<stage>+ba``: the verified keypoint matches are chained
into tracks, triangulated and refined with the cameras by robust bundle adjustment
(:mod:`posernet.sfm`), component by component. Rotation-only pairs (pure rotation, too small a
baseline) keep their rotation in averaging but give no translation direction.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .frontend.assembly import GraphStats
from .frontend.images import ImageRecord
from .frontend.pairs import PairOptions, PairSelection
from .frontend.pipeline import ImageFrontend
from .frontend.results import FrontendResult
from .geometry import invert_se3
from .graph import ViewGraph
from .io import atomic_write_json
from .refinement import RefineResult, refine_graphs
from .sfm import BundleOptions, SfmResult, anchored_cameras, bundle_adjust_reconstruction
from .sfm.selfcheck import CheckOptions, PairEvidence, SelfCheck, check_reconstruction

__all__ = ["GT_UNITS", "NothingPlaced", "Reconstruction", "bundle_stage", "edge_weights",
           "focal_mode", "gauge_fixed", "largest_point_cloud", "main_first_line", "pair_evidence",
           "poses_json", "reconstruct", "refocus_line", "self_check", "solve_view_graph",
           "stage_choice_line",
           "trajectory_errors_table",
           "unplaced_json", "write_camera_view", "write_colmap_models", "write_poses_json"]

#: the length unit of aligned positions and their errors: a photo set's pose files name none
#: (a DTU scan's are millimetres, 7-Scenes' metres)
GT_UNITS = "ground-truth units"


@dataclass
class Reconstruction:
    """Everything a run produced: the front end's result (images, features, verified pairs,
    the view graph of all images, counts), the refine/average result, the bundle adjustment
    and the self-check. Every output is written from it alone."""

    frontend: FrontendResult
    result: RefineResult
    sfm: dict[str, list[SfmResult]] = field(default_factory=dict)  # BA stage -> per component
    #: per stage (images, pair_selection, pairs, graph, averaging, bundle_adjustment): wall
    #: seconds, items, and the process's peak memory (MB) at its end
    stages: dict[str, dict[str, float]] = field(default_factory=dict)
    #: the final stage held against its evidence (:func:`self_check`); cameras that failed
    #: are unsolved in ``result.solved[stage]``. None when the check was not run.
    check: SelfCheck | None = None
    #: in a weakly textured or sparse set whose matcher has a fallback: how many images the
    #: main matcher alone placed (``placed``, ``images``, ``main_first``; ``placed`` is None
    #: when its edges touch too few images, ``linked``, to reach the share, and the fallback
    #: placed more than that: it was then not solved) and whether the fallback then
    #: ``"ran"`` or was ``"not needed"``; when it ran, how many images its pass placed
    #: (``fallback_placed``) and which result was ``kept`` (``"main"``: the fallback placed
    #: no more). None elsewhere.
    main_first: dict[str, Any] | None = None
    #: with one guessed focal length that bundle adjustment moved by more than
    #: ``bundle.refocus``: the guess and the adjusted focal length (``guess_px``,
    #: ``adjusted_px``, ``share``), the cameras each pass placed (``placed``, ``again``) and
    #: which result was ``kept`` (``"again"``, verified with the adjusted one, unless it placed
    #: fewer: ``"first"``). None elsewhere.
    refocus: dict[str, Any] | None = None
    #: with a refiner and the self-check: each stage's cameras that passed
    #: (``{"initial+ba": k, "refined+ba": k}``); the final stage is the one with more
    #: (the refined one on a tie). None elsewhere.
    stage_checks: dict[str, int] | None = None

    @property
    def graph(self) -> ViewGraph:
        """The view graph of all images (node ``i`` is image ``i``)."""
        return self.frontend.graph

    @property
    def stats(self) -> GraphStats:
        return self.frontend.stats

    @property
    def pairs(self) -> PairSelection:
        """Which image pairs were matched."""
        return self.frontend.selection

    @property
    def records(self) -> tuple[ImageRecord, ...]:
        return self.frontend.records

    @property
    def stage(self) -> str:
        """The final stage: ``refined`` when PoserNet ran, else ``initial``; with ``+ba`` when
        bundle adjustment ran. With the self-check, the refined stage must pass at least as
        many cameras as the initial one (:attr:`stage_checks`), else the initial one is final."""
        s = "refined" if "refined" in self.result.edge_pose else "initial"
        s = f"{s}+ba" if f"{s}+ba" in self.result.absolute else s
        checks = self.stage_checks
        if checks is not None and s.startswith("refined"):
            initial = s.replace("refined", "initial")
            if checks.get(s, 0) < checks.get(initial, 0):
                return initial
        return s


def edge_weights(frontend: FrontendResult, graph: ViewGraph | None = None) -> Tensor:
    """``[E, 2]`` (rotation, translation) averaging weights of ``graph``'s edges (default: the
    front end's graph): translation weight 0 on rotation-only pairs (their direction says
    nothing), 1 elsewhere. Node ``i`` of the graph is image ``i`` (the graph of all images)."""
    graph = frontend.graph if graph is None else graph
    w = torch.ones(graph.num_edges, 2, dtype=torch.float64)
    for e, (i, j) in enumerate(graph.edge_index.T.tolist()):
        if frontend.pair(i, j).rotation_only:
            w[e, 1] = 0.0
    return w


def focal_mode(records: Sequence[ImageRecord] | Any, requested: str = "auto") -> str:
    """The bundle adjustment's focal-length mode: ``requested`` unless it is ``"auto"``, which
    refines the focal length when any image's intrinsics were guessed (EXIF or prior): one
    shared focal length when every image has the same guess, one per camera otherwise.
    ``records``: the images, or anything holding them as ``records`` (a front end, its
    result)."""
    if requested != "auto":
        return requested
    recs = list(getattr(records, "records", records))
    if all(r.intrinsics_source == "given" for r in recs):
        return "none"
    same = all(np.array_equal(r.K, recs[0].K) for r in recs)
    return "shared" if same else "per_camera"


def bundle_stage(frontend: FrontendResult, result: RefineResult, stage: str,
                 options: BundleOptions | None = None,
                 weights: Tensor | None = None) -> list[SfmResult]:
    """Bundle-adjust the averaged poses of ``stage`` (in ``result``, of the front end's graph)
    from the front end's keypoints and verified matches, one connected component at a time,
    and store them as stage ``<stage>+ba`` (unplaced cameras stay unplaced). Cameras that the
    graph's edges with a usable direction (``weights [E, 2]``, translation column; default
    :func:`edge_weights`) do not pin are first re-placed from 3D points; those whose position
    nothing determines are not placed in ``<stage>+ba``. Returns one run per component."""
    graph = frontend.graph
    weights = edge_weights(frontend) if weights is None else weights
    options = options or BundleOptions(refine_focal="auto")
    poses = result.absolute[stage][0].double()
    solved = result.solved[stage][0].bool()
    comp = result.component[stage][0]
    uv = frontend.keypoints()
    matches = frontend.verified_matches()
    K = frontend.intrinsics()
    dist = frontend.distortion()
    options = dataclasses.replace(options, refine_focal=focal_mode(frontend.records,
                                                                   options.refine_focal))
    # Which cameras the averaging pinned: the graph's edges with a usable direction.
    edges = graph.edge_index.T.numpy().astype(np.int64)
    prs = [frontend.pair(i, j) for i, j in edges.tolist()]
    strength = np.asarray([p.num_inliers for p in prs], np.float64)
    rotation_only = [tuple(e) for e, p in zip(edges.tolist(), prs, strict=True)
                     if p.rotation_only]
    out = poses.clone()
    solved_ba = solved.clone()
    runs = []
    for c in torch.unique(comp[solved]).tolist():
        members = solved & (comp == c)
        if int(members.sum()) < 2:
            continue
        anchored = anchored_cameras(edges, weights[:, 1].numpy(), members.numpy(), strength)
        sfm = bundle_adjust_reconstruction(uv, matches, K, dist, poses.numpy(),
                                           members.numpy(), options, anchored=anchored,
                                           seed=frontend.seed, rotation_only=rotation_only)
        idx = torch.from_numpy(np.flatnonzero(members.numpy()))
        out[idx] = torch.from_numpy(sfm.w2c[idx.numpy()]).to(out.dtype)
        solved_ba[torch.from_numpy(np.flatnonzero(sfm.undetermined))] = False
        runs.append(sfm)
    key = f"{stage}+ba"
    result.absolute[key] = [out.to(result.absolute[stage][0].dtype)]
    result.solved[key] = [solved_ba]
    result.component[key] = [comp.clone()]
    return runs


def pair_evidence(frontend: FrontendResult, graph: ViewGraph | None = None,
                  K: np.ndarray | None = None) -> PairEvidence:
    """The verified two-view geometry of ``graph``'s edges (default: the front end's graph;
    their initial relative poses, rotation-only flags and inlier counts) as the self-check's
    evidence. ``K (N, 3, 3)``: the intrinsics to normalise the inliers with (the front end's
    when None); pass the bundle adjustment's when it refined the focal length, else right
    poses miss the lines."""
    from .geometry import pose_vec_to_matrix
    from .sfm import undistort_keypoints

    graph = frontend.graph if graph is None else graph
    T = pose_vec_to_matrix(graph.edge_pose.double()).numpy()
    edges = graph.edge_index.T.numpy().astype(np.int64)
    prs = [frontend.pair(i, j) for i, j in edges.tolist()]
    if K is None:
        K = frontend.intrinsics()
    und = undistort_keypoints(frontend.keypoints(), K, frontend.distortion())
    norm = [(u - K[i, :2, 2]) / np.diag(K[i])[:2] for i, u in enumerate(und)]
    xa, xb, mp = [], [], []
    for e, ((i, j), p) in enumerate(zip(edges.tolist(), prs, strict=True)):
        if p.inliers is None or not len(p.inliers):
            continue
        ki, kj = (p.inliers[:, 0], p.inliers[:, 1]) if p.a == i else (p.inliers[:, 1],
                                                                      p.inliers[:, 0])
        xa.append(norm[i][ki])
        xb.append(norm[j][kj])
        mp.append(np.full(len(ki), e))
    focal = 0.5 * (K[edges[:, 1], 0, 0] + K[edges[:, 1], 1, 1])

    def cat(x: list[np.ndarray], k: int) -> np.ndarray:
        return np.concatenate(x) if x else np.zeros((0, k))

    return PairEvidence(pairs=edges, R=T[:, :3, :3], t=T[:, :3, 3],
                        rotation_only=np.array([p.rotation_only for p in prs], bool),
                        weight=np.array([0 if p.inliers is None else len(p.inliers)
                                         for p in prs], np.float64),
                        match_pair=cat(mp, 0).reshape(-1).astype(np.int64),
                        x_a=cat(xa, 2), x_b=cat(xb, 2), focal=focal,
                        planar=np.array([bool((p.info or {}).get("planar", False))
                                         for p in prs], bool))


def final_intrinsics(rec: Reconstruction) -> list[np.ndarray]:
    """Each image's ``K (3, 3)`` as used last: the bundle adjustment's (focal length
    refined) where it ran on the final stage, the front end's elsewhere."""
    K = [r.K.astype(np.float64) for r in rec.frontend.records]
    for run in rec.sfm.get(rec.stage, []):
        for i in np.flatnonzero(run.refined):
            K[i] = run.K[i]
    return K


def self_check(rec: Reconstruction, options: CheckOptions | None = None,
               stage: str | None = None) -> SelfCheck:
    """Hold ``stage`` (default: the final stage) of ``rec`` against its verified pairs and
    (after bundle adjustment) its 3D points, one connected component at a time
    (:func:`posernet.sfm.selfcheck.check_reconstruction`). The cameras that fail become
    unsolved in ``rec.result.solved[stage]``, and a block of cameras that nothing ties to the
    rest of its component becomes a component of its own in ``rec.result.component[stage]``;
    the outcome of the final stage is stored in ``rec.check``."""
    res = rec.result
    final = stage is None or stage == rec.stage
    stage = rec.stage if stage is None else stage
    poses = res.absolute[stage][0].double().numpy()
    solved = res.solved[stage][0].bool()
    comp = res.component[stage][0]
    N = poses.shape[0]
    evidence = pair_evidence(rec.frontend, K=np.stack(final_intrinsics(rec)))
    passed = np.zeros(N, bool)
    reason = [""] * N
    rot = np.full(evidence.pairs.shape[0], np.nan)
    dirs, inl = rot.copy(), rot.copy()
    share, tri = np.full(N, np.nan), np.full(N, np.nan)
    pts = np.zeros(N, np.int64)
    runs = rec.sfm.get(stage, [])
    part = np.full(N, -1, np.int64)
    comp_out = comp.clone()
    next_comp = int(comp.max()) + 1 if comp.numel() else 0
    for c in torch.unique(comp[solved]).tolist():
        members = (solved & (comp == c)).numpy()
        run = next((r for r in runs if r.placed[members].any()), None)
        obs = None
        if run is not None and run.obs_image.size:
            keep = members[run.obs_image]
            obs = (run.points, run.obs_image[keep], run.obs_point[keep])
        out = check_reconstruction(poses, members, evidence, *(obs or (None, None, None)),
                                   options=options)
        passed |= out.passed
        part[members & out.passed] = 0
        # a block of tied pairs that nothing ties to the rest is a component of its own
        for k in np.unique(out.part[members & (out.part > 0)]).tolist():
            block = members & (out.part == k)
            part[block] = int(part.max(initial=0)) + 1
            comp_out[torch.from_numpy(block)] = next_comp
            next_comp += 1
        for i in np.flatnonzero(members):
            reason[i] = out.reason[i]
            share[i], tri[i], pts[i] = out.agreeing_share[i], out.triangulation_deg[i], \
                out.points[i]
        inside = members[evidence.pairs].all(1)
        rot[inside], dirs[inside] = out.rotation_error_deg[inside], \
            out.direction_error_deg[inside]
        inl[inside] = out.inlier_share[inside]
    check = SelfCheck(placed=solved.numpy().copy(), passed=passed, reason=reason,
                      rotation_error_deg=rot, direction_error_deg=dirs, agreeing_share=share,
                      points=pts, triangulation_deg=tri, inlier_share=inl,
                      options=options or CheckOptions(), part=part)
    res.solved[stage][0] = torch.from_numpy(passed).to(res.solved[stage][0].dtype)
    res.component[stage][0] = comp_out
    if final:
        rec.check = check
    return check


def reconstruct(
    frontend: ImageFrontend,
    model: torch.nn.Module | None,
    backend: Any,
    device: str | torch.device = "cpu",
    name: str = "images",
    estimate: str = "kp",
    progress: bool = True,
    guard: bool = False,
    bundle_adjust: bool = True,
    bundle: BundleOptions | None = None,
    pairs: PairOptions | None = None,
    check: CheckOptions | bool | None = True,
    release_descriptors: bool = False,
) -> Reconstruction:
    """Evaluate the image pairs that ``pairs`` selects (default: every pair; see
    :func:`posernet.frontend.pairs.select_pairs`), assemble the graph, refine its ``estimate``
    (``kp`` or ``bb``) initial poses with ``model`` (``None``: no refinement), average them
    with ``backend`` and, with ``bundle_adjust`` (``bundle``: its options, defaults when
    ``None``), bundle-adjust each stage's averaged poses (stage ``<stage>+ba``; needs a
    backend). ``refine_focal="auto"`` refines the focal length of guessed intrinsics
    (:func:`focal_mode`).
    ``guard``: keep the input pose where the model's confidence says refinement would not help
    (:func:`posernet.refinement.refine_graphs`; needs a confidence head). With a confidence head
    the averaging starts from the model's per-edge confidence.
    ``check``: hold the final stage against its evidence (:func:`self_check`; options, or
    ``True`` for the defaults, ``False`` to skip): cameras that fail are reported unsolved.
    ``release_descriptors``: free the front end's descriptors once the last pair stage is
    done (:meth:`ImageFrontend.release_descriptors`; less peak memory in averaging and bundle
    adjustment; the front end cannot match new pairs afterwards).

    The front end's stages hand on typed results (:meth:`ImageFrontend.extract`,
    :meth:`~ImageFrontend.select_pairs`, :meth:`~ImageFrontend.match`,
    :meth:`~ImageFrontend.view_graph`); the rest runs on the assembled
    :class:`~posernet.frontend.results.FrontendResult` alone (:func:`solve_view_graph`).
    Raises :class:`NothingPlaced` when no pair became an edge.

    Guessed intrinsics, one focal length shared by every image: when bundle adjustment moved
    it by more than ``bundle.refocus`` of the guess, the pairs were verified with a wrong
    one (their relative poses bent by it), so everything from the pairs on runs again with the
    adjusted focal length (:meth:`ImageFrontend.with_intrinsics`, still refined); that
    result is kept unless it places fewer cameras (:attr:`Reconstruction.refocus` says
    which)."""
    args = (model, backend, device, name, estimate, progress, guard, bundle_adjust, bundle,
            pairs, check, release_descriptors)
    rec = _reconstruct_once(frontend, *args)
    share = (bundle or BundleOptions()).refocus
    focal = adjusted_focal(rec) if bundle_adjust and share > 0 else None
    guess = float(frontend.records[0].K[0, 0])
    if focal is None or abs(focal / guess - 1.0) <= share:
        return rec
    # one pass more: a third, from the second pass's focal length, placed no camera more
    # right on the far-apart dino views, the office room or the plain ring
    K = np.stack([r.K for r in frontend.records]).astype(np.float64)
    K[:, :2, :2] *= focal / guess  # fx, fy and skew by one factor, as the adjustment does
    record = {"guess_px": guess, "adjusted_px": focal, "share": share, "placed": _placed(rec)}
    try:
        again = _reconstruct_once(frontend.with_intrinsics(K), *args)
    except NothingPlaced:
        rec.refocus = {**record, "again": 0, "kept": "first"}
        return rec
    for k, v in rec.stages.items():  # the kept result's stage times count both passes
        if k in again.stages:
            again.stages[k]["seconds"] += v["seconds"]
            again.stages[k]["peak_mb"] = max(again.stages[k]["peak_mb"], v["peak_mb"])
    if _placed(again) < record["placed"]:
        rec.refocus = {**record, "again": _placed(again), "kept": "first"}
        return rec
    again.refocus = {**record, "again": _placed(again), "kept": "again"}
    return again


def adjusted_focal(rec: Reconstruction) -> float | None:
    """The focal length (px) the bundle adjustment of ``rec``'s final stage gave images that
    share one guessed focal length: that of its component with the most refined cameras (then
    the most observations). None when the intrinsics were given, differ between images, or
    nothing was adjusted."""
    recs = rec.frontend.records
    if any(r.intrinsics_source == "given" for r in recs) or focal_mode(recs) != "shared":
        return None
    runs = [r for r in rec.sfm.get(rec.stage, []) if r.refined.any()]
    if not runs:
        return None
    best = max(runs, key=lambda r: (int(r.refined.sum()), int(r.obs_image.size)))
    return float(best.K[int(np.flatnonzero(best.refined)[0]), 0, 0])


def _reconstruct_once(frontend: ImageFrontend, model: torch.nn.Module | None, backend: Any,
                      device: str | torch.device, name: str, estimate: str, progress: bool,
                      guard: bool, bundle_adjust: bool, bundle: BundleOptions | None,
                      pairs: PairOptions | None, check: CheckOptions | bool | None,
                      release_descriptors: bool) -> Reconstruction:
    """:func:`reconstruct` with the front end's intrinsics as they are."""
    n = len(frontend.records)
    clock = _StageClock()
    frontend.extract(progress=progress)
    clock.done("images", n)
    selection = frontend.select_pairs(pairs)
    clock.done("pair_selection", len(selection.pairs))
    args = (model, backend, device, name, estimate, progress, guard, bundle_adjust, bundle,
            check)
    if not frontend.fallback_pending():
        return _solve(frontend, selection, clock, *args, release=release_descriptors)
    # A weakly textured or sparse set: the main matcher alone first; the fallback's less
    # precise matches only where that leaves images unplaced, and its result only where it
    # places more of them.
    share = float(frontend.matcher.main_first)
    solve_args = (model, backend, device, guard, bundle_adjust, bundle, check)
    frontend.hold_fallback(True)
    try:
        view: FrontendResult | None = _pair_stages(frontend, selection, clock, name, estimate,
                                                  progress)
    except NothingPlaced:
        view = None
    finally:
        frontend.hold_fallback(False)
    # A camera is placed only through its edges: the images they touch bound what the main
    # matcher's result can place, so its solve waits where that bound is below the share.
    linked = _linked_images(view)
    rec, placed = None, 0
    if view is not None and linked >= share * n:
        rec = _solve_view(view, clock, *solve_args)
        placed = _placed(rec)
    main = {"placed": placed if rec is not None or view is None else None, "linked": linked,
            "images": n, "main_first": share,
            "sparse": bool(frontend.summary.fallback.get("sparse", 0))}
    if rec is not None and placed >= share * n:
        rec.main_first = {**main, "fallback": "not needed"}
        return rec
    frontend.forget_pairs()
    second = _solve(frontend, selection, clock, *args, release=release_descriptors)
    again = _placed(second)
    if rec is None and view is not None and linked >= again:
        # the fallback placed no more than the main matcher's edges reach, and at a tie the
        # main matcher's more precise result would stay: solve it after all
        rec = _solve_view(view, clock, *solve_args)
        placed = main["placed"] = _placed(rec)
    # what the fallback's pass matched again and kept (the kept result may be the main one)
    fb = second.frontend.summary.fallback
    ran = {"fallback": "ran", "fallback_placed": again,
           "fallback_tried": int(fb.get("tried", 0)), "fallback_kept": int(fb.get("kept", 0))}
    if rec is not None and placed >= again:
        # the fallback placed no more cameras: the main matcher's more precise result stays;
        # its summary says so instead of counting no pair matched again
        rec.frontend.summary.fallback["main_kept"] = 1
        rec.main_first = {**main, **ran, "kept": "main"}
        return rec
    second.main_first = {**main, **ran, "kept": "fallback"}
    return second


def _placed(rec: Reconstruction) -> int:
    """Cameras the final stage of ``rec`` placed."""
    return int(rec.result.solved[rec.stage][0].sum()) if rec.result.absolute else 0


def _linked_images(view: FrontendResult | None) -> int:
    """Images with at least one edge in ``view``'s graph (0 without a view)."""
    if view is None or view.graph.num_edges == 0:
        return 0
    return int(torch.unique(view.graph.edge_index).numel())


def refocus_line(record: dict[str, Any]) -> str:
    """One line on :attr:`Reconstruction.refocus`."""
    head = (f"focal length: guessed {record['guess_px']:.0f} px, adjusted to "
            f"{record['adjusted_px']:.0f} px (more than {record['share']:.0%} off), so the "
            f"pairs were verified again with it")
    if record["kept"] == "again":
        return f"{head}: {record['again']} cameras placed (first pass {record['placed']})"
    return (f"{head}, which placed fewer cameras ({record['again']} against "
            f"{record['placed']}): the first pass is kept")


def stage_choice_line(rec: Reconstruction) -> str | None:
    """One line on :attr:`Reconstruction.stage_checks` (None without a choice)."""
    if rec.stage_checks is None:
        return None
    counts = ", ".join(f"{s} {k}" for s, k in rec.stage_checks.items())
    kept = "the refined poses" if rec.stage.startswith("refined") else \
        "the unrefined poses (the refiner did not pay its way here)"
    return f"cameras passing the self-check: {counts}; kept {kept}"


def main_first_line(record: dict[str, Any]) -> str:
    """One line on :attr:`Reconstruction.main_first`."""
    kind = "sparse set" if record.get("sparse") else "weakly textured set"
    if record["placed"] is None:  # not solved: its edges reach too few images
        head = (f"{kind}: the main matcher's pairs alone link {record['linked']} of "
                f"{record['images']} images")
    else:
        head = (f"{kind}: the main matcher alone placed {record['placed']} of "
                f"{record['images']} images")
    if record["fallback"] == "ran":
        kept = ("its result is kept" if record["kept"] == "fallback" else
                "the main matcher's result is kept")
        return (f"{head} (< {record['main_first']:.0%}), so the pairs were matched again "
                f"with the fallback ({record['fallback_tried']} of them, "
                f"{record['fallback_kept']} kept), which placed {record['fallback_placed']}: "
                f"{kept}")
    return f"{head} (>= {record['main_first']:.0%}): the fallback was not needed"


def _solve(frontend: ImageFrontend, selection: PairSelection, clock: _StageClock,
           model: torch.nn.Module | None, backend: Any, device: str | torch.device,
           name: str, estimate: str, progress: bool, guard: bool, bundle_adjust: bool,
           bundle: BundleOptions | None, check: CheckOptions | bool | None,
           release: bool = False) -> Reconstruction:
    """:func:`reconstruct` from the selected pairs on: the pair stage (matching, verification,
    screening: crowded inliers, rotations breaking triangles), the graph stage, then
    :func:`solve_view_graph`. ``release``: the front end's descriptors go after the graph
    stage."""
    view = _pair_stages(frontend, selection, clock, name, estimate, progress, release)
    return _solve_view(view, clock, model, backend, device, guard, bundle_adjust, bundle,
                       check)


def _pair_stages(frontend: ImageFrontend, selection: PairSelection, clock: _StageClock,
                 name: str, estimate: str, progress: bool, release: bool = False
                 ) -> FrontendResult:
    """The pair and graph stages of :func:`_solve`: the assembled view graph with its
    ``estimate`` initial poses; NothingPlaced when no pair became an edge."""
    matches = frontend.match(selection.pairs, progress=progress)
    clock.done("pairs", len(selection.pairs))
    view = frontend.view_graph(selection, matches, meta={"name": name, "size": "all"})
    if release:
        frontend.release_descriptors()
    view = dataclasses.replace(view, graph=view.graph.with_estimate(estimate))
    clock.done("graph", view.graph.num_edges)
    if view.graph.num_edges == 0:
        raise NothingPlaced(
            "no image pair passed matching and two-view verification, so no camera can be "
            "placed (" + "; ".join(line for line in view.summary.lines()
                                   if line.startswith(("pairs:", "verification:"))) + ")",
            view, clock.stages)
    return view


def solve_view_graph(frontend: FrontendResult, model: torch.nn.Module | None, backend: Any,
                     device: str | torch.device = "cpu", guard: bool = False,
                     bundle_adjust: bool = True, bundle: BundleOptions | None = None,
                     check: CheckOptions | bool | None = True) -> Reconstruction:
    """The stages after the front end on its result alone (built by an
    :class:`ImageFrontend` or by hand): refine the graph's edges with ``model`` (``None``:
    no refinement), average them with ``backend``, bundle-adjust (:func:`bundle_stage`) and
    check (:func:`self_check`); arguments as in :func:`reconstruct`. The graph needs an
    edge."""
    if frontend.graph.num_edges == 0:
        raise ValueError("the view graph has no edge: no camera can be placed")
    return _solve_view(frontend, _StageClock(), model, backend, device, guard, bundle_adjust,
                       bundle, check)


def _solve_view(view: FrontendResult, clock: _StageClock, model: torch.nn.Module | None,
                backend: Any, device: str | torch.device, guard: bool, bundle_adjust: bool,
                bundle: BundleOptions | None, check: CheckOptions | bool | None
                ) -> Reconstruction:
    """Refine, average, bundle-adjust and check ``view``'s graph (stage times into
    ``clock``)."""
    n = len(view.records)
    graph = view.graph
    weights = edge_weights(view)
    confidence = (model is not None and bool(getattr(model, "adaptive", False))
                  and bool(getattr(model, "confidence", False)))
    result = refine_graphs(model, [graph], backend=backend, batch_size=1, device=device,
                           progress=False, guard=guard, weighted=confidence,
                           edge_weight=[weights])
    clock.done("averaging", graph.num_edges)
    rec = Reconstruction(view, result, stages=clock.stages)
    if bundle_adjust and backend is not None:
        for s in list(result.absolute):
            rec.sfm[f"{s}+ba"] = bundle_stage(view, result, s, bundle, weights)
        clock.done("bundle_adjustment", n)
    if check is not False and result.absolute:
        opts = check if isinstance(check, CheckOptions) else None
        final = rec.stage
        if final.startswith("refined"):
            # The refiner must pay its way on this run: where its stage leaves fewer cameras
            # that agree with the evidence than the unrefined one, the unrefined one is final.
            initial = final.replace("refined", "initial")
            checks = {s: self_check(rec, opts, s) for s in (initial, final)}
            rec.stage_checks = {s: int(c.passed.sum()) for s, c in checks.items()}
            rec.check = checks[rec.stage]
        else:
            self_check(rec, opts)
        clock.done("self_check", n)
    return rec


class _StageClock:
    """Wall time, item count and peak memory so far at the end of each stage."""

    def __init__(self) -> None:
        self.stages: dict[str, dict[str, float]] = {}
        self.t = time.perf_counter()

    def done(self, name: str, items: int) -> None:
        now = time.perf_counter()
        took = now - self.t + self.stages.get(name, {}).get("seconds", 0.0)  # stage again
        self.stages[name] = {"seconds": round(took, 3), "items": int(items),
                             "peak_mb": _peak_mb()}
        release_free_memory()
        self.t = time.perf_counter()


def release_free_memory() -> None:
    """Hand the heap memory freed so far back to the operating system (glibc's
    ``malloc_trim``; nothing elsewhere).

    The image stage allocates in worker threads, each with its own malloc arena; what a stage
    frees there stays mapped (and counted in the process's resident memory) while the next
    stages allocate afresh in the main thread's arena. Trimmed between stages, the 256-frame
    sequence's peak went from about 935 to 830 MB."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # another C library (musl): nothing to trim
        pass


def _peak_mb() -> float:
    """Peak resident memory of this process so far (MB; NaN where the OS does not say)."""
    try:
        import resource
    except ImportError:  # Windows
        return float("nan")
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(rss / (1024 * 1024 if sys.platform == "darwin" else 1024), 1)


class NothingPlaced(ValueError):
    """No image pair became an edge, so no camera can be placed. Carries what the front end
    found (``frontend``: its result, with its summary, every evaluated pair and its matches;
    ``pairs``: the selection; ``stages``: timings) so that the caller can still report it
    (:func:`unplaced_json`)."""

    def __init__(self, message: str, frontend: FrontendResult,
                 stages: dict[str, dict[str, float]]) -> None:
        super().__init__(message)
        self.frontend, self.stages = frontend, stages

    @property
    def pairs(self) -> PairSelection:
        return self.frontend.selection


def unplaced_json(err: NothingPlaced, info: dict[str, Any] | None = None) -> dict[str, Any]:
    """The ``poses.json`` record of a run that placed no camera: every camera unsolved with
    the reason, every evaluated pair in ``rejected_pairs`` (same format as :func:`poses_json`).
    """
    fe = err.frontend
    reason = "no image pair passed matching and two-view verification"
    cams = {r.key: {"solved": False, "component": None, "camera_to_world": None,
                    "world_to_camera": None, "q_wxyz": None, "t": None, "edges": 0,
                    "boxes": len(fe.images[i].boxes) if fe.summary.boxes else 0,
                    "size": list(r.size) if r.size else None,
                    "K": [[round(float(v), 6) for v in row] for row in r.K],
                    "dist": None if r.dist is None else [float(v) for v in r.dist],
                    "intrinsics_source": r.intrinsics_source, "note": reason}
            for i, r in enumerate(fe.records)}
    return {"format": "posernet-poses", "version": 1, **(info or {}), "stage": None,
            "positions": None, "backend": None, "frontend": fe.summary.to_dict(),
            "pair_selection": err.pairs.as_dict(), "stages": err.stages,
            "bundle_adjustment": {}, "cameras": cams, "edges": [],
            "rejected_pairs": fe.rejected_pairs()}


def gauge_fixed(poses: Tensor, solved: Tensor, component: Tensor) -> Tensor:
    """World-to-camera ``poses (N, 4, 4)`` with each component's first solved camera at the
    identity (``w2c_i <- w2c_i inv(w2c_ref)``); unsolved cameras are left as they are."""
    out = poses.clone().double()
    for c in torch.unique(component[solved]).tolist():
        members = torch.nonzero(solved & (component == c)).flatten()
        ref_inv = invert_se3(out[members[0]])
        out[members] = out[members] @ ref_inv
    return out


def _num(v: Any) -> Any:
    """JSON-safe scalar (numpy numbers to Python, non-finite floats to None)."""
    if isinstance(v, dict):
        return {str(k): _num(x) for k, x in v.items()}
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float):
        return round(v, 6) if np.isfinite(v) else None
    return v


def sfm_record(r: SfmResult, keys: list[str]) -> dict[str, Any]:
    """JSON-ready summary of one component's bundle adjustment."""
    st = r.stats
    return {
        "cameras_refined": [keys[i] for i in np.flatnonzero(r.refined)],
        "cameras_weak": [keys[i] for i in np.flatnonzero(r.weak)],
        "cameras_position_undetermined": [keys[i] for i in np.flatnonzero(r.undetermined)],
        "tracks": int(r.tracks.num_tracks),
        "track_observations": int(r.tracks.track.size), "points": int(r.points.shape[0]),
        "observations": int(r.obs_image.size),
        "reprojection_px": {f"{k}_{w}": _num(st.get(f"{k}_error_{w}"))
                            for k in ("median", "mean") for w in ("before", "after")},
        "runs": [{"converged": bool(b.converged), "accepted": bool(b.accepted),
                  "evaluations": int(b.iterations), "message": b.message} for b in r.bundles],
        "seconds": _num(st.get("seconds", {})),
        "message": r.message,
        # cameras whose averaged position no edge pinned, re-placed by PnP on 3D points
        "resection": {keys[i]: {"points": n, "pnp_inliers": k, "resected": ok}
                      for i, n, k, ok in st.get("resection", {}).get("cameras", [])},
        # the start kept (averaged poses or incremental registration) and what each kept
        "start": _start_record(st.get("start"), keys),
    }


def _start_record(start: dict[str, Any] | None, keys: list[str]) -> dict[str, Any] | None:
    if not start:
        return None
    out = {k: _num(v) for k, v in start.items() if k not in ("observations", "cameras")}
    if start.get("observations"):
        out["observations_kept"] = dict(start["observations"])
        out["cameras_kept"] = dict(start.get("cameras") or {})
    return out


def poses_json(rec: Reconstruction, info: dict[str, Any] | None = None) -> dict[str, Any]:
    """JSON-ready record (format ``posernet-poses``, version 1), see docs/formats.md."""
    from .geometry import pose_vec_to_matrix
    from .records import camera_record, pose_records

    g, res, stage = rec.graph, rec.result, rec.stage
    cams: dict[str, Any] = {}
    if res.absolute:
        poses = res.absolute[stage][0]
        solved, comp = res.solved[stage][0].bool(), res.component[stage][0]
        fixed = gauge_fixed(poses, solved, comp)
    K_out = final_intrinsics(rec)
    degree = torch.bincount(g.edge_index.flatten(), minlength=g.num_nodes)
    n_boxes = torch.bincount(g.det_node, minlength=g.num_nodes)
    for i, r in enumerate(rec.frontend.records):
        placed = res.absolute and bool(solved[i])
        cam: dict[str, Any] = {**camera_record(fixed[i] if placed else None,
                                               comp[i] if placed else None, digits=9),
                               "edges": int(degree[i]), "boxes": int(n_boxes[i]),
                               "size": list(r.size) if r.size else None,
                               "K": [[round(float(v), 6) for v in row] for row in K_out[i]],
                               "dist": None if r.dist is None else [float(v) for v in r.dist],
                               "intrinsics_source": r.intrinsics_source}
        if any(bool(run.undetermined[i]) for run in rec.sfm.get(stage, [])):
            cam["note"] = ("position not determined: a single edge's direction and too few "
                           "3D points shared with the other cameras")
        elif rec.check is not None and rec.check.reason[i]:
            cam["note"] = "failed the self-check: " + rec.check.reason[i]
        elif rec.check is not None and placed and bool(rec.check.split[i]):
            cam["note"] = ("a component of its own: nothing ties its distance to the other "
                           "cameras of its image pairs (split off by the self-check)")
        cams[r.key] = cam
    keys = [r.key for r in rec.frontend.records]
    edges = []
    rows_per_edge = torch.bincount(g.pair_edge, minlength=g.num_edges).tolist()
    edge_records = {s: pose_records(pose_vec_to_matrix(p[0].double()), digits=9)
                    for s, p in res.edge_pose.items()}
    for e, (i, j) in enumerate(g.edge_index.T.tolist()):
        rows = rows_per_edge[e]
        pr = rec.frontend.pair(i, j)
        item: dict[str, Any] = {"source": keys[i], "target": keys[j], "matched_boxes": rows,
                                "rotation_only": bool(pr.rotation_only),
                                "track_matches": 0 if pr.inliers is None else len(pr.inliers),
                                "verification": dict(pr.info)}
        for s, recs in edge_records.items():
            item[s] = recs[e]
        edges.append(item)
    bundle = {s: [sfm_record(r, keys) for r in runs] for s, runs in rec.sfm.items()}
    return {"format": "posernet-poses", "version": 1, **(info or {}), "stage": stage,
            "positions": "up to one similarity (rotation, translation, global scale) per "
                         "component: no metric scale is known from images alone",
            "backend": res.backend, "frontend": rec.frontend.summary.to_dict(),
            "pair_selection": None if rec.pairs is None else rec.pairs.as_dict(),
            "stages": rec.stages,
            "bundle_adjustment": bundle,
            "self_check": None if rec.check is None else rec.check.to_dict(keys),
            "main_first": rec.main_first, "refocus": rec.refocus,
            "stage_checks": rec.stage_checks,
            "cameras": cams, "edges": edges,
            "rejected_pairs": rec.frontend.rejected_pairs()}


def _component_models(rec: Reconstruction) -> Iterator[tuple[Any, np.ndarray, np.ndarray]]:
    """Per bundle-adjusted component of two or more refined cameras, largest first:
    ``(run, cameras (C,), points (P, 3))`` with the points in the frame of ``poses.json`` (the
    component's world moves with its first camera)."""
    res = rec.result
    poses = res.absolute[rec.stage][0].double()
    solved = res.solved[rec.stage][0].bool().numpy()
    comp = res.component[rec.stage][0].numpy()
    models = []
    for r in rec.sfm.get(rec.stage, []):
        # one adjustment may hold several components: the self-check splits off blocks that
        # nothing ties to the rest; each gets its own model, with the points its cameras see
        for c in np.unique(comp[r.placed & solved]).tolist():
            mine = r.placed & solved & (comp == c)
            cams = np.flatnonzero(r.refined & mine)
            if cams.size < 2 or r.points.shape[0] == 0:
                continue
            models.append((r if mine.sum() == (r.placed & solved).sum() else
                           _run_subset(r, mine), cams, np.flatnonzero(mine)[0]))
    for r, cams, gauge in sorted(models, key=lambda m: -m[1].size):
        if r.points.shape[0] == 0:
            continue
        M = poses[gauge].numpy()  # the gauge camera: its component's first
        yield r, cams, r.points @ M[:3, :3].T + M[:3, 3]


def _run_subset(r: Any, cams: np.ndarray) -> Any:
    """Bundle adjustment result ``r`` cut to the cameras ``cams (N,)``: their observations, and
    the points two of them see (renumbered)."""
    keep = cams[r.obs_image]
    seen = np.bincount(r.obs_point[keep], minlength=r.points.shape[0])
    point_ok = seen >= 2
    keep &= point_ok[r.obs_point]
    new_id = np.cumsum(point_ok) - 1
    return dataclasses.replace(r, points=r.points[point_ok],
                               point_track=r.point_track[point_ok],
                               obs_image=r.obs_image[keep], obs_keypoint=r.obs_keypoint[keep],
                               obs_point=new_id[r.obs_point[keep]])


def _keypoints(rec: Reconstruction) -> list[np.ndarray]:
    return rec.frontend.keypoints()


def write_colmap_models(folder: str | os.PathLike[str], rec: Reconstruction,
                        workers: int = 1) -> list[Path]:
    """The final bundle-adjusted stage as COLMAP models, one per component of two or more
    refined cameras, largest first: ``folder/0``, ``folder/1``, ... (:mod:`posernet.export`), in
    the frame of ``poses.json``. Text models, or binary ones (every model of the run) when an
    exported image's name holds whitespace, which COLMAP's text format cannot carry. Returns
    the model folders (none without bundle adjustment). ``workers``: threads reading the
    images for the points' colours."""
    from .export import colmap_text_name_ok, write_colmap_model
    from .sfm import reprojection_errors, undistort_keypoints

    models = list(_component_models(rec))
    if not models:
        return []
    recs = rec.frontend.records
    names = [x.key for x in recs]
    binary = not all(colmap_text_name_ok(names[i]) for _, cams, _ in models for i in cams)
    K = np.stack([r.K for r in recs]).astype(np.float64)
    dist = [r.dist for r in recs]
    uv = _keypoints(rec)
    und = undistort_keypoints(uv, K, dist)
    res = rec.result
    fixed = gauge_fixed(res.absolute[rec.stage][0].double(), res.solved[rec.stage][0].bool(),
                        res.component[rec.stage][0])
    out: list[Path] = []
    offs = np.concatenate(([0], np.cumsum([len(u) for u in und])))
    flat = np.concatenate([u.reshape(-1, 2) for u in und])
    for r, cams, pts in models:
        xy = flat[offs[r.obs_image] + r.obs_keypoint]
        err = reprojection_errors(r.points, xy, r.obs_point, r.obs_image, r.K, r.w2c)
        folder_k = Path(folder) / str(len(out))
        write_colmap_model(folder_k, names, [x.path for x in recs], [x.size for x in recs],
                           r.K, dist, fixed.numpy(), cams, uv, pts, r.obs_image,
                           r.obs_keypoint, r.obs_point, err, binary=binary,
                           workers=workers, keypoint_colours=rec.frontend.keypoint_colours())
        out.append(folder_k)
    return out


def largest_point_cloud(rec: Reconstruction, workers: int = 1
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The largest bundle-adjusted component: its cameras ``(C,)`` (image indices), points
    ``(P, 3)`` in the frame of ``poses.json`` and their image colours ``(P, 3)`` RGB; None
    without bundle adjustment. ``workers``: threads reading the images."""
    from .export import point_colours

    r, cams, pts = next(_component_models(rec), (None, None, None))
    if r is None:
        return None
    colours = point_colours([x.path for x in rec.frontend.records], _keypoints(rec),
                            r.obs_image, r.obs_keypoint, r.obs_point, pts.shape[0],
                            workers, rec.frontend.keypoint_colours())
    return cams, pts, colours


def write_poses_json(path: str | os.PathLike[str], rec: Reconstruction,
                     info: dict[str, Any] | None = None) -> Path:
    """Write :func:`poses_json` atomically."""
    return atomic_write_json(path, poses_json(rec, info), indent=1)


def write_camera_view(path: str | os.PathLike[str], rec: Reconstruction,
                      record: dict[str, Any] | None = None, workers: int = 1) -> Path | None:
    """``cameras.html``: the largest component's cameras and points, interactive and offline
    (:mod:`posernet.viewer`); with ground truth for each of its cameras (3 or more), moved onto
    it by the similarity of the camera centres (:func:`posernet.ground_truth.align_cameras`)
    and shown with it. ``record``: :func:`poses_json` of ``rec`` (made when None);
    ``workers``: threads reading the images for the points' colours. None when no camera is
    placed."""
    from .export import largest_component
    from .ground_truth import align_cameras
    from .viewer import write_html_view

    record = poses_json(rec) if record is None else record
    names = largest_component(record["cameras"])
    if not names:
        return None
    cams = {n: dict(record["cameras"][n]) for n in names}
    cloud = largest_point_cloud(rec, workers)
    points = colours = None
    keys = [r.key for r in rec.records]
    if cloud is not None and {keys[i] for i in cloud[0]} <= set(names):
        points, colours = cloud[1], cloud[2]
    gt = {r.key: r.c2w for r in rec.records if r.c2w is not None and r.key in cams}
    moved = align_cameras({n: cams[n]["camera_to_world"] for n in names}, gt, points)
    units = "scale-free"
    if moved is not None:
        for n in names:
            cams[n]["camera_to_world"] = moved.cameras[n]
        points = moved.points
        units = f"{GT_UNITS} (aligned by a similarity)"
    title = (f"{len(names)} of {len(record['cameras'])} cameras (largest component)"
             + (f", {len(points)} points" if points is not None else ""))
    return write_html_view(path, cams, points, colours,
                           ground_truth=gt if moved is not None else None, title=title,
                           units=units)


def trajectory_errors_table(rec: Reconstruction,
                            record: dict[str, Any] | None = None) -> str | None:
    """The evo-style APE / RPE table (markdown) of the largest component against the ground
    truth, cameras in name order (:func:`posernet.ground_truth.trajectory_table`), from
    ``record`` (:func:`poses_json` of ``rec``, made when None); None without ground truth for
    each of them or with fewer than 3."""
    from .export import largest_component
    from .ground_truth import trajectory_table

    record = poses_json(rec) if record is None else record
    names = largest_component(record["cameras"])
    gt = {r.key: r.c2w for r in rec.records}
    if any(gt.get(n) is None for n in names):
        return None
    return trajectory_table({n: record["cameras"][n]["camera_to_world"] for n in names}, gt)

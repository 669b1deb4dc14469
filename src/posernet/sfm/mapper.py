"""Orchestrator: verified matches + motion-averaging poses -> refined poses and 3D points.

Global-SfM style: tracks on the placed images, triangulation at the input poses (loose error
threshold: those poses may be degrees off), robust bundle adjustment, then per round: drop the
observations whose error is still above ``max_reproj_px``, triangulate the tracks that were not
yet in the problem with the refined poses (strict filters), bundle-adjust again.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ..geometry import umeyama_alignment
from .bundle import BundleOptions, BundleResult, bundle_adjust
from .incremental import register_incrementally
from .positioning import global_positioning
from .resection import resect_cameras
from .tracks import Tracks, build_tracks
from .triangulation import reprojection_errors, triangulate_tracks, undistort_keypoints

__all__ = ["SfmResult", "bundle_adjust_reconstruction"]


@dataclass
class SfmResult:
    """Output of :func:`bundle_adjust_reconstruction` for ``N`` images.

    ``w2c (N, 4, 4)`` refined world-to-camera poses (input poses where not refined; positions
    up to one global scale, see ``stats``), ``K (N, 3, 3)`` (refined focal when asked),
    ``points (P, 3)`` kept 3D points and ``point_track (P,)`` their track ids in ``tracks``;
    final observations ``obs_image, obs_keypoint, obs_point (O,)`` (keypoint index into
    ``uv[image]``, point index into ``points``); ``observations_per_image (N,)``; masks
    ``placed`` (input), ``refined`` (pose from the bundle adjustment) and ``weak`` (placed but
    under ``min_points_per_camera`` points: input pose kept, moved by the similarity that
    maps the input frame to the adjusted one); ``bundles`` every BA run; ``stats`` numbers
    for a summary (see :meth:`lines`).
    """

    w2c: np.ndarray
    K: np.ndarray
    points: np.ndarray
    point_track: np.ndarray
    obs_image: np.ndarray
    obs_keypoint: np.ndarray
    obs_point: np.ndarray
    observations_per_image: np.ndarray
    placed: np.ndarray
    refined: np.ndarray
    weak: np.ndarray
    tracks: Tracks
    bundles: list[BundleResult] = field(default_factory=list)
    stats: dict[str, Any] = field(default_factory=dict)
    message: str = ""
    #: weak cameras whose position nothing determined (averaging did not pin it, PnP failed):
    #: callers should not report them as placed
    undetermined: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    def lines(self) -> list[str]:
        """Human-readable summary, one fact per line."""
        s = self.stats
        out = [*self.tracks.lines()]
        if "resection" in s:
            r = s["resection"]
            out.append(f"cameras not pinned by averaging: {r['tried']}; re-placed from 3D points "
                       f"(PnP) {r['resected']}, failed {r['failed']}")
        if "start" in s:
            st = s["start"]
            obs = st.get("observations") or {}
            out.append(f"start: {st['kept']} ({st.get('why', '')})" + (
                "; observations kept: " + ", ".join(f"from the {k} start {v}"
                                                    for k, v in obs.items()) if obs else ""))
        if "triangulation" in s:
            out.append("initial triangulation: " + ", ".join(
                f"{k} {v}" for k, v in s["triangulation"].items()))
        out.append(f"points kept: {self.points.shape[0]} with {self.obs_image.size} "
                   f"observations; cameras refined {int(self.refined.sum())}/"
                   f"{int(self.placed.sum())} placed, weak (input pose kept) "
                   f"{int(self.weak.sum())}")
        if "median_error_before" in s:  # set only when an adjustment was accepted
            out.append(f"reprojection error median/mean: {s['median_error_before']:.3f}/"
                       f"{s['mean_error_before']:.3f} px -> {s['median_error_after']:.3f}/"
                       f"{s['mean_error_after']:.3f} px over {len(self.bundles)} BA run(s)")
        out.append("seconds: " + ", ".join(f"{k} {v:.2f}" for k, v in s["seconds"].items()))
        out.append(self.message)
        return out


def _similarity_np(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama ``dst ~ s R src + t`` for ``(K, 3)`` arrays (the package's implementation)."""
    s, R, t = umeyama_alignment(torch.from_numpy(src), torch.from_numpy(dst))
    return float(s), R.numpy(), t.numpy()


def _move_poses(w2c: np.ndarray, s: float, Q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World-to-camera poses ``(M, 4, 4)`` after the world moves by ``X' = s Q X + t``."""
    out = w2c.copy()
    R, tr = w2c[:, :3, :3], w2c[:, :3, 3]
    c = -np.einsum("mji,mj->mi", R, tr)
    c2 = s * c @ Q.T + t
    R2 = R @ Q.T
    out[:, :3, :3] = R2
    out[:, :3, 3] = -np.einsum("mij,mj->mi", R2, c2)
    return out


def _check_inputs(uv: Sequence[np.ndarray], K: np.ndarray, dist: Sequence[Any] | None,
                  w2c: np.ndarray, placed: np.ndarray) -> int:
    N = len(uv)
    if K.shape != (N, 3, 3):
        raise ValueError(f"K must be (N, 3, 3) with N = len(uv) = {N}, got {K.shape}")
    if w2c.shape != (N, 4, 4):
        raise ValueError(f"w2c must be (N, 4, 4) with N = {N}, got {w2c.shape}")
    if placed.shape != (N,):
        raise ValueError(f"placed must be ({N},), got {placed.shape}")
    if dist is not None and len(dist) != N:
        raise ValueError(f"dist must be None or have one entry per image ({N}), got {len(dist)}")
    for i, u in enumerate(uv):
        a = np.asarray(u)
        if a.size and (a.ndim != 2 or a.shape[1] != 2):
            raise ValueError(f"uv[{i}] must be (K_i, 2) pixels, got {a.shape}")
    return N


def bundle_adjust_reconstruction(uv: Sequence[np.ndarray],
                                 pair_matches: Mapping[tuple[int, int], np.ndarray],
                                 K: np.ndarray, dist: Sequence[np.ndarray | None] | None,
                                 w2c: np.ndarray, placed: np.ndarray,
                                 options: BundleOptions | None = None,
                                 anchored: np.ndarray | None = None,
                                 seed: int = 0,
                                 rotation_only: Iterable[tuple[int, int]] = ()) -> SfmResult:
    """Tracks, triangulation and robust bundle adjustment of the placed images.

    ``uv[i] (K_i, 2)`` keypoint pixels of image i (distorted as detected), ``pair_matches``
    verified ``(M, 2)`` keypoint index pairs per image pair ``(a, b)``, ``K (N, 3, 3)``,
    ``dist``: per image OpenCV distortion coefficients or None, ``w2c (N, 4, 4)`` initial
    poses (motion averaging), ``placed (N,)`` which of them are meaningful. Placed cameras
    with a non-finite pose are treated as not placed. ``anchored (N,)``: the placed cameras
    whose averaged position is trustworthy (see
    :func:`~posernet.sfm.resection.anchored_cameras`; None: all); the others are first
    re-placed by PnP on points triangulated from the anchored ones (``seed``: its RANSAC), and
    those that fail are kept out of the adjustment (weak). ``rotation_only``: image pairs
    whose two-view geometry found no baseline (a revisited spot): their cameras may share a
    centre, which the choice of start does not then take for a collapse. Malformed shapes
    raise ValueError; a failed bundle adjustment keeps the previous (ultimately the input)
    poses.
    """
    opt = options or BundleOptions()
    if opt.start != "averaged":
        return _best_start(uv, pair_matches, K, dist, w2c, placed, opt, anchored, seed,
                           rotation_only)
    t_all = time.perf_counter()
    seconds: dict[str, float] = {}
    K = np.asarray(K, np.float64)
    w2c = np.asarray(w2c, np.float64)
    placed_in = np.asarray(placed, bool).reshape(-1)
    N = _check_inputs(uv, K, dist, w2c, placed_in)
    w2c_in = w2c
    placed = placed_in & np.isfinite(w2c).all((1, 2)) & np.isfinite(K).all((1, 2))
    n_bad = int((placed_in & ~placed).sum())

    t0 = time.perf_counter()
    und = undistort_keypoints(uv, K, dist)
    seconds["undistort"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    sub = {k: m for k, m in pair_matches.items() if placed[int(k[0])] and placed[int(k[1])]}
    tracks = build_tracks(sub, [len(u) for u in und])
    seconds["tracks"] = time.perf_counter() - t0
    T = tracks.num_tracks
    track, image, kp = tracks.track, tracks.image, tracks.keypoint
    offs = np.concatenate(([0], np.cumsum([len(u) for u in und]))).astype(np.int64)
    flat = np.concatenate([u.reshape(-1, 2) for u in und]) if N else np.zeros((0, 2))
    xy = flat[offs[image] + kp] if T else np.zeros((0, 2))

    def result(out_w2c: np.ndarray, out_K: np.ndarray, pts: np.ndarray, in_ba: np.ndarray,
               active: np.ndarray, refined: np.ndarray, weak: np.ndarray,
               bundles: list[BundleResult], stats: dict[str, Any], msg: str) -> SfmResult:
        keep_tr = np.flatnonzero(in_ba)
        remap = np.full(T, -1, np.int64)
        remap[keep_tr] = np.arange(keep_tr.size)
        sel = active & in_ba[track] if T else np.zeros(0, bool)
        seconds["total"] = time.perf_counter() - t_all
        stats["seconds"] = seconds
        stats["invalid_placed_poses"] = n_bad
        return SfmResult(undetermined=weak & guessed,
                         w2c=out_w2c, K=out_K, points=pts[keep_tr], point_track=keep_tr,
                         obs_image=image[sel], obs_keypoint=kp[sel],
                         obs_point=remap[track[sel]],
                         observations_per_image=np.bincount(image[sel], minlength=N),
                         placed=placed, refined=refined, weak=weak, tracks=tracks,
                         bundles=bundles, stats=stats, message=msg)

    no = np.zeros(N, bool)
    stats: dict[str, Any] = {"tracks": T}
    not_pinned = no.copy()
    guessed = no.copy()  # position neither pinned by averaging nor found by PnP
    if anchored is not None and T:
        anchor = pinned = np.asarray(anchored, bool).reshape(-1) & placed
        if (placed & ~anchor).any() and int(anchor.sum()) >= 2:
            # Adjust the pinned cameras first: points triangulated from averaged poses are
            # too rough (tens of px) for PnP. The others follow into the adjusted frame.
            t0 = time.perf_counter()
            core = bundle_adjust_reconstruction(uv, pair_matches, K, dist, w2c, anchor, opt)
            w2c = w2c.copy()
            ok = core.refined
            if ok.any():
                w2c[ok], K = core.w2c[ok], np.where(ok[:, None, None], core.K, K)
                rest = placed & ~anchor
                if int(ok.sum()) >= 3:
                    c_in = -np.einsum("nji,nj->ni", w2c_in[ok, :3, :3], w2c_in[ok, :3, 3])
                    c_out = -np.einsum("nji,nj->ni", w2c[ok, :3, :3], w2c[ok, :3, 3])
                    w2c[rest] = _move_poses(w2c_in[rest], *_similarity_np(c_in, c_out))
                anchor = anchor & ok  # pinned but too weakly seen: PnP may do better
            seconds["core_bundle"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            rs = resect_cameras(xy, track, image, T, K, w2c, anchor, placed,
                                max_reproj_px=opt.max_reproj_px,
                                min_angle_deg=opt.min_angle_deg,
                                min_inliers=max(6, opt.min_points_per_camera),
                                reproj_factor=opt.initial_reproj_factor, seed=seed)
            w2c = rs.w2c
            not_pinned = rs.failed
            # position unknown: never pinned, or pinned but contradicted by the adjusted points
            min_pts = max(6, opt.min_points_per_camera)
            guessed = placed & ~anchor & ~rs.resected & (~pinned | (rs.points >= min_pts))
            stats["resection"] = {"tried": int((placed & ~anchor).sum()),
                                  "resected": int(rs.resected.sum()),
                                  "failed": int(rs.failed.sum()),
                                  "cameras": [(int(i), int(rs.points[i]), int(rs.inliers[i]),
                                               bool(rs.resected[i]))
                                              for i in np.flatnonzero(placed & ~anchor)]}
            seconds["resection"] = time.perf_counter() - t0
    if T == 0:
        return result(w2c.copy(), K.copy(), np.zeros((0, 3)), np.zeros(0, bool),
                      np.zeros(0, bool), no, placed.copy(), [], {},
                      "no tracks between placed images: input poses kept")

    # 1. Triangulate at the input poses; adaptive error threshold.
    t0 = time.perf_counter()
    ok = ~not_pinned[image]  # a camera PnP could not place would spoil its tracks
    tri = triangulate_tracks(xy[ok], track[ok], image[ok], T, K, w2c, max_reproj_px=np.inf,
                             min_angle_deg=opt.min_angle_deg)
    in_ba = tri.valid.copy()
    thr0 = opt.max_reproj_px
    if in_ba.any():
        thr0 = max(thr0, opt.initial_reproj_factor * float(np.median(tri.max_error[in_ba])))
    over = in_ba & (tri.max_error > thr0)
    in_ba &= ~over
    counts = dict(tri.counts)
    counts["reprojection"] += int(over.sum())
    counts["valid"] = int(in_ba.sum())
    seconds["triangulate"] = time.perf_counter() - t0
    pts = tri.points
    active = np.ones(track.size, bool)
    # Weak cameras: too few points to pin their pose; leave them out of the problem.
    n_pts = np.bincount(image[in_ba[track]], minlength=N)
    weak = placed & ((n_pts < opt.min_points_per_camera) | not_pinned)
    active &= ~weak[image]
    in_ba &= np.bincount(track[active], minlength=T) >= 2
    stats.update(triangulation=counts, initial_threshold_px=thr0)

    cur_w2c, cur_K = w2c.copy(), K.copy()
    bundles: list[BundleResult] = []
    for r in range(opt.rounds):
        t0 = time.perf_counter()
        sel = active & in_ba[track]
        ba = bundle_adjust(cur_w2c, np.nan_to_num(pts), cur_K, xy[sel], image[sel], track[sel],
                           opt)
        bundles.append(ba)
        seconds[f"bundle_{r + 1}"] = time.perf_counter() - t0
        if not ba.accepted:
            break
        cur_w2c, cur_K = ba.w2c, ba.K
        pts = np.where(in_ba[:, None], ba.points, pts)
        if r == opt.rounds - 1:
            break
        # Filter: drop observations the adjusted model still misses; a track that keeps
        # fewer than 2 of them leaves the problem.
        t0 = time.perf_counter()
        err = reprojection_errors(np.nan_to_num(pts), xy, track, image, cur_K, cur_w2c)
        active &= ~(in_ba[track] & ~(err <= opt.max_reproj_px))
        in_ba &= np.bincount(track[active], minlength=T) >= 2
        # Tracks not yet in the problem: triangulate with the refined poses, strict filters.
        out_tr = ~in_ba[track] & active & ~weak[image]
        tri2 = triangulate_tracks(xy[out_tr], track[out_tr], image[out_tr], T, cur_K, cur_w2c,
                                  max_reproj_px=opt.max_reproj_px,
                                  min_angle_deg=opt.min_angle_deg)
        new = tri2.valid & ~in_ba
        pts = np.where(new[:, None], tri2.points, pts)
        in_ba |= new
        seconds[f"filter_{r + 1}"] = time.perf_counter() - t0

    accepted = [b for b in bundles if b.accepted]
    stats["bundle_runs"] = len(bundles)
    if not accepted:
        msg = ("bundle adjustment failed: " + bundles[0].message if bundles else
               "nothing to adjust") + "; input poses kept"
        return result(w2c.copy(), K.copy(), pts, in_ba, active, no, placed.copy(), bundles,
                      stats, msg)
    stats["median_error_before"] = accepted[0].median_error_before
    stats["mean_error_before"] = accepted[0].mean_error_before
    stats["median_error_after"] = accepted[-1].median_error_after
    stats["mean_error_after"] = accepted[-1].mean_error_after
    # Cameras left with too few observations after filtering are weak too.
    sel = active & in_ba[track]
    per_img = np.bincount(image[sel], minlength=N)
    weak = placed & (weak | (per_img < opt.min_points_per_camera))
    refined = placed & ~weak
    out = cur_w2c.copy()
    out_K = cur_K.copy()
    out_K[~refined] = K[~refined]
    if weak.any():
        # Keep the weak cameras' input poses, expressed in the adjusted frame (the gauge camera
        # is held, but the free scale may drift slightly).
        c_in = -np.einsum("nji,nj->ni", w2c[refined, :3, :3], w2c[refined, :3, 3])
        c_out = -np.einsum("nji,nj->ni", out[refined, :3, :3], out[refined, :3, 3])
        if refined.sum() >= 3:
            s, Q, t = _similarity_np(c_in, c_out)
        else:
            s, Q, t = 1.0, np.eye(3), np.zeros(3)
        out[weak] = _move_poses(w2c[weak], s, Q, t)
    out[~placed] = w2c[~placed]
    stats["scale_note"] = ("camera positions are up to one global scale (gauge: one camera per "
                           "component fixed, scale free)")
    msg = (f"bundle adjustment: {len(accepted)}/{len(bundles)} run(s) accepted; "
           f"{int(refined.sum())} cameras refined, {int(weak.sum())} weak kept at input pose")
    return result(out, out_K, pts, in_ba, active, refined, weak, bundles, stats, msg)


def _support(r: SfmResult) -> int:
    """Observations the adjustment explains: those kept in cameras it refined (a failed
    adjustment refines none)."""
    return int(r.refined[r.obs_image].sum())


def _observations(uv: Sequence[np.ndarray], pair_matches: Mapping[tuple[int, int], np.ndarray],
                  K: np.ndarray, dist: Sequence[np.ndarray | None] | None, members: np.ndarray
                  ) -> tuple[Tracks, np.ndarray]:
    """Tracks among ``members`` and their undistorted pixels ``(O, 2)``."""
    und = undistort_keypoints(uv, K, dist)
    sub = {k: m for k, m in pair_matches.items() if members[int(k[0])] and members[int(k[1])]}
    tracks = build_tracks(sub, [len(u) for u in und])
    offs = np.concatenate(([0], np.cumsum([len(u) for u in und]))).astype(np.int64)
    flat = np.concatenate([u.reshape(-1, 2) for u in und]) if len(und) else np.zeros((0, 2))
    return tracks, flat[offs[tracks.image] + tracks.keypoint]


def _restart(uv: Sequence[np.ndarray], pair_matches: Mapping[tuple[int, int], np.ndarray],
             K: np.ndarray, dist: Sequence[np.ndarray | None] | None, w2c: np.ndarray,
             start: np.ndarray, started: np.ndarray, members: np.ndarray, opt: BundleOptions,
             seed: int, seconds: float, what: str) -> SfmResult:
    """Bundle adjustment from the poses ``start`` of the ``started`` cameras; the other
    ``members`` are left unplaced (weak, position undetermined, averaged pose kept)."""
    res = bundle_adjust_reconstruction(uv, pair_matches, K, dist, start, started, opt,
                                       seed=seed)
    left = members & ~started
    N = members.size
    res.placed = res.placed | left
    res.weak = res.weak | left
    res.undetermined = (res.undetermined if res.undetermined.size else np.zeros(N, bool)) | left
    res.w2c[left] = w2c[left]
    res.stats["seconds"][what] = seconds
    return res


def baseline_pairs(pair_matches: Mapping[tuple[int, int], np.ndarray],
                   rotation_only: Iterable[tuple[int, int]] = ()) -> np.ndarray:
    """``(E, 2)`` the matched image pairs whose two-view geometry has a baseline: those with
    matches, less the ``rotation_only`` ones (either order). Two cameras of such a pair on one
    spot contradict their own matches; of a rotation-only pair (the same spot revisited, as
    at frames 403 and 417 of a 1024-frame room sequence) they agree with them."""
    skip = {(min(a, b), max(a, b)) for a, b in ((int(a), int(b)) for a, b in rotation_only)}
    keep = [(int(a), int(b)) for (a, b), m in pair_matches.items()
            if len(m) and (min(int(a), int(b)), max(int(a), int(b))) not in skip]
    return np.array(keep, np.int64).reshape(-1, 2)


def _open_pairs(r: SfmResult, pair_matches: Mapping[tuple[int, int], np.ndarray],
                num_keypoints: Sequence[int], opt: BundleOptions) -> int:
    """Verified pairs of two refined cameras with ``opt.pair_explained_matches`` matches or
    more of which less than ``opt.pair_explained_min`` end as one 3D point seen in both: the
    adjustment dropped their matches as outliers. On a turntable ring adjusted from averaged
    poses whose loop did not close, the pairs across the seam kept 21-23 % of 110-300
    matches while every camera was refined and 93 % of the observations explained; the
    correct adjustments of the development sets keep 45 % or more of every such pair."""
    big = [(k, m) for k, m in pair_matches.items()
           if len(m) >= opt.pair_explained_matches
           and r.refined[int(k[0])] and r.refined[int(k[1])]]
    if not big or r.obs_image.size == 0:
        return 0
    offs = np.concatenate(([0], np.cumsum(num_keypoints))).astype(np.int64)
    point = np.full(int(offs[-1]), -1, np.int64)  # the 3D point of each keypoint, -1: none
    point[offs[r.obs_image] + r.obs_keypoint] = r.obs_point
    pair = np.concatenate([np.full(len(m), i) for i, (_, m) in enumerate(big)])
    a = np.concatenate([offs[int(k[0])] + m[:, 0] for k, m in big])
    b = np.concatenate([offs[int(k[1])] + m[:, 1] for k, m in big])
    kept = (point[a] == point[b]) & (point[a] >= 0)
    share = np.bincount(pair, kept, len(big)) / np.bincount(pair, minlength=len(big))
    return int((share < opt.pair_explained_min).sum())


def _doubts(r: SfmResult, members: np.ndarray, opt: BundleOptions,
            pairs: np.ndarray, open_pairs: int = 0) -> list[str]:
    """Why an adjustment of the ``members`` may have kept a wrong start (empty: no doubt):
    cameras left unrefined, too few track observations explained, ``open_pairs`` verified
    pairs whose matches it dropped (:func:`_open_pairs`), a start whose median reprojection
    error was above ``opt.start_error_px``, a camera whose points are
    seen only under tiny angles (explained by rotation alone), or two centres on one spot
    (a collapse that bundle adjustment keeps): two refined cameras of a matched image pair
    with a baseline (``pairs (E, 2)``, :func:`baseline_pairs`) closer than a tenth of the
    typical spacing, the median over cameras of
    the distance to their nearest matched partner. Not the median over all camera pairs:
    along a long sequence the next frame is always within 2% of that; and not 2% of the
    median over matched pairs: a turntable camera collapsed onto its neighbour (6% of the
    spacing, 2.1% of that median) kept a camera 8 deg and most of the ring off."""
    from .selfcheck import triangulation_angles

    out = []
    if not bool(r.refined[members].all()):
        out.append(f"{int((members & ~r.refined).sum())} camera(s) unrefined")
    explained = _support(r) / max(int(r.tracks.track.size), 1)
    if explained < opt.explained_min:
        out.append(f"explains {explained:.0%} of the track observations")
    if open_pairs:
        out.append(f"{open_pairs} verified pair(s) keep under {opt.pair_explained_min:.0%} "
                   "of their matches")
    start_px = float(r.stats.get("median_error_before", 0.0))
    if start_px > opt.start_error_px:
        # from that far off, an adjustment can settle in a wrong minimum that explains its
        # observations well (8 DTU views started at 242 px: 0.33 px, two cameras 11 and 36 deg
        # off, 85 % of the observations)
        out.append(f"started {start_px:.0f} px off")
    ref = np.flatnonzero(r.refined)
    if ref.size >= 2 and r.obs_image.size:
        _, tri = triangulation_angles(r.w2c, r.points, r.obs_image, r.obs_point,
                                      r.w2c.shape[0])
        low = int((tri[ref] < opt.min_angle_deg).sum())
        if low:
            out.append(f"{low} camera(s) see their points at under {opt.min_angle_deg:g} deg")
        c = -np.einsum("nji,nj->ni", r.w2c[:, :3, :3], r.w2c[:, :3, 3])
        linked = pairs[r.refined[pairs[:, 0]] & r.refined[pairs[:, 1]]]
        d = np.linalg.norm(c[linked[:, 0]] - c[linked[:, 1]], axis=1)
        nearest = np.full(c.shape[0], np.inf)
        np.minimum.at(nearest, linked[:, 0], d)
        np.minimum.at(nearest, linked[:, 1], d)
        spacing = float(np.median(nearest[np.isfinite(nearest)])) if d.size else 0.0
        if spacing > 0 and (d < 0.1 * spacing).any():
            out.append("camera centres coincide")
    return out


def _score(r: SfmResult) -> tuple[int, int]:
    """Rank of an adjustment among starts: refined cameras whose points are not explained by
    rotation alone, then observations explained."""
    from .selfcheck import triangulation_angles

    good = 0
    if r.obs_image.size:
        _, tri = triangulation_angles(r.w2c, r.points, r.obs_image, r.obs_point,
                                      r.w2c.shape[0])
        good = int((r.refined & (tri >= 1.0)).sum())
    return good, _support(r)


def _best_start(uv: Sequence[np.ndarray], pair_matches: Mapping[tuple[int, int], np.ndarray],
                K: np.ndarray, dist: Sequence[np.ndarray | None] | None, w2c: np.ndarray,
                placed: np.ndarray, opt: BundleOptions, anchored: np.ndarray | None,
                seed: int, rotation_only: Iterable[tuple[int, int]] = ()) -> SfmResult:
    """:func:`bundle_adjust_reconstruction` from the start ``opt.start`` names (see
    :data:`~posernet.sfm.bundle.STARTS`); ``stats["start"]`` says which start was kept, why,
    and what each start tried kept (refined cameras seeing their points at a useful angle,
    observations)."""
    averaged_opt = dataclasses.replace(opt, start="averaged")
    K = np.asarray(K, np.float64)
    w2c = np.asarray(w2c, np.float64)
    members = np.asarray(placed, bool).reshape(-1) & np.isfinite(w2c).all((1, 2))
    _check_inputs(uv, K, dist, w2c, members)
    small = int(members.sum()) <= opt.incremental_max_cameras
    pairs = baseline_pairs(pair_matches, rotation_only)
    n_kp = [len(u) for u in uv]

    def averaged() -> SfmResult:
        return bundle_adjust_reconstruction(uv, pair_matches, K, dist, w2c, placed,
                                            averaged_opt, anchored=anchored, seed=seed)

    def positioned() -> SfmResult | None:
        t0 = time.perf_counter()
        tracks, xy = _observations(uv, pair_matches, K, dist, members)
        gp = global_positioning(xy, tracks.track, tracks.image, tracks.num_tracks, K, w2c,
                                members)
        if int(gp.positioned.sum()) < 2:
            return None
        res = _restart(uv, pair_matches, K, dist, w2c, gp.w2c, gp.positioned, members,
                       averaged_opt, seed, time.perf_counter() - t0, "positioning")
        return res if res.refined.any() else None  # no adjustment accepted

    def incremental() -> SfmResult | None:
        t0 = time.perf_counter()
        tracks, xy = _observations(uv, pair_matches, K, dist, members)
        reg = register_incrementally(xy, tracks.track, tracks.image, tracks.num_tracks, K,
                                     w2c, members,
                                     dataclasses.replace(averaged_opt, refine_focal="none"),
                                     min_inliers=max(6, opt.min_points_per_camera), seed=seed)
        if int(reg.registered.sum()) < 2:
            return None
        return _restart(uv, pair_matches, K, dist, w2c, reg.w2c, reg.registered, members,
                        averaged_opt, seed, time.perf_counter() - t0, "registration")

    if opt.start == "positioning":
        res = positioned()
        if res is None:
            res = averaged()
            res.stats["start"] = {"kept": "averaged", "why": "positioning placed no camera"}
        else:
            res.stats["start"] = {"kept": "positioning", "why": "start=positioning"}
        return res
    tried: dict[str, SfmResult] = {}
    why = ""
    if opt.start == "auto" or not small:
        tried["averaged"] = averaged()
        doubts = _doubts(tried["averaged"], members, opt, pairs,
                         _open_pairs(tried["averaged"], pair_matches, n_kp, opt))
        if not doubts:
            tried["averaged"].stats["start"] = {
                "kept": "averaged", "why": "every camera refined, explaining "
                f"{_support(tried['averaged']) / max(tried['averaged'].tracks.track.size, 1):.0%}"
                " of the track observations, none collapsed"}
            return tried["averaged"]
        why = "averaged start: " + "; ".join(doubts)
        if opt.start == "auto":
            res = positioned()
            if res is not None:
                tried["positioning"] = res
    if small:
        best = max(tried.values(), key=_score) if tried else None
        if best is None or _doubts(best, members, opt, pairs,
                                   _open_pairs(best, pair_matches, n_kp, opt)):
            res = incremental()
            if res is not None:
                tried["incremental"] = res
    if not tried:  # start=incremental, and the registration placed nothing
        tried["averaged"] = averaged()
    order = list(tried)
    kept = max(order, key=lambda k: (_score(tried[k]), -order.index(k)))
    out = tried[kept]
    for k, r in tried.items():  # the starts tried and not kept took time too
        if k != kept:
            out.stats["seconds"][f"{k}_start_discarded"] = r.stats["seconds"]["total"]
    obs = {k: _support(r) for k, r in tried.items()}
    out.stats["start"] = {"kept": kept, "why": why or f"start={opt.start}",
                          "observations": obs,
                          "cameras": {k: _score(r)[0] for k, r in tried.items()}}
    if not small:
        out.stats["start"]["why"] += (f"; component over {opt.incremental_max_cameras} cameras:"
                                      " not registered incrementally")
    return out

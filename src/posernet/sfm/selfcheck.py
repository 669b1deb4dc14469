"""Hold a finished reconstruction against the evidence it came from, camera by camera.

Motion averaging and bundle adjustment can return a confident, low-reprojection-error answer
that is wrong: on a sparse ring or chain, translation averaging may stack many camera centres
on one spot, and rotations that explain the matches by turning alone reproject as well as the
truth. A user without ground truth cannot see that, so every camera reported as placed must
pass these checks first (:func:`check_reconstruction`):

* **pairs**: each verified image pair against the relative pose of the final cameras. Where
  the pair's inlier matches are known, the pair agrees when the final pose explains at least
  ``min_inlier_share`` of them (Sampson distance to the epipolar lines within
  ``max_epipolar_px``; for a rotation-only pair, transfer by the relative rotation alone).
  That is the evidence itself: with a narrow field of view a two-view rotation can be
  degrees off and still fit the matches, and a bundle-adjusted pose that fits them as well is
  not wrong for it. Where no matches are known (box-centre edges), the two-view rotation and
  translation direction must lie within ``max_rotation_deg`` / ``max_direction_deg``. A
  camera passes when its agreeing pairs carry at least ``min_agreeing_share`` of its pairs'
  weight (their inlier counts) and, when a single pair agrees, that pair has at least
  ``min_single_pair_inliers`` inliers: two views with a few dozen matches can fit a pose tens
  of degrees off (two-view ambiguity), so one weak pair is no proof; nor is one pair whose
  inliers a homography explains (``planar``, with ``single_planar_fails``): a plane seen from
  two views fits two relative poses, and the five-point solver may return the wrong one.
  Cameras are dropped one
  at a time, the worst first, and the others re-scored without them, so that a good camera is
  not failed for its pairs with a bad one.
* **coinciding centres**: a camera whose centre lies on another camera's although their pair
  has a baseline (not rotation-only) has been collapsed onto it.
* **structure** (with bundle adjustment): enough 3D points seen by the camera, and rays to
  them that meet the other views' rays at a useful angle; points seen only under tiny angles
  are explained by rotation alone and do not fix the camera's position.
* **tied scales** (with bundle adjustment): a verified pair fixes the direction between its
  cameras, not their distance. Two pairs that share a camera have their distances tied only
  by a third pair closing the triangle or by 3D points all three cameras see
  (``scale_links`` of them). On a chain of pairs whose points stop at two views (a sparse
  ring, views matched by different matchers), the next camera's distance is free: the answer
  there is whatever the solvers chose, right on an evenly spaced turntable, wrong elsewhere.
  The largest block of tied pairs (most cameras, then most inliers) keeps its cameras in the
  component, with every camera whose pairs into the block cross (two known lines meet at it);
  a rotation-only pair ties its cameras to one centre and so to any block. The next largest
  block among the cameras left, and so on, is a component of its own (``part`` 1, 2, ...):
  its cameras are right among themselves, only their distance to the others is free, as
  between two models of an incremental mapper. A camera in no block of two or more fails.

A camera that fails is reported unsolved with its reason. The run has verified itself when
at least two cameras pass.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..options import check_options, option

__all__ = ["CheckOptions", "PairEvidence", "SelfCheck", "check_reconstruction"]


@dataclass
class CheckOptions:
    """Thresholds of :func:`check_reconstruction`.

    ``max_epipolar_px`` / ``min_inlier_share``: a verified pair with known matches agrees with
    the final poses when this share of its inliers lies within this distance of their
    epipolar lines; ``max_rotation_deg`` / ``max_direction_deg``: a pair without matches
    agrees when its two-view rotation and (pairs with a baseline) translation direction are
    within these; ``min_agreeing_share``: the inlier-weighted share of a camera's pairs that must
    agree; ``min_points``: 3D points a camera must see (with bundle adjustment);
    ``min_single_pair_inliers`` / ``min_single_pair_kept``: a camera that rests on one
    agreeing pair needs that many inliers in it and (with bundle adjustment) must see at
    least this share of them as 3D points (a wrong two-view geometry, e.g. a mirrored match,
    agrees with the pose it produced but its matches do not join the other cameras' points);
    ``single_planar_fails``: nor may that pair be planar (two relative poses fit a plane's
    matches); ``min_triangulation_deg``: the median angle between a camera's rays and the
    other views' rays to the same points must reach it; ``coincide_ratio``: two cameras
    whose pair has a baseline count as collapsed when their centres are closer than this
    times the median distance between verified pairs' centres; ``scale_links``: 3D points
    seen by all three cameras of two pairs that share a camera tie the pairs' distances (a
    triangle of pairs always does; 0: no check of tied scales).
    """

    max_epipolar_px: float = option(2.0, gt=0, help="a verified pair agrees when the final "
                                    "poses put min_inlier_share of its inlier matches within "
                                    "this many px of their epipolar lines")
    min_inlier_share: float = option(0.5, ge=0, le=1, help="... that share")
    max_rotation_deg: float = option(5.0, gt=0, le=180, help="pairs without matches (box "
                                     "centres): the two-view rotation this close")
    max_direction_deg: float = option(15.0, gt=0, le=180, help="... and the translation "
                                      "direction (pairs with a baseline) this close")
    min_agreeing_share: float = option(0.5, ge=0, le=1, help="inlier-weighted share of a "
                                       "camera's pairs that must agree")
    min_single_pair_inliers: int = option(50, ge=0, help="a camera with one agreeing pair: "
                                          "that pair needs this many inliers")
    min_single_pair_kept: float = option(0.75, ge=0, le=1, help="... and this share of them "
                                         "must join the 3D points")
    single_planar_fails: bool = option(True, help="... and it may not be planar (a plane fits "
                                       "two relative poses)")
    min_points: int = option(15, ge=0, help="a camera in the bundle adjustment must see this "
                             "many 3D points")
    min_triangulation_deg: float = option(1.0, ge=0, lt=90, help="median angle between its rays "
                                          "and the other views' rays")
    coincide_ratio: float = option(0.02, ge=0, lt=1, help="centres closer than this x the median "
                                   "pair baseline: collapsed")
    scale_links: int = option(1, ge=0, help="3D points all three cameras of two pairs sharing "
                              "a camera must see to tie the pairs' distances (0: no check of "
                              "tied scales)")

    def __post_init__(self) -> None:
        check_options(self)


@dataclass
class PairEvidence:
    """Verified two-view geometry of ``E`` image pairs: ``pairs (E, 2)`` image indices
    ``(a, b)``, ``R (E, 3, 3)`` and unit ``t (E, 3)`` mapping camera a to camera b
    (``x_b = R x_a + t``), ``rotation_only (E,)`` (no usable direction), ``weight (E,)``
    (inlier count), ``planar (E,)`` (optional: a homography explains the inliers). Optional
    inlier matches: ``match_pair (M,)`` the pair of each, ``x_a,
    x_b (M, 2)`` their normalised (undistorted, ``K^-1``) image coordinates, ``focal (E,)``
    pixels per normalised unit (to measure distances in pixels)."""

    pairs: np.ndarray
    R: np.ndarray
    t: np.ndarray
    rotation_only: np.ndarray
    weight: np.ndarray
    match_pair: np.ndarray | None = None
    x_a: np.ndarray | None = None
    x_b: np.ndarray | None = None
    focal: np.ndarray | None = None
    planar: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.pairs = np.asarray(self.pairs, np.int64).reshape(-1, 2)
        E = self.pairs.shape[0]
        self.R = np.asarray(self.R, np.float64).reshape(E, 3, 3)
        self.t = np.asarray(self.t, np.float64).reshape(E, 3)
        self.rotation_only = np.asarray(self.rotation_only, bool).reshape(E)
        self.weight = np.asarray(self.weight, np.float64).reshape(E)
        self.planar = (np.zeros(E, bool) if self.planar is None
                       else np.asarray(self.planar, bool).reshape(E))
        if self.match_pair is not None:
            self.match_pair = np.asarray(self.match_pair, np.int64).reshape(-1)
            M = self.match_pair.size
            self.x_a = np.asarray(self.x_a, np.float64).reshape(M, 2)
            self.x_b = np.asarray(self.x_b, np.float64).reshape(M, 2)
            self.focal = np.asarray(self.focal, np.float64).reshape(E)


@dataclass
class SelfCheck:
    """Outcome of :func:`check_reconstruction` for ``N`` cameras.

    ``passed (N,)``: placed and verified; ``reason[i]``: why placed camera ``i`` failed
    (``""`` when it passed or was not placed); per pair ``rotation_error_deg`` /
    ``direction_error_deg (E,)`` (NaN where a camera is not placed or, for the direction,
    the pair is rotation-only), ``inlier_share (E,)`` (NaN without matches); per camera
    ``agreeing_share``, ``points``, ``triangulation_deg`` (NaN where not measured).
    """

    placed: np.ndarray
    passed: np.ndarray
    reason: list[str]
    rotation_error_deg: np.ndarray
    direction_error_deg: np.ndarray
    agreeing_share: np.ndarray
    points: np.ndarray
    triangulation_deg: np.ndarray
    inlier_share: np.ndarray = field(default_factory=lambda: np.zeros(0))
    options: CheckOptions = field(default_factory=CheckOptions)
    #: ``(N,)`` the block of tied pairs a passing camera belongs to: 0 the largest (the
    #: component's frame), k >= 1 a further block that nothing ties to it (a component of its
    #: own); -1 for a camera that did not pass
    part: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    @property
    def split(self) -> np.ndarray:
        """``(N,)`` passing cameras split off into components of their own."""
        return self.passed & (self.part > 0) if self.part.size else np.zeros_like(self.passed)

    @property
    def failed(self) -> np.ndarray:
        """``(N,)`` placed cameras that failed a check."""
        return self.placed & ~self.passed

    @property
    def verified(self) -> bool:
        """Whether the run verified itself: at least two cameras passed."""
        return int(self.passed.sum()) >= 2

    def line(self, names: Sequence[str] | None = None) -> str:
        """One line for a person: how many placed cameras passed, and the first failures."""
        n_placed, n_fail = int(self.placed.sum()), int(self.failed.sum())
        if not self.verified:
            return (f"self-check: could not verify the reconstruction: {int(self.passed.sum())}"
                    f" of {n_placed} placed cameras agree with their verified image pairs and "
                    "3D points; none is reported as placed")
        n_split = int(self.split.sum())
        split = (f"; {n_split} of them in {self.split_parts} component(s) of their own (nothing "
                 "ties their distance to the other cameras)") if n_split else ""
        if not n_fail:
            return f"self-check: all {n_placed} placed cameras agree with their evidence{split}"
        idx = np.flatnonzero(self.failed)
        label = [names[i] if names is not None else str(i) for i in idx[:3]]
        more = f" and {n_fail - 3} more" if n_fail > 3 else ""
        first = "; ".join(f"{n}: {self.reason[i]}" for n, i in zip(label, idx[:3], strict=False))
        split = (f"; of the {n_placed - n_fail} that passed, {n_split} are in "
                 f"{self.split_parts} component(s) of their own (nothing ties their distance to "
                 "the other cameras)") if n_split else ""
        return (f"self-check: {n_fail} of {n_placed} placed cameras failed and are reported "
                f"unsolved ({first}{more}){split}")

    @property
    def split_parts(self) -> int:
        """How many components of their own the split cameras form."""
        return int(np.unique(self.part[self.split]).size) if self.split.any() else 0

    def to_dict(self, names: Sequence[str]) -> dict:
        """JSON-ready per-camera record (failed cameras with their reasons)."""
        return {"verified": self.verified, "placed_before": int(self.placed.sum()),
                "passed": int(self.passed.sum()),
                "failed": {names[i]: self.reason[i] for i in np.flatnonzero(self.failed)},
                "split": {names[i]: int(self.part[i]) for i in np.flatnonzero(self.split)},
                "options": {k: getattr(self.options, k) for k in
                            self.options.__dataclass_fields__}}


def _angle_deg(cos: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def pair_errors(w2c: np.ndarray, evidence: PairEvidence) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation-direction error (deg, ``(E,)`` each) of each verified pair
    against the relative pose of ``w2c (N, 4, 4)``; direction NaN for rotation-only pairs and
    for cameras at one centre."""
    a, b = evidence.pairs[:, 0], evidence.pairs[:, 1]
    Ra, Rb = w2c[a, :3, :3], w2c[b, :3, :3]
    ta, tb = w2c[a, :3, 3], w2c[b, :3, 3]
    R_ab = Rb @ Ra.transpose(0, 2, 1)
    t_ab = tb - np.einsum("eij,ej->ei", R_ab, ta)
    D = R_ab @ evidence.R.transpose(0, 2, 1)
    rot = _angle_deg((np.trace(D, axis1=1, axis2=2) - 1.0) / 2.0)
    n1 = np.linalg.norm(t_ab, axis=1)
    n2 = np.linalg.norm(evidence.t, axis=1)
    ok = (n1 > 1e-12) & (n2 > 1e-12)
    cos = np.einsum("ei,ei->e", t_ab, evidence.t) / np.where(ok, n1 * n2, 1.0)
    direction = np.where(ok, _angle_deg(cos), np.nan)
    direction[evidence.rotation_only] = np.nan
    return rot, direction


def inlier_shares(w2c: np.ndarray, evidence: PairEvidence, max_px: float) -> np.ndarray:
    """``(E,)`` share of each pair's inlier matches that the relative pose of ``w2c`` explains
    within ``max_px``: Sampson distance to the epipolar lines, or for a rotation-only pair the
    transfer error of the relative rotation alone; NaN for pairs without matches."""
    E = evidence.pairs.shape[0]
    out = np.full(E, np.nan)
    if evidence.match_pair is None or evidence.match_pair.size == 0:
        return out
    a, b = evidence.pairs[:, 0], evidence.pairs[:, 1]
    R_ab = w2c[b, :3, :3] @ w2c[a, :3, :3].transpose(0, 2, 1)
    t_ab = w2c[b, :3, 3] - np.einsum("eij,ej->ei", R_ab, w2c[a, :3, 3])
    n_t = np.linalg.norm(t_ab, axis=1)
    # centres on one spot: no epipolar geometry, nothing explained (a rotation-only pair is
    # judged by its rotation below)
    size = np.maximum(np.linalg.norm(w2c[a, :3, 3], axis=1), np.linalg.norm(w2c[b, :3, 3], axis=1))
    same = n_t <= 1e-9 * np.maximum(size, 1.0)
    t_ab /= np.maximum(n_t, 1e-300)[:, None]
    tx = np.zeros((E, 3, 3))
    tx[:, 0, 1], tx[:, 0, 2], tx[:, 1, 2] = -t_ab[:, 2], t_ab[:, 1], -t_ab[:, 0]
    tx -= tx.transpose(0, 2, 1)
    m = evidence.match_pair
    Em = (tx @ R_ab)[m]
    xa = np.concatenate((evidence.x_a, np.ones((m.size, 1))), 1)
    xb = np.concatenate((evidence.x_b, np.ones((m.size, 1))), 1)
    Fx = np.einsum("mij,mj->mi", Em, xa)
    Ftx = np.einsum("mji,mj->mi", Em, xb)
    num = np.einsum("mi,mi->m", xb, Fx) ** 2
    den = Fx[:, 0] ** 2 + Fx[:, 1] ** 2 + Ftx[:, 0] ** 2 + Ftx[:, 1] ** 2
    err = np.sqrt(num / np.maximum(den, 1e-300)) * evidence.focal[m]
    err[same[m]] = np.inf
    rot = evidence.rotation_only[m]
    if rot.any():  # x_b ~ R x_a: distance in the image of b
        p = np.einsum("mij,mj->mi", R_ab[m[rot]], xa[rot])
        ok = p[:, 2] > 1e-12
        proj = p[:, :2] / np.where(ok, p[:, 2], 1.0)[:, None]
        err[rot] = np.where(ok, np.linalg.norm(proj - evidence.x_b[rot], axis=1)
                            * evidence.focal[m[rot]], np.inf)
    good = np.bincount(m, (err <= max_px).astype(np.float64), E)
    n = np.bincount(m, minlength=E)
    has = n > 0
    out[has] = good[has] / n[has]
    return out


def triangulation_angles(w2c: np.ndarray, points: np.ndarray, obs_image: np.ndarray,
                         obs_point: np.ndarray, num_cameras: int
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Per camera: points it sees ``(N,)`` and the median over its observations of the
    largest angle (deg) between its ray and another view's ray to the same point ``(N,)``
    (NaN for a camera without observations of points seen twice).

    The largest angle is taken against the two extreme rays of each point (the ray furthest
    from the rays' mean, and the ray furthest from that one): exact where a point's rays
    spread along one direction (a camera path), close otherwise, in time linear in the
    observations. Not the angle to the mean of the other rays: for a camera between two
    views at equal angles either side, that mean lies along its own ray."""
    N = num_cameras
    counts = np.bincount(obs_image, minlength=N)
    med = np.full(N, np.nan)
    if obs_image.size == 0:
        return counts, med
    P = points.shape[0]
    R, t = w2c[:, :3, :3], w2c[:, :3, 3]
    centre = -np.einsum("nji,nj->ni", R, t)
    ray = points[obs_point] - centre[obs_image]
    ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-300)
    mean = np.zeros((P, 3))
    np.add.at(mean, obs_point, ray)
    # the ray furthest from the mean, then the ray furthest from that one
    argmin = _ArgminPerGroup(obs_point, P)
    first = ray[argmin(np.einsum("oi,oi->o", ray, mean[obs_point]))]
    to_first = np.einsum("oi,oi->o", ray, first[obs_point])
    second = ray[argmin(to_first)]
    cos = np.minimum(to_first, np.einsum("oi,oi->o", ray, second[obs_point]))
    seen = np.bincount(obs_point, minlength=P)[obs_point]
    ang = np.where(seen >= 2, _angle_deg(np.clip(cos, -1.0, 1.0)), np.nan)
    order = np.argsort(obs_image, kind="stable")
    img_sorted = obs_image[order]
    bounds = np.searchsorted(img_sorted, np.arange(N + 1))
    a_sorted = ang[order]
    for i in np.flatnonzero(counts):
        vals = a_sorted[bounds[i]:bounds[i + 1]]
        vals = vals[np.isfinite(vals)]
        if vals.size:
            med[i] = float(np.median(vals))
    return counts, med


class _ArgminPerGroup:
    """For values ``(O,)`` of observations in groups ``group (O,)`` (in ``[0, G)``): ``(G,)``
    the index of an observation with its group's smallest value (0 for an empty group). The
    grouping is sorted once; each call is linear."""

    def __init__(self, group: np.ndarray, G: int) -> None:
        self.order = np.argsort(group, kind="stable")
        self.sorted = group[self.order]
        self.starts = np.flatnonzero(np.r_[True, self.sorted[1:] != self.sorted[:-1]])
        self.sizes = np.diff(np.r_[self.starts, self.sorted.size])
        self.G = G

    def __call__(self, values: np.ndarray) -> np.ndarray:
        out = np.zeros(self.G, np.int64)
        if not self.sorted.size:
            return out
        v = values[self.order]
        low = np.repeat(np.minimum.reduceat(v, self.starts), self.sizes)
        hit = v <= low
        out[self.sorted[hit]] = self.order[hit]  # any observation at its group's minimum
        return out


def check_reconstruction(w2c: np.ndarray, placed: np.ndarray, evidence: PairEvidence,
                         points: np.ndarray | None = None,
                         obs_image: np.ndarray | None = None,
                         obs_point: np.ndarray | None = None,
                         options: CheckOptions | None = None) -> SelfCheck:
    """Check every placed camera of ``w2c (N, 4, 4)`` (``placed (N,)``) against the verified
    pairs ``evidence`` and, when given, the bundle-adjusted ``points (P, 3)`` with their
    observations ``obs_image, obs_point (O,)`` (see the module docstring).

    Cameras are failed by the structure check first, then by the pair check (thin support,
    then one at a time by the lowest agreeing share, re-scoring the rest after each), then by
    the coinciding-centre check among those left.
    """
    opt = options or CheckOptions()
    w2c = np.asarray(w2c, np.float64)
    N = w2c.shape[0]
    placed = np.asarray(placed, bool).reshape(N) & np.isfinite(w2c).all((1, 2))
    reason = [""] * N
    ok = placed.copy()
    E = evidence.pairs.shape[0]
    rot_err, dir_err = (pair_errors(w2c, evidence) if E else (np.zeros(0), np.zeros(0)))
    a, b = (evidence.pairs[:, 0], evidence.pairs[:, 1]) if E else (np.zeros(0, int),) * 2
    both = placed[a] & placed[b] if E else np.zeros(0, bool)
    rot_err = np.where(both, rot_err, np.nan)
    dir_err = np.where(both, dir_err, np.nan)

    # Structure: points seen and their triangulation angles.
    n_pts = np.zeros(N, np.int64)
    tri = np.full(N, np.nan)
    if points is not None and obs_image is not None and obs_point is not None:
        obs_image = np.asarray(obs_image, np.int64)
        obs_point = np.asarray(obs_point, np.int64)
        n_pts, tri = triangulation_angles(w2c, np.asarray(points, np.float64), obs_image,
                                          obs_point, N)
        for i in np.flatnonzero(ok):
            if n_pts[i] < opt.min_points:
                ok[i] = False
                reason[i] = f"sees {int(n_pts[i])} 3D points (< {opt.min_points})"
            elif np.isfinite(tri[i]) and tri[i] < opt.min_triangulation_deg:
                ok[i] = False
                reason[i] = (f"its 3D points are explained by rotation alone (median "
                             f"triangulation angle {tri[i]:.2f} deg < "
                             f"{opt.min_triangulation_deg:g})")

    # Pairs: drop the worst camera at a time, re-scoring the others without it.
    agree = np.zeros(E, bool)
    inl = np.full(E, np.nan)
    if E:
        agree = (rot_err <= opt.max_rotation_deg) & (
            evidence.rotation_only | (dir_err <= opt.max_direction_deg))
        inl = np.where(both, inlier_shares(w2c, evidence, opt.max_epipolar_px), np.nan)
        has = np.isfinite(inl)
        agree[has] = inl[has] >= opt.min_inlier_share
    w = np.maximum(evidence.weight, 1.0) if E else np.zeros(0)
    # Thin support, judged once on the whole reconstruction (not re-judged as neighbours
    # fail, which would peel a chain from its ends): one agreeing pair, and a weak one.
    live = ok[a] & ok[b] if E else np.zeros(0, bool)
    good = live & agree
    n_good = np.bincount(a[good], minlength=N) + np.bincount(b[good], minlength=N)
    strongest = np.zeros(N)
    np.maximum.at(strongest, a[good], w[good])
    np.maximum.at(strongest, b[good], w[good])
    for i in np.flatnonzero(ok & (n_good == 1) & (strongest < opt.min_single_pair_inliers)):
        ok[i] = False
        reason[i] = (f"rests on one verified image pair with {int(strongest[i])} inliers "
                     f"(< {opt.min_single_pair_inliers}): too few to rule out a two-view "
                     "ambiguity")
    if opt.single_planar_fails and E:
        n_planar = (np.bincount(a[good & evidence.planar], minlength=N)
                    + np.bincount(b[good & evidence.planar], minlength=N))
        for i in np.flatnonzero(ok & (n_good == 1) & (n_planar == 1)):
            ok[i] = False
            reason[i] = ("rests on one verified image pair whose inliers a homography "
                         "explains: a plane seen from two views fits two relative poses")
    if points is not None:
        thin = ok & (n_good == 1) & (n_pts < opt.min_single_pair_kept * strongest)
        for i in np.flatnonzero(thin):
            ok[i] = False
            reason[i] = (f"rests on one verified image pair, and only {int(n_pts[i])} of its "
                         f"{int(strongest[i])} inliers join the 3D points (< "
                         f"{opt.min_single_pair_kept:g}): its two-view geometry does not fit "
                         "the other cameras")
    share = np.full(N, np.nan)
    while True:
        live = ok[a] & ok[b] if E else np.zeros(0, bool)
        tot = np.bincount(a[live], w[live], N) + np.bincount(b[live], w[live], N)
        good = live & agree
        yes = np.bincount(a[good], w[good], N) + np.bincount(b[good], w[good], N)
        share = np.where(tot > 0, yes / np.maximum(tot, 1e-300), 0.0)
        bad = ok & (share < opt.min_agreeing_share)
        if not bad.any():
            break
        worst = int(np.flatnonzero(bad)[np.argmin(share[bad])])
        ok[worst] = False
        mine = (a == worst) | (b == worst)
        n_pairs = int((mine & both).sum())
        if tot[worst] == 0:
            reason[worst] = ("no verified image pair links it to another camera that passed"
                             if n_pairs else "no verified image pair")
        else:
            n_agree = int((mine & both & agree).sum())
            reason[worst] = (f"disagrees with its verified image pairs: {n_agree} of "
                             f"{n_pairs} agree (weighted share {share[worst]:.2f} < "
                             f"{opt.min_agreeing_share:g})")
    # Coinciding centres on pairs that have a baseline, among the cameras still passing (a
    # camera whose collapsed partners failed above keeps its place).
    centre = -np.einsum("nji,nj->ni", w2c[:, :3, :3], w2c[:, :3, 3])
    base = both & ~evidence.rotation_only if E else np.zeros(0, bool)
    if base.any():
        dist = np.linalg.norm(centre[a] - centre[b], axis=1)
        scale = float(np.median(dist[base]))
        close = base & (dist < opt.coincide_ratio * scale)
        close &= ok[a] & ok[b]
        for e in np.flatnonzero(close):
            for i, j in ((a[e], b[e]), (b[e], a[e])):
                if ok[i]:
                    ok[i] = False
                    reason[i] = (f"its centre coincides with camera {int(j)}'s although "
                                 "their verified pair has a baseline (collapsed)")

    part = np.where(ok, 0, -1)
    if opt.scale_links and E and points is not None:
        live = ok[a] & ok[b]
        part = _tied_blocks(w2c, evidence, live & agree, obs_image, obs_point,
                            opt.scale_links, N)
        for i in np.flatnonzero(ok & (part < 0)):
            ok[i] = False
            reason[i] = ("its distance to the other cameras is not fixed: no triangle of "
                         "verified pairs and no 3D point seen with a third camera ties its "
                         "pair to the rest")
        _thin_blocks(part, ok, reason, live & agree, w, evidence, opt)

    share = np.where(placed, share, np.nan)
    if int(ok.sum()) < 2:
        for i in np.flatnonzero(ok):
            ok[i] = False
            reason[i] = "no other camera passed the checks"
    return SelfCheck(placed=placed, passed=ok, reason=reason, rotation_error_deg=rot_err,
                     direction_error_deg=dir_err, agreeing_share=share, points=n_pts,
                     triangulation_deg=tri, inlier_share=inl, options=opt,
                     part=np.where(ok, part, -1))


def _thin_blocks(part: np.ndarray, ok: np.ndarray, reason: list[str], good: np.ndarray,
                 w: np.ndarray, evidence: PairEvidence, opt: CheckOptions) -> None:
    """The thin-support rules again inside each split-off block (``part`` >= 1; ``ok``,
    ``reason`` and ``part`` updated in place): a camera resting on one agreeing pair of its
    block needs ``min_single_pair_inliers`` in it and, with ``single_planar_fails``, a pair a
    homography does not explain; a block left with fewer than two cameras fails."""
    a, b = evidence.pairs[:, 0], evidence.pairs[:, 1]
    for k in np.unique(part[part > 0]).tolist():
        inside = good & (part[a] == k) & (part[b] == k)
        n_in = np.bincount(a[inside], minlength=part.size) + np.bincount(b[inside],
                                                                          minlength=part.size)
        for e in np.flatnonzero(inside):
            for i in (a[e], b[e]):
                if n_in[i] != 1 or not ok[i]:
                    continue
                if w[e] < opt.min_single_pair_inliers:
                    why = (f"with {int(w[e])} inliers (< {opt.min_single_pair_inliers}): too "
                           "few to rule out a two-view ambiguity")
                elif opt.single_planar_fails and evidence.planar[e]:
                    why = "whose inliers a homography explains"
                else:
                    continue
                ok[i], part[i] = False, -1
                reason[i] = ("in a component of its own (nothing ties it to the others), it "
                             f"rests on one verified image pair {why}")
        left = np.flatnonzero(part == k)
        if left.size < 2:
            for i in left:
                ok[i], part[i] = False, -1
                reason[i] = ("in a component of its own (nothing ties it to the others), no "
                             "other camera of it passed the checks")


#: a camera outside the block joins when its pairs into the block cross at this angle or more
_MIN_CROSSING_DEG = 10.0


def _tied_blocks(w2c: np.ndarray, evidence: PairEvidence, use: np.ndarray,
                 obs_image: np.ndarray | None, obs_point: np.ndarray | None, links: int,
                 N: int) -> np.ndarray:
    """``(N,)`` the block of tied pairs ``use (E,)`` each camera belongs to: 0 the largest
    (:func:`_tied_block`), then 1, 2, ... the largest among the pairs whose cameras no earlier
    block holds, while such a block has two cameras or more; -1 for the rest."""
    part = np.full(N, -1, np.int64)
    use = use.copy()
    for k in range(N):
        block = _tied_block(w2c, evidence, use, obs_image, obs_point, links, N)
        if int(block.sum()) < 2:
            break
        part[block] = k
        taken = part >= 0
        use &= ~(taken[evidence.pairs[:, 0]] | taken[evidence.pairs[:, 1]])
    return part


def _tied_block(w2c: np.ndarray, evidence: PairEvidence, use: np.ndarray,
                obs_image: np.ndarray | None, obs_point: np.ndarray | None, links: int,
                N: int) -> np.ndarray:
    """``(N,)`` the cameras of the largest block of pairs ``use (E,)`` whose distances are
    tied (see the module docstring): most cameras, then most inliers; then every camera whose
    pairs into the block cross (the lines from two block cameras meet at it; final centres
    of ``w2c``). All ``False`` when no pair is used."""
    from ..frontend.consistency import triangles

    ids = np.flatnonzero(use)
    out = np.zeros(N, bool)
    if not ids.size:
        return out
    pairs = evidence.pairs[ids]
    # links between the used pairs (local ids): the pairs of each triangle, and a
    # rotation-only pair with every pair at its cameras (one centre for both)
    tri = triangles(pairs, N)
    u, v = [tri[:, 0], tri[:, 1]], [tri[:, 1], tri[:, 2]]
    for r in np.flatnonzero(evidence.rotation_only[ids]):
        at = np.flatnonzero(np.isin(pairs, pairs[r]).any(1))
        u.append(np.full(at.size, r))
        v.append(at)
    label = _components(ids.size, u, v)
    if np.unique(label).size > 1 and obs_image is not None and obs_point is not None \
            and len(obs_image):
        # pairs sharing a camera whose three cameras see >= links common 3D points (only
        # where the triangles left more than one block: dense sets never get here)
        u2, v2 = _point_links(pairs, np.asarray(obs_image, np.int64),
                              np.asarray(obs_point, np.int64), links, N)
        label = _components(ids.size, [*u, u2], [*v, v2])
    best, key = -1, (-1, -1.0)
    for lab in np.unique(label):
        cams = np.unique(pairs[label == lab])
        k = (cams.size, float(evidence.weight[ids[label == lab]].sum()))
        if k > key:
            best, key = lab, k
    out[np.unique(pairs[label == best])] = True
    # A camera with pairs to two cameras of the block, in directions that are not parallel,
    # sits where the two lines meet: it joins, and the block grows until none is left.
    centre = -np.einsum("nji,nj->ni", w2c[:, :3, :3], w2c[:, :3, 3])
    while True:
        grew = False
        for k in np.flatnonzero(~out & np.isin(np.arange(N), pairs)):
            mine = (pairs == k).any(1)
            others = pairs[mine].sum(1) - k
            ends = np.unique(others[out[others]])
            if ends.size < 2:
                continue
            d = centre[ends] - centre[k]
            d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
            cos = np.abs(d @ d.T)
            if (cos < np.cos(np.radians(_MIN_CROSSING_DEG))).any():
                out[k] = grew = True
        if not grew:
            return out


def _components(K: int, u: list[np.ndarray], v: list[np.ndarray]) -> np.ndarray:
    """Connected-component label ``(K,)`` of ``K`` nodes with the links ``u[k][i] - v[k][i]``."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    uu, vv = np.concatenate(u).astype(np.int64), np.concatenate(v).astype(np.int64)
    graph = coo_matrix((np.ones(uu.size), (uu, vv)), shape=(K, K))
    return connected_components(graph, directed=False)[1]


def _point_links(pairs: np.ndarray, obs_image: np.ndarray, obs_point: np.ndarray, links: int,
                 N: int) -> tuple[np.ndarray, np.ndarray]:
    """Links ``(u, v)`` between pairs ``(K, 2)`` that share a camera and whose three cameras
    see at least ``links`` common 3D points (observations ``obs_image``/``obs_point``)."""
    from scipy.sparse import csc_matrix

    P = int(obs_point.max()) + 1
    vis = csc_matrix((np.ones(obs_point.size, bool), (obs_point, obs_image)), shape=(P, N))
    index = {(int(i), int(j)): k for k, (i, j) in enumerate(pairs)}
    index.update({(j, i): k for (i, j), k in list(index.items())})
    partners: dict[int, list[int]] = {}
    for i, j in pairs.tolist():
        partners.setdefault(i, []).append(j)
        partners.setdefault(j, []).append(i)
    u, v = [], []
    for j, nb in partners.items():
        if len(nb) < 2:
            continue
        # points seen by j and each partner: (points, partners) counts of triples
        both = vis[:, nb].multiply(vis[:, [j]]).tocsc().astype(np.int64)
        common = (both.T @ both).toarray()  # points seen by j, x and y
        x, y = np.nonzero(np.triu(common >= links, 1))
        u += [index[(j, nb[q])] for q in x]
        v += [index[(j, nb[q])] for q in y]
    return np.asarray(u, np.int64), np.asarray(v, np.int64)

"""Two-view geometric verification: accept an image pair's relative pose only when the matches
support it, as structure-from-motion systems do.

:func:`verify_two_view` fits an essential matrix (OpenCV's 5-point inside RANSAC / USAC) to the
pair's correspondences and then decides, in this order (a rejection names its rule in
``TwoView.status``):

* ``too_few_matches``: fewer correspondences than ``min_inliers``.
* ``static``: most matches do not move between the two images (``max_static_ratio`` of them
  within ``static_px``): a watermark, a time stamp, sensor dust or a uniform background matched
  to itself. No real camera motion keeps the scene still in the image, except none at all.
* ``no_model``: RANSAC found no essential matrix / pose.
* **Pure rotation** first, because under a pure rotation (or on a plane) the essential matrix
  is not unique and its cheirality test fails for reasons that say nothing about the pair:
  when a rotation alone explains ``max_rotation_ratio`` of the essential-matrix inliers, the
  pair is a **rotation-only** edge (``status="rotation"``) with that rotation, subject to the
  count rules below. The translation direction of such an edge is meaningless and must not
  reach translation averaging.
* **Plane**: when a homography explains ``max_rotation_ratio`` of them the pair is reported
  ``planar``, and the homography's decomposition replaces the 5-point pose if it puts more
  points in front of both cameras.
* ``cheirality``: fewer than ``min_front`` of the essential-matrix inliers triangulate in
  front of both cameras (a wrong or degenerate solution).
* ``too_few_inliers`` / ``low_inlier_ratio``: fewer than ``min_inliers`` pose inliers, or fewer
  than ``min_inlier_ratio`` of all correspondences.
* A pair that passes is a full edge (``status="ok"``), or a rotation-only edge when the median
  triangulation angle of its inliers is below ``min_tri_angle`` (too small a baseline to see
  depth).

Once every pair is verified, the edges are also checked against each other
(:mod:`posernet.frontend.consistency`): inliers crowded on a small part of either image
(``min_spread``, :func:`inlier_spread`) and rotations that contradict the triangles of the
view graph (``max_loop_deg``, ``max_loop_share``) reject an edge.

Keypoints on uniform regions are removed before matching ever sees them
(:func:`keypoint_contrast`): on an object photographed on black, learned matchers otherwise pair
up background noise between views from opposite sides.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..options import check_options, option
from .relpose import METHODS, normalised_points

__all__ = ["TwoView", "VerifyRules", "epipolar_consistent", "inlier_spread", "keypoint_contrast",
           "verify_two_view"]


@dataclass(frozen=True)
class VerifyRules:
    """Thresholds of two-view verification (see the module docstring)."""

    min_inliers: int = option(15, ge=5, help="pose inliers (5: the 5-point minimum; 15 is "
                              "COLMAP's default minimum as well)")
    min_inlier_ratio: float = option(0.2, ge=0, le=1, help="pose inliers / matches in matched "
                                     "boxes")
    min_front: float = option(0.9, ge=0, le=1, help="share of inliers triangulated in front of "
                              "both cameras")
    max_rotation_ratio: float = option(0.9, ge=0, le=1, help="a pure rotation explaining this "
                                       "share -> rotation-only edge")
    min_tri_angle: float = option(1.0, ge=0, help="degrees: median triangulation angle below "
                                  "this -> rotation-only edge")
    static_px: float = option(1.0, ge=0, help="matches moving less than this (px) are static ...")
    max_static_ratio: float = option(0.5, ge=0, le=1, help="... and a pair with more static "
                                     "matches is rejected")
    min_contrast: float = option(3.0, ge=0, help="grey levels: keypoints on flatter patches "
                                 "(uniform background) dropped")
    contrast_radius: int = option(4, ge=1, help="patch half-size of that contrast (px)")
    # checks of the verified pairs against each other (posernet.frontend.consistency)
    min_spread: float = option(0.015, ge=0, le=1, help="share of each image the inliers' hull "
                               "must cover (0: off)")
    max_loop_deg: float = option(6.0, ge=0, le=180, help="degrees: a triangle of edges whose "
                                 "rotations do not close within this is inconsistent (0: off)")
    max_loop_share: float = option(0.5, ge=0, le=1, help="an edge inconsistent in more than this "
                                   "share of its triangles (inlier-weighted) is rejected")

    def __post_init__(self) -> None:
        check_options(self)


@dataclass
class TwoView:
    """The verified geometry of one image pair (poses map camera 1 to camera 2).

    ``R (3, 3)``, unit ``t (3,)`` or ``None`` when rejected; ``inliers (M,)`` bool over the
    given correspondences; ``status`` ``"ok"``, ``"rotation"`` (rotation-only edge) or the
    rejection reason; ``info`` the measured quantities (counts, ratios, angles).
    """

    R: np.ndarray | None
    t: np.ndarray | None
    inliers: np.ndarray
    status: str
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def accepted(self) -> bool:
        return self.status in ("ok", "rotation")

    @property
    def rotation_only(self) -> bool:
        return self.status == "rotation"

    @property
    def pose(self) -> tuple[np.ndarray, np.ndarray] | None:
        return (self.R, self.t) if self.accepted else None


def keypoint_contrast(grey: np.ndarray, uv: np.ndarray, radius: int = 4) -> np.ndarray:
    """Standard deviation of the grey levels in the ``(2r+1)^2`` patch around each keypoint.

    ``grey (H, W)`` uint8 or float image, ``uv (K, 2)`` pixel (x, y); returns ``(K,)``.
    """
    if uv.shape[0] == 0:
        return np.zeros(0)
    g = grey.astype(np.float32)
    k = (2 * int(radius) + 1,) * 2
    mean = cv2.boxFilter(g, -1, k, borderType=cv2.BORDER_REFLECT)
    sq = cv2.boxFilter(g * g, -1, k, borderType=cv2.BORDER_REFLECT)
    std = np.sqrt(np.maximum(sq - mean * mean, 0.0))
    h, w = g.shape[:2]
    x = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, w - 1)
    y = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, h - 1)
    return std[y, x].astype(np.float64)


def inlier_spread(uv: np.ndarray, size: tuple[int, int], keep: float = 0.9) -> float:
    """Share of the image (``size`` (W, H)) that the convex hull of the inliers ``uv (M, 2)``
    (pixels) covers, on the ``keep`` share of them nearest their median so that a few stray
    matches do not stretch it.

    A pose fitted on matches crowded on a small patch is ill-conditioned (over a narrow field
    of view rotation and translation trade off), however many there are.
    """
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    area = float(size[0]) * float(size[1])
    if uv.shape[0] < 3 or area <= 0:
        return 0.0
    d = np.linalg.norm(uv - np.median(uv, axis=0), axis=1)
    n = max(3, int(np.ceil(keep * uv.shape[0])))
    near = uv[np.argsort(d, kind="stable")[:n]].astype(np.float32)
    return float(cv2.contourArea(cv2.convexHull(near))) / area


def _bearings(x: np.ndarray) -> np.ndarray:
    """Normalised image coordinates ``(M, 2)`` -> unit bearing vectors ``(M, 3)``."""
    b = np.concatenate([x, np.ones((x.shape[0], 1))], axis=1)
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def _fit_rotation(b1: np.ndarray, b2: np.ndarray) -> np.ndarray:
    """Least-squares rotation with ``b2 ~ R b1`` (Kabsch on unit bearings ``(M, 3)``)."""
    U, _, Vt = np.linalg.svd(b2.T @ b1)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _rotation_support(b1: np.ndarray, b2: np.ndarray,
                      tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Best pure rotation of the bearings (two refits on its own inliers) and its inliers."""
    R = _fit_rotation(b1, b2)
    for _ in range(2):
        ok = np.linalg.norm(b2 - b1 @ R.T, axis=1) < tol
        if ok.sum() < 3:
            break
        R = _fit_rotation(b1[ok], b2[ok])
    return R, np.linalg.norm(b2 - b1 @ R.T, axis=1) < tol


def _triangulation_angles(x1: np.ndarray, x2: np.ndarray, R: np.ndarray,
                          t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per correspondence (normalised coords ``(M, 2)``): the angle (degrees) between the two
    viewing rays at the triangulated point, and whether it lies in front of both cameras."""
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = np.hstack([R, t.reshape(3, 1)])
    Xh = cv2.triangulatePoints(P1, P2, x1.T.astype(np.float64), x2.T.astype(np.float64))
    w = Xh[3]
    X = (Xh[:3] / np.where(np.abs(w) > 1e-12, w, 1e-12)).T  # (M, 3) in camera 1
    c2 = -R.T @ t
    r1, r2 = X, X - c2
    cos = (r1 * r2).sum(1) / np.maximum(np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1),
                                        1e-300)
    ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    front = (X[:, 2] > 0) & ((X @ R.T + t)[:, 2] > 0) & np.isfinite(X).all(1)
    return ang, front


def _to_normalised(p1: np.ndarray, p2: np.ndarray, K1: np.ndarray, K2: np.ndarray | None,
                   dist1: np.ndarray | None, dist2: np.ndarray | None
                   ) -> tuple[np.ndarray, np.ndarray, float]:
    """Pixels ``(M, 2)`` of both images -> undistorted normalised coordinates, and the mean
    focal length that turns a pixel threshold into a normalised one (``K2`` defaults to
    ``K1``)."""
    K1 = np.asarray(K1, dtype=np.float64)
    K2 = K1 if K2 is None else np.asarray(K2, dtype=np.float64)
    f = 0.25 * (K1[0, 0] + K1[1, 1] + K2[0, 0] + K2[1, 1])
    return normalised_points(p1, K1, dist1), normalised_points(p2, K2, dist2), float(f)


def verify_two_view(
    p1: np.ndarray,
    p2: np.ndarray,
    K1: np.ndarray,
    K2: np.ndarray | None = None,
    dist1: np.ndarray | None = None,
    dist2: np.ndarray | None = None,
    rules: VerifyRules | None = None,
    threshold: float = 1.0,
    prob: float = 0.999,
    max_iters: int = 1000,
    seed: int = 0,
    method: str = "usac",
) -> TwoView:
    """Verified relative pose from pixel correspondences ``p1, p2 (M, 2)``.

    ``K1``/``K2 (3, 3)`` intrinsics (``K2`` defaults to ``K1``), ``dist1``/``dist2`` OpenCV
    distortion coefficients or ``None``; ``threshold`` the RANSAC threshold in pixels (on the
    undistorted, normalised points it is divided by the mean focal length). Never raises on
    degenerate input: the returned :class:`TwoView` says why it was rejected.
    """
    rules = rules or VerifyRules()
    if method not in METHODS:
        raise ValueError(f"unknown 5-point method {method!r}; choose from {sorted(METHODS)}")
    p1 = np.asarray(p1, dtype=np.float64).reshape(-1, 2)
    p2 = np.asarray(p2, dtype=np.float64).reshape(-1, 2)
    if p1.shape != p2.shape:
        raise ValueError(f"correspondences differ in shape: {p1.shape} vs {p2.shape}")
    M = p1.shape[0]
    none = np.zeros(M, bool)
    info: dict[str, Any] = {"matches": M}

    def reject(status: str, inliers: np.ndarray = none) -> TwoView:
        return TwoView(None, None, inliers, status, info)

    if M < max(5, int(rules.min_inliers)):
        return reject("too_few_matches")
    static = float((np.linalg.norm(p2 - p1, axis=1) < rules.static_px).mean())
    info["static_ratio"] = round(static, 4)
    if static > rules.max_static_ratio:
        return reject("static")
    x1, x2, f = _to_normalised(p1, p2, K1, K2, dist1, dist2)
    if not (np.isfinite(x1).all() and np.isfinite(x2).all()):
        return reject("no_model")
    thr = threshold / f
    cv2.setRNGSeed(int(seed) & 0x7FFFFFFF)
    try:
        E, mask = cv2.findEssentialMat(x1, x2, np.eye(3), method=METHODS[method], prob=prob,
                                       threshold=thr, maxIters=max_iters)
        if E is None or E.shape[0] < 3 or E.shape[1] != 3 or not np.isfinite(E[:3]).all():
            return reject("no_model")
        E = np.ascontiguousarray(E[:3])
        e_in = mask.reshape(-1).astype(bool)
        # the cheirality test of the essential inliers alone: recoverPose triangulates every
        # point it is given four times and judges each on its own, so the outliers (masked
        # out of its counts anyway) cost time and change nothing
        idx = np.flatnonzero(e_in)
        if idx.size < 5:
            info["essential_inliers"] = int(idx.size)
            return reject("too_few_inliers", e_in)
        _, R, t, sub = cv2.recoverPose(E, x1[idx], x2[idx], np.eye(3))
        pmask = np.zeros(M, bool)
        pmask[idx] = sub.reshape(-1) > 0
    except cv2.error:
        return reject("no_model")
    if R is None or t is None or not (np.isfinite(R).all() and np.isfinite(t).all()):
        return reject("no_model")
    t = t.reshape(3)
    if np.linalg.norm(t) < 1e-9 or abs(np.linalg.det(R) - 1.0) > 1e-3:
        return reject("no_model")
    t = t / np.linalg.norm(t)
    n_e = int(e_in.sum())
    info["essential_inliers"] = n_e
    if n_e < 5:
        return reject("too_few_inliers", e_in)

    def enough(inl: np.ndarray) -> str | None:
        """The count / ratio rule on a final inlier set (``None``: passes)."""
        info.update(inliers=int(inl.sum()), inlier_ratio=round(float(inl.sum()) / M, 4))
        if inl.sum() < rules.min_inliers:
            return "too_few_inliers"
        if inl.sum() / M < rules.min_inlier_ratio:
            return "low_inlier_ratio"
        return None

    # Degeneracies first: under a pure rotation or on a plane the essential matrix is not
    # unique, and its cheirality test fails for reasons that say nothing about the pair.
    b1, b2 = _bearings(x1), _bearings(x2)
    R_rot, rot_ok = _rotation_support(b1[e_in], b2[e_in], 2.0 * thr)
    rot_ratio = float(rot_ok.mean())
    info["rotation_ratio"] = round(rot_ratio, 4)
    if rot_ratio >= rules.max_rotation_ratio:
        inl = np.zeros(M, bool)
        inl[np.flatnonzero(e_in)[rot_ok]] = True
        why = enough(inl)
        return reject(why, inl) if why else TwoView(R_rot, t, inl, "rotation", info)
    H_fit = _homography_fit(x1[e_in], x2[e_in], 2.0 * thr, rules.max_rotation_ratio)
    h_ratio = H_fit[1] if H_fit is not None else 0.0
    info["homography_ratio"] = round(h_ratio, 4)
    planar = h_ratio >= rules.max_rotation_ratio
    info["planar"] = planar
    # the plane's poses are only wanted on a planar pair (their cheirality tests cost four
    # triangulations of every inlier)
    H_sol = _homography_pose(x1[e_in], x2[e_in], *H_fit) if planar and H_fit else None
    inl = pmask.reshape(-1).astype(bool) & e_in
    if planar and H_sol is not None and H_sol[2] > inl.sum():
        # the plane's decomposition puts more points in front than the essential matrix did
        R, t = H_sol[0], H_sol[1]
        inl = np.zeros(M, bool)
        inl[np.flatnonzero(e_in)[H_sol[4]]] = True
    front = float(inl.sum()) / n_e
    info["front_ratio"] = round(front, 4)
    if front < rules.min_front:
        info.update(inliers=int(inl.sum()), inlier_ratio=round(float(inl.sum()) / M, 4))
        return reject("cheirality", inl)
    why = enough(inl)
    if why:
        return reject(why, inl)
    ang, _ = _triangulation_angles(x1[inl], x2[inl], R, t)
    tri = float(np.median(ang))
    info["tri_angle"] = round(tri, 3)
    if tri < rules.min_tri_angle:
        return TwoView(R, t, inl, "rotation", info)
    return TwoView(R, t, inl, "ok", info)


#: chance of missing a plane that explains the planar share of the points (sets the draws)
_PLANE_MISS = 1e-9


def _homography_fit(x1: np.ndarray, x2: np.ndarray, thr: float, share: float = 0.9
                    ) -> tuple[np.ndarray, float] | None:
    """For normalised correspondences ``(M, 2)``: the RANSAC homography and the share of the
    correspondences it explains, or ``None``.

    Only a plane explaining at least ``share`` of them matters (the planar test), so RANSAC
    draws just enough 4-point samples to find such a plane but for a chance of
    :data:`_PLANE_MISS` (20 draws for 0.9, at most 300; 300 before: 1.7 -> 0.3 ms a pair on
    rendered frames). Below that share the returned one is the best of those draws, a lower
    bound of what a plane explains.
    """
    if x1.shape[0] < 4:
        return None
    clean = max(share, 0.05) ** 4  # a sample of 4 points all on the plane
    draws = 300 if clean >= 1 else int(np.clip(np.ceil(np.log(_PLANE_MISS)
                                                        / np.log1p(-clean)), 20, 300))
    try:
        H, hmask = cv2.findHomography(x1, x2, cv2.RANSAC, thr, maxIters=draws, confidence=0.99)
    except cv2.error:
        return None
    if H is None or hmask is None or not np.isfinite(H).all():
        return None
    return H, float(hmask.mean())


def _homography_pose(x1: np.ndarray, x2: np.ndarray, H: np.ndarray, ratio: float
                     ) -> tuple | None:
    """The best decomposition of the homography ``H`` of normalised correspondences
    ``(M, 2)`` (``ratio``: the share it explains): ``(R, unit t, points in front, ratio, front
    mask)``, or ``None``."""
    try:
        _, Rs, ts, _ = cv2.decomposeHomographyMat(H, np.eye(3))
    except cv2.error:
        return None
    best = None
    for Rk, tk in zip(Rs, ts, strict=True):
        tk = tk.reshape(3)
        nt = float(np.linalg.norm(tk))
        if nt < 1e-9 or not np.isfinite(Rk).all():
            continue
        _, front = _triangulation_angles(x1, x2, Rk, tk / nt)
        if best is None or front.sum() > best[2]:
            best = (Rk, tk / nt, int(front.sum()), ratio, front)
    return best


def epipolar_consistent(
    p1: np.ndarray,
    p2: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    K1: np.ndarray,
    K2: np.ndarray | None = None,
    dist1: np.ndarray | None = None,
    dist2: np.ndarray | None = None,
    threshold: float = 1.0,
) -> np.ndarray:
    """``(M,)`` mask of correspondences ``p1, p2 (M, 2)`` (pixels) that agree with the verified
    pose ``R, t``: Sampson distance below ``threshold`` pixels and in front of both cameras.

    Used to collect every match a verified pose explains (not only those it was fitted on) for
    keypoint tracks."""
    if p1.shape[0] == 0:
        return np.zeros(0, bool)
    x1, x2, f = _to_normalised(p1, p2, K1, K2, dist1, dist2)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    E = tx @ R
    h1 = np.concatenate([x1, np.ones((x1.shape[0], 1))], 1)
    h2 = np.concatenate([x2, np.ones((x2.shape[0], 1))], 1)
    Ex1, Etx2 = h1 @ E.T, h2 @ E
    num = (h2 * Ex1).sum(1) ** 2
    den = Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2
    sampson = np.sqrt(num / np.maximum(den, 1e-300)) * f
    _, front = _triangulation_angles(x1, x2, R, t)
    return (sampson < threshold) & front

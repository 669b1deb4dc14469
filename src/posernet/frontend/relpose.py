"""Initial relative poses with OpenCV's 5-point algorithm + RANSAC, failures made explicit.

``five_point`` returns ``(R, t)`` mapping camera-1 points to camera 2 (``x2 = R x1 + t``, unit
``t``), the convention of edge ``i -> j`` (``R_ij = R_j R_i^T``), or ``None`` when OpenCV cannot
give a usable pose (too few points, no essential matrix, degenerate output, no point passing the
cheirality check). Callers drop such edges and count them; a NaN pose is never produced.

Two images with the same intrinsics and no distortion use OpenCV's pixel-space solver directly
(what the synthetic generator does). Different intrinsics, or lens distortion, are handled by
undistorting both point sets to normalised camera coordinates first; the RANSAC threshold is
then the pixel threshold divided by the mean focal length, so it keeps its meaning in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..options import check_options, option

__all__ = ["METHODS", "PoseOptions", "five_point", "normalised_points"]


METHODS = {"usac": cv2.USAC_DEFAULT, "ransac": cv2.RANSAC}


@dataclass
class PoseOptions:
    """OpenCV 5-point + RANSAC (``findEssentialMat`` / ``recoverPose``)."""

    method: str = option("usac", choices=tuple(METHODS),
                         help="usac: USAC_DEFAULT (fast); ransac: classic, as in the paper")
    ransac_prob: float = option(0.999, gt=0, lt=1, help="RANSAC confidence")
    kp_threshold: float = option(1.0, gt=0, help="RANSAC threshold (px) on keypoints")
    bb_threshold: float = option(1.0, gt=0, help="RANSAC threshold (px) on box centres")
    max_iters: int = option(1000, ge=1, help="most RANSAC iterations")

    def __post_init__(self) -> None:
        check_options(self)


def normalised_points(p: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """Pixels ``(M, 2)`` -> undistorted normalised image coordinates ``(M, 2)``."""
    d = None if dist is None else np.asarray(dist, dtype=np.float64).reshape(-1)
    return cv2.undistortPoints(p.reshape(-1, 1, 2), K, d).reshape(-1, 2)


def five_point(
    p1: np.ndarray,
    p2: np.ndarray,
    K: np.ndarray,
    threshold: float = 1.0,
    prob: float = 0.999,
    max_iters: int = 1000,
    seed: int = 0,
    method: str = "usac",
    K2: np.ndarray | None = None,
    dist1: np.ndarray | None = None,
    dist2: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Relative pose from pixel correspondences ``p1, p2 (M, 2)``.

    ``K (3, 3)`` are the intrinsics of image 1 (and of image 2 unless ``K2`` is given);
    ``dist1``/``dist2`` OpenCV distortion coefficients ``(k1, k2, p1, p2[, k3...])`` or ``None``.
    ``method``: ``"ransac"`` is OpenCV's classic RANSAC around the 5-point solver (what the paper
    used; slow in OpenCV 5, about 10-40 ms a call), ``"usac"`` the same 5-point solver inside
    OpenCV's USAC framework (``USAC_DEFAULT``, about 10x faster). ``cv2.setRNGSeed(seed)`` runs
    first so that RANSAC is reproducible. ``threshold`` is in pixels. Returns ``R (3, 3)`` and
    unit ``t (3,)`` or ``None``.
    """
    if method not in METHODS:
        raise ValueError(f"unknown 5-point method {method!r}; choose from {sorted(METHODS)}")
    if p1.shape[0] < 5 or p1.shape != p2.shape:
        return None
    p1 = np.ascontiguousarray(p1, dtype=np.float64)
    p2 = np.ascontiguousarray(p2, dtype=np.float64)
    Kd = np.asarray(K, dtype=np.float64)
    K2d = Kd if K2 is None else np.asarray(K2, dtype=np.float64)
    general = K2 is not None and not np.array_equal(K2d, Kd)
    general = general or any(d is not None and np.any(np.asarray(d) != 0) for d in (dist1, dist2))
    if general:
        p1, p2 = normalised_points(p1, Kd, dist1), normalised_points(p2, K2d, dist2)
        threshold = threshold / (0.25 * (Kd[0, 0] + Kd[1, 1] + K2d[0, 0] + K2d[1, 1]))
        Kd = np.eye(3)
    cv2.setRNGSeed(int(seed) & 0x7FFFFFFF)
    try:
        E, mask = cv2.findEssentialMat(
            p1, p2, Kd, method=METHODS[method], prob=prob, threshold=threshold, maxIters=max_iters
        )
        if E is None or E.shape[0] < 3 or E.shape[1] != 3 or not np.isfinite(E[:3]).all():
            return None
        # With exactly five points OpenCV stacks up to ten solutions; take the first like a
        # plain pipeline would.
        E = np.ascontiguousarray(E[:3])
        good, R, t, _ = cv2.recoverPose(E, p1, p2, Kd, mask=mask)
    except cv2.error:
        return None
    if good < 1 or R is None or t is None:
        return None
    t = t.reshape(3)
    n = float(np.linalg.norm(t))
    if not (np.isfinite(R).all() and np.isfinite(t).all()) or n < 1e-9:
        return None
    if abs(np.linalg.det(R) - 1.0) > 1e-3:
        return None
    return R.astype(np.float64), t / n

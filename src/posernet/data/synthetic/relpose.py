"""Initial relative poses with OpenCV's 5-point algorithm + RANSAC, failures made explicit.

``five_point`` returns ``(R, t)`` mapping camera-1 points to camera 2 (``x2 = R x1 + t``, unit
``t``), the convention of edge ``i -> j`` in ``DESIGN.md``, or ``None`` when OpenCV cannot give
a usable pose (too few points, no essential matrix, degenerate output, no point passing the
cheirality check). Callers drop such edges and count them; a NaN pose is never produced.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["METHODS", "five_point"]


METHODS = {"usac": cv2.USAC_DEFAULT, "ransac": cv2.RANSAC}


def five_point(
    p1: np.ndarray,
    p2: np.ndarray,
    K: np.ndarray,
    threshold: float = 1.0,
    prob: float = 0.999,
    max_iters: int = 1000,
    seed: int = 0,
    method: str = "usac",
) -> tuple[np.ndarray, np.ndarray] | None:
    """Relative pose from pixel correspondences ``p1, p2 (M, 2)`` of two images sharing ``K``.

    ``method``: ``"ransac"`` is OpenCV's classic RANSAC around the 5-point solver (what the paper
    used; slow in OpenCV 5, about 10-40 ms a call), ``"usac"`` the same 5-point solver inside
    OpenCV's USAC framework (``USAC_DEFAULT``, about 10x faster). ``cv2.setRNGSeed(seed)`` runs
    first so that RANSAC is reproducible. Returns ``R (3, 3)`` and unit ``t (3,)`` or ``None``.
    """
    if p1.shape[0] < 5 or p1.shape != p2.shape:
        return None
    p1 = np.ascontiguousarray(p1, dtype=np.float64)
    p2 = np.ascontiguousarray(p2, dtype=np.float64)
    Kd = np.asarray(K, dtype=np.float64)
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

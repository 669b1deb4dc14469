"""The pinhole camera in numpy: look-at poses and the projection of points to pixels.

The numpy side of camera geometry, once (the torch side is :mod:`posernet.geometry`): the
simulator (:mod:`posernet.data.synthetic.camera`, the renderer), the SfM stage
(:func:`posernet.sfm.triangulation.project`) and its synthetic scenes
(:mod:`posernet.sfm.synthetic`) import it. It needs numpy only, so the SfM stage's hot path
pulls in nothing else.

Camera frame: OpenCV (x right, y down, z forward). Poses are world-to-camera
``x_cam = R X + t``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["look_at", "project"]


def look_at(centres: np.ndarray, targets: np.ndarray, roll: np.ndarray | None = None,
            up: np.ndarray | None = None) -> np.ndarray:
    """World-to-camera poses ``(F, 4, 4)`` of cameras at ``centres (F, 3)`` looking at ``targets``.

    The image "up" follows the world direction ``up`` (default +z, the simulator's world);
    ``roll (F,)`` (radians) turns the camera about its optical axis. Raises ``ValueError`` when
    a camera looks along ``up``.
    """
    fwd = targets - centres
    fwd = fwd / np.linalg.norm(fwd, axis=-1, keepdims=True)
    right = np.cross(fwd, np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, float))
    norm = np.linalg.norm(right, axis=-1, keepdims=True)
    if np.any(norm < 1e-6):
        raise ValueError("look_at: a camera looks straight up or down")
    right = right / norm
    down = np.cross(fwd, right)
    if roll is not None:
        c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]
        right, down = c * right + s * down, -s * right + c * down
    R = np.stack((right, down, fwd), axis=-2)  # rows: camera axes in world coordinates
    T = np.zeros((centres.shape[0], 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = -np.einsum("fij,fj->fi", R, centres)
    T[:, 3, 3] = 1.0
    return T


def project(points_cam: np.ndarray, K: np.ndarray, k1: float = 0.0) -> np.ndarray:
    """Pixels ``(*, 2)`` of camera-frame points ``(*, 3)``, with radial distortion ``k1``.

    ``K``: one ``(3, 3)`` matrix, or one per point ``(*, 3, 3)`` (a skew term is applied).
    ``x_d = x (1 + k1 r^2)`` on normalised coordinates; ``r^2`` is capped at 2 so that points
    far outside the field of view stay monotonic (they only matter for clipped boxes). Points
    behind the camera land mirrored; points at ``z = 0`` give inf / NaN (no warning).
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = points_cam[..., :2] / points_cam[..., 2:3]
    if k1:
        r2 = np.minimum((xy * xy).sum(-1, keepdims=True), 2.0)
        xy = xy * (1.0 + k1 * r2)
    K = np.asarray(K)
    focal = np.stack((K[..., 0, 0], K[..., 1, 1]), axis=-1)
    centre = np.stack((K[..., 0, 2], K[..., 1, 2]), axis=-1)
    with np.errstate(invalid="ignore"):
        uv = xy * focal + centre
        if np.any(K[..., 0, 1]):
            uv[..., 0] += K[..., 0, 1] * xy[..., 1]
    return uv

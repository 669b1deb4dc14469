"""Pinhole camera (Kinect-like) in numpy: intrinsics, look-at poses, projection, cuboid boxes.

Camera frame: OpenCV (x right, y down, z forward). Poses are world-to-camera
``x_cam = R X + t``; the world has z up. :func:`look_at` and :func:`project` are
:mod:`posernet.pinhole`'s (the one numpy camera geometry), named here for the simulator.
"""

from __future__ import annotations

import numpy as np

from ...pinhole import look_at, project

__all__ = [
    "CUBOID_EDGES",
    "cuboid_corners",
    "intrinsics",
    "look_at",
    "project",
    "projected_boxes",
    "rotation_z",
]

# Corner k of a cuboid has signs bits (x: bit 0, y: bit 1, z: bit 2) of its half extents.
_SIGNS = np.array(
    [[1 if k & 1 else -1, 1 if k & 2 else -1, 1 if k & 4 else -1] for k in range(8)],
    dtype=np.float64,
)
# The 12 edges join corners that differ in one bit.
CUBOID_EDGES = np.array(
    [(a, a | (1 << b)) for a in range(8) for b in range(3) if not a & (1 << b)], dtype=np.int64
)


def intrinsics(focal: float, width: int, height: int) -> np.ndarray:
    """3x3 K with the principal point at the image centre (7-Scenes: f = 585, 640x480)."""
    return np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])


def rotation_z(yaw: np.ndarray) -> np.ndarray:
    """Rotations about the world z axis, ``yaw (O,)`` radians -> ``(O, 3, 3)``."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((*np.shape(yaw), 3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1] = c, -s, s, c
    R[..., 2, 2] = 1.0
    return R


def cuboid_corners(centre: np.ndarray, half: np.ndarray, R: np.ndarray) -> np.ndarray:
    """World corners ``(O, 8, 3)`` of cuboids (centre ``(O, 3)``, half extents, ``R (O, 3, 3)``)."""
    local = _SIGNS[None] * half[:, None, :]
    return np.einsum("oij,okj->oki", R, local) + centre[:, None, :]


def projected_boxes(
    corners_cam: np.ndarray, K: np.ndarray, width: int, height: int, near: float, k1: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Image boxes of cuboids, clipped to the near plane and to the image.

    ``corners_cam (O, 8, 3)`` in the camera frame -> ``boxes (O, 4)`` pixel ``(x1, y1, x2, y2)``
    and ``valid (O,)``. The cuboid is clipped against ``z = near`` exactly (corners in front plus
    the points where edges cross the plane), so the box contains the projection of every part of
    the cuboid in front of the camera.
    """
    O = corners_cam.shape[0]
    z = corners_cam[..., 2]
    a, b = corners_cam[:, CUBOID_EDGES[:, 0]], corners_cam[:, CUBOID_EDGES[:, 1]]  # (O, 12, 3)
    za, zb = a[..., 2], b[..., 2]
    crosses = (za - near) * (zb - near) < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(crosses, (near - za) / (zb - za), 0.0)
    cut = a + s[..., None] * (b - a)
    pts = np.concatenate((corners_cam, cut), axis=1)  # (O, 20, 3)
    ok = np.concatenate((z >= near, crosses), axis=1)
    pts = np.where(ok[..., None], pts, np.array([0.0, 0.0, 1.0]))  # dummies, masked below
    uv = project(pts, K, k1)
    big = np.inf
    x1 = np.where(ok, uv[..., 0], big).min(1)
    y1 = np.where(ok, uv[..., 1], big).min(1)
    x2 = np.where(ok, uv[..., 0], -big).max(1)
    y2 = np.where(ok, uv[..., 1], -big).max(1)
    boxes = np.stack(
        (
            np.clip(x1, 0, width),
            np.clip(y1, 0, height),
            np.clip(x2, 0, width),
            np.clip(y2, 0, height),
        ),
        axis=-1,
    )
    valid = ok.any(1) & (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
    boxes[~valid] = 0.0
    return boxes.reshape(O, 4), valid

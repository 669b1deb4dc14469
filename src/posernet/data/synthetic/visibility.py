"""Which scene keypoints a camera sees: frustum, facing and occlusion by other cuboids.

Occlusion is exact for the simulated geometry: the segment from the camera centre to a keypoint
is tested against every other cuboid (slab test in the cuboid's frame). To keep this cheap the
test only runs for cuboids whose projected box contains the keypoint's projection.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import cuboid_corners, project, projected_boxes
from .scenes import Scene

__all__ = ["View", "observe"]

_MIN_COS = 0.1  # grazing views (> ~84 deg from the normal) see no texture


@dataclass
class View:
    """What one camera sees.

    ``kp_ids (V,)`` visible keypoints (sorted) with pixels ``kp_uv (V, 2)`` and the cosine of the
    viewing angle ``kp_cos (V,)``; per cuboid ``obj_box (O, 4)`` (projected, clipped),
    ``obj_valid (O,)``, ``obj_visible (O,)`` fraction of its facing in-image keypoints that are
    unoccluded (NaN when it has none) and ``obj_vis_box (O, 4)`` box of its visible keypoints.
    """

    kp_ids: np.ndarray
    kp_uv: np.ndarray
    kp_cos: np.ndarray
    obj_box: np.ndarray
    obj_valid: np.ndarray
    obj_visible: np.ndarray
    obj_vis_box: np.ndarray


def _segment_hits(
    origin: np.ndarray, ends: np.ndarray, centre: np.ndarray, half: np.ndarray, yaw: np.ndarray
) -> np.ndarray:
    """Whether segments ``origin -> ends (K, 3)`` cross cuboids ``(K, ...)`` before their end."""
    c, s = np.cos(yaw), np.sin(yaw)

    def to_local(v: np.ndarray) -> np.ndarray:  # R_z(-yaw) v
        return np.stack((c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1], v[:, 2]), 1)

    o = to_local(origin[None] - centre)
    d = to_local(ends - origin[None])
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (-half - o) * inv
        t2 = (half - o) * inv
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    return (tmin < tmax) & (tmax > 0.0) & (tmin < 1.0)


def observe(
    scene: Scene,
    w2c: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    near: float,
    far: float,
    k1: float = 0.0,
) -> View:
    """Visible keypoints and per-cuboid boxes for the world-to-camera pose ``w2c (4, 4)``."""
    R, t = w2c[:3, :3], w2c[:3, 3]
    C = -R.T @ t
    O = scene.num_objects
    corners = cuboid_corners(scene.centre, scene.half, scene.rotation)
    corners_cam = corners @ R.T + t
    obj_box, obj_valid = projected_boxes(corners_cam, K, width, height, near, k1)
    corners_cam_z_min = corners_cam[..., 2].min(1)

    X = scene.kp_xyz
    Xc = X @ R.T + t
    z = Xc[:, 2]
    ray = C - X
    dist = np.linalg.norm(ray, axis=1)
    cos = (scene.kp_normal * ray).sum(1) / np.maximum(dist, 1e-9)
    cand = np.nonzero((z > near) & (z < far) & (cos > _MIN_COS))[0]
    uv = project(Xc[cand], K, k1)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
    cand, uv = cand[inside], uv[inside]
    owner = scene.kp_owner[cand]

    # candidate occluders: cuboids whose box covers the keypoint, other than its owner
    # (float32 halves the memory traffic of these (V, O) tests; pixels need no more precision)
    # Only cuboids that can be in front of the keypoint: their nearest corner is closer.
    live = np.nonzero(obj_valid)[0]
    bx = obj_box[live].astype(np.float32)
    zmin = corners_cam_z_min[live].astype(np.float32)
    u = uv.astype(np.float32)
    cover = (
        (u[:, None, 0] >= bx[None, :, 0])
        & (u[:, None, 0] <= bx[None, :, 2])
        & (u[:, None, 1] >= bx[None, :, 1])
        & (u[:, None, 1] <= bx[None, :, 3])
        & (zmin[None, :] < z[cand].astype(np.float32)[:, None])
        & (owner[:, None] != live[None])
    )
    pi, oi = np.nonzero(cover)
    oi = live[oi]
    occluded = np.zeros(cand.size, bool)
    if pi.size:
        # lift the end point off its surface so that touching supports do not count
        ends = X[cand[pi]] + 2e-3 * scene.kp_normal[cand[pi]]
        hit = _segment_hits(C, ends, scene.centre[oi], scene.half[oi], scene.yaw[oi])
        occluded[pi[hit]] = True
    vis = ~occluded

    # per-object visibility and the box of its visible part
    own_mask = owner >= 0
    n_all = np.bincount(owner[own_mask], minlength=O)
    n_vis = np.bincount(owner[own_mask & vis], minlength=O)
    with np.errstate(invalid="ignore", divide="ignore"):
        obj_visible = np.where(n_all > 0, n_vis / n_all, np.nan)
    obj_vis_box = np.zeros((O, 4))
    sel = own_mask & vis
    if sel.any():
        o = owner[sel]
        u = uv[sel]
        x1 = np.full(O, np.inf)
        y1 = np.full(O, np.inf)
        x2 = np.full(O, -np.inf)
        y2 = np.full(O, -np.inf)
        np.minimum.at(x1, o, u[:, 0])
        np.minimum.at(y1, o, u[:, 1])
        np.maximum.at(x2, o, u[:, 0])
        np.maximum.at(y2, o, u[:, 1])
        has = np.isfinite(x1)
        obj_vis_box[has] = np.stack((x1, y1, x2, y2), 1)[has]
    return View(
        kp_ids=cand[vis],
        kp_uv=uv[vis],
        kp_cos=cos[cand][vis],
        obj_box=obj_box,
        obj_valid=obj_valid,
        obj_visible=obj_visible,
        obj_vis_box=obj_vis_box,
    )

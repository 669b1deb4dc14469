"""The JSON records of poses, one writer for every output that holds them (``refined.json`` of
``posernet-refine``, ``poses.json`` of ``posernet-reconstruct``).

A camera: ``solved``, ``component``, ``world_to_camera`` and ``camera_to_world`` (4x4),
``q_wxyz`` and ``t`` (the world-to-camera rotation as a unit quaternion and its translation); a
camera nothing placed has ``solved: false`` and ``null`` for the rest, never an invented pose.
An edge's relative pose: ``q_wxyz``, ``t`` and the 4x4 ``matrix`` mapping source-camera points
into the target camera.
"""

from __future__ import annotations

from typing import Any

from torch import Tensor

from .geometry import invert_se3, matrix_to_pose_vec

__all__ = ["camera_record", "pose_record", "pose_records"]


def _matrix(T: Tensor, digits: int | None) -> list[list[float]]:
    return _rows(T.double().tolist(), digits)


def _rows(rows: list[list[float]], digits: int | None) -> list[list[float]]:
    if digits is None:
        return rows
    return [[float(f"{v:.{digits}g}") for v in row] for row in rows]


def pose_record(T: Tensor, digits: int | None = None) -> dict[str, Any]:
    """``{"q_wxyz", "t", "matrix"}`` of a 4x4 pose ``T``; ``digits``: significant digits of
    the matrix entries (None: as computed)."""
    return pose_records(T[None], digits)[0]


def pose_records(T: Tensor, digits: int | None = None) -> list[dict[str, Any]]:
    """:func:`pose_record` of each pose of ``T [E, 4, 4]``, converted in one batch (an
    output with thousands of edges)."""
    T = T.double()
    p = matrix_to_pose_vec(T).tolist()
    return [{"q_wxyz": q[:4], "t": q[4:], "matrix": _rows(m, digits)}
            for q, m in zip(p, T.tolist(), strict=True)]


def camera_record(T: Tensor | None, component: int | None = None,
                  digits: int | None = None) -> dict[str, Any]:
    """The pose fields of one camera from its world-to-camera ``T [4, 4]`` (None: not placed);
    ``digits`` as in :func:`pose_record`."""
    if T is None:
        return {"solved": False, "component": None, "world_to_camera": None,
                "camera_to_world": None, "q_wxyz": None, "t": None}
    T = T.double()
    return {"solved": True, "component": None if component is None else int(component),
            "world_to_camera": _matrix(T, digits),
            "camera_to_world": _matrix(invert_se3(T), digits),
            "q_wxyz": matrix_to_pose_vec(T)[:4].tolist(), "t": T[:3, 3].tolist()}

"""Structure from motion back end: verified matches + initial absolute poses -> refined poses
and 3D points.

Stages (each usable on its own):

* :mod:`~posernet.sfm.tracks` -- :func:`build_tracks`: pairwise matches -> multi-view tracks
  (connected components over ``(image, keypoint)``; inconsistent and one-view tracks dropped);
* :mod:`~posernet.sfm.triangulation` -- :func:`triangulate_tracks`: batched DLT with
  cheirality, triangulation-angle and reprojection filters; :func:`undistort_keypoints`;
* :mod:`~posernet.sfm.bundle` -- :func:`bundle_adjust`: robust bundle adjustment on
  Levenberg-Marquardt with Schur-complement steps (or scipy's least squares) and an analytic
  sparse Jacobian;
* :mod:`~posernet.sfm.resection` -- :func:`anchored_cameras` (which averaged positions the
  edge directions pin) and :func:`resect_cameras` (the others re-placed by PnP on 3D points);
* :mod:`~posernet.sfm.positioning` -- :func:`global_positioning`: camera centres and points
  together from their viewing rays (rotations known), the start that cannot collapse;
* :mod:`~posernet.sfm.mapper` -- :func:`bundle_adjust_reconstruction`: the orchestrator
  (start, tracks, triangulation, BA, filter, BA) used as the last stage of a reconstruction;
* :mod:`~posernet.sfm.selfcheck` -- :func:`check_reconstruction`: every placed camera held
  against its verified pairs and its 3D points;
* :mod:`~posernet.sfm.synthetic` -- synthetic scenes for tests and benchmarks.

Conventions: world-to-camera ``w2c (N, 4, 4)``, ``x_cam = R X + t``, pixels ``K x_cam / z``
(OpenCV axes); observations are undistorted pixels. Camera positions after bundle adjustment
are defined up to one global scale (the gauge fixes one camera per component, not the scale).
"""

from __future__ import annotations

from .bundle import LOSSES, BundleOptions, BundleResult, bundle_adjust, gauge_cameras
from .mapper import SfmResult, bundle_adjust_reconstruction
from .positioning import Positioning, PositioningOptions, global_positioning
from .resection import Resection, anchored_cameras, resect_cameras
from .selfcheck import CheckOptions, PairEvidence, SelfCheck, check_reconstruction
from .tracks import Tracks, build_tracks
from .triangulation import (
    REASONS,
    Triangulation,
    project,
    reprojection_errors,
    triangulate_tracks,
    undistort_keypoints,
)

__all__ = [
    "LOSSES",
    "REASONS",
    "BundleOptions",
    "BundleResult",
    "CheckOptions",
    "PairEvidence",
    "Positioning",
    "PositioningOptions",
    "Resection",
    "SelfCheck",
    "SfmResult",
    "Tracks",
    "Triangulation",
    "anchored_cameras",
    "build_tracks",
    "bundle_adjust",
    "bundle_adjust_reconstruction",
    "check_reconstruction",
    "gauge_cameras",
    "global_positioning",
    "project",
    "reprojection_errors",
    "resect_cameras",
    "triangulate_tracks",
    "undistort_keypoints",
]

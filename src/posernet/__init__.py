"""posernet: refine relative camera poses with matched object detections (PoserNet, ECCV 2022),
then average them into absolute camera poses.

The public API is re-exported here; see the README for a tour.
"""

from . import geometry, sync
from .graph import (
    GraphBatch,
    GraphValidationError,
    ViewGraph,
    denormalize_boxes,
    load_graphs,
    node_attributes,
    normalize_boxes,
    save_graphs,
)
from .metrics import (
    absolute_pose_errors,
    per_graph_mean,
    relative_pose_errors,
    threshold_row,
    umeyama_alignment,
)
from .nn import PoserConv, PoserNet, posernet_loss

__version__ = "0.1.0"

__all__ = [
    "GraphBatch",
    "GraphValidationError",
    "PoserConv",
    "PoserNet",
    "ViewGraph",
    "__version__",
    "absolute_pose_errors",
    "denormalize_boxes",
    "geometry",
    "load_graphs",
    "node_attributes",
    "normalize_boxes",
    "per_graph_mean",
    "posernet_loss",
    "relative_pose_errors",
    "save_graphs",
    "sync",
    "threshold_row",
    "umeyama_alignment",
]

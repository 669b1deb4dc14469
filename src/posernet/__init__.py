"""posernet: refine relative camera poses with matched object detections (PoserNet, ECCV 2022),
then average them into absolute camera poses.

The public API is re-exported here; see the README and docs/ for a tour.
"""

# first, before torch, OpenCV and SciPy load: Ctrl-C while a posernet command starts up
from . import startup  # noqa: F401

# isort: split
from . import geometry, sync
from .checkpoints import CheckpointError, read_checkpoint
from .geometry import umeyama_alignment
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
)
from .nn import PoserConv, PoserNet, posernet_loss

__version__ = "0.1.0"

# The image front end (OpenCV, optional learned matchers) loads on first use, so that importing
# the network or the geometry does not pay for it.
_LAZY = {"frontend": ".frontend", "reconstruct": ".reconstruct", "sfm": ".sfm"}


def __getattr__(name: str) -> object:
    if name in _LAZY:
        import importlib

        return importlib.import_module(_LAZY[name], __name__)
    raise AttributeError(f"module 'posernet' has no attribute {name!r}")

__all__ = [
    "CheckpointError",
    "GraphBatch",
    "GraphValidationError",
    "PoserConv",
    "PoserNet",
    "ViewGraph",
    "__version__",
    "absolute_pose_errors",
    "denormalize_boxes",
    "frontend",
    "geometry",
    "load_graphs",
    "node_attributes",
    "normalize_boxes",
    "per_graph_mean",
    "posernet_loss",
    "read_checkpoint",
    "reconstruct",
    "relative_pose_errors",
    "save_graphs",
    "sfm",
    "sync",
    "threshold_row",
    "umeyama_alignment",
]

"""Simulator of the paper's 7-Scenes data path: scenes, handheld sequences, objectness boxes,
keypoint and box matching, OpenCV 5-point initial poses, and view graph sampling.

Entry points:

* :func:`generate_dataset` writes a dataset directory (what ``posernet-make-data`` runs);
* :func:`simulate_graphs` returns graphs of one scene/split/size in memory;
* :class:`SceneWorld` exposes the simulated scene, images and image pairs (for tests).

Modules: ``config`` (options, presets), ``scenes``, ``trajectories``, ``camera``,
``visibility``, ``detections``, ``matching``, ``relpose``, ``world``, ``sampling``, ``chunks``,
``generate``, ``summary``.
"""

from ..writer import DatasetExistsError, GenerationError, export_json
from .chunks import Chunk, plan_chunks, simulate_chunk, simulate_graphs
from .config import (
    ConfigError,
    DatasetOptions,
    available_presets,
    load_preset,
    options_from_dict,
    resolve_options,
)
from .generate import generate_dataset
from .sampling import SamplingError
from .scenes import SCENE_PRESETS, Scene, build_scene
from .summary import PAPER_INITIAL, format_summary
from .world import Frame, PairResult, SceneWorld

__all__ = [
    "PAPER_INITIAL",
    "SCENE_PRESETS",
    "Chunk",
    "ConfigError",
    "DatasetExistsError",
    "DatasetOptions",
    "Frame",
    "GenerationError",
    "PairResult",
    "SamplingError",
    "Scene",
    "SceneWorld",
    "available_presets",
    "build_scene",
    "export_json",
    "format_summary",
    "generate_dataset",
    "load_preset",
    "options_from_dict",
    "plan_chunks",
    "resolve_options",
    "simulate_chunk",
    "simulate_graphs",
]

"""Options of the synthetic 7-Scenes-like dataset: dataclasses, presets and validation.

The presets live in ``posernet/conf/dataset/<name>.yaml`` (the Hydra config group of
``posernet-make-data``) and are read here too, so Hydra and plain Python see the same numbers.
A preset file only lists what differs from the dataclass defaults below. Every check raises
:class:`ConfigError` naming the offending field (``dataset.small.train`` ...).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from ...conf import config_root
from ...frontend.relpose import PoseOptions
from ...options import ConfigValueError, check_options
from ..layout import LARGE_SCENES, SCENES, SIZES, SPLITS

if TYPE_CHECKING:
    from ...conf import Traversable

__all__ = [
    "CameraOptions",
    "ConfigError",
    "DatasetOptions",
    "DetectorOptions",
    "GraphCounts",
    "KeypointOptions",
    "MatchOptions",
    "PoseOptions",
    "SamplingOptions",
    "SequenceOptions",
    "available_presets",
    "load_preset",
    "options_from_dict",
    "resolve_options",
]

#: a dataset option is unknown or out of range (the message names the field): the one config
#: error type of every posernet option, :class:`posernet.options.ConfigValueError`
ConfigError = ConfigValueError


@dataclass
class GraphCounts:
    """How many graphs of one size per scene and split, and how many images each has."""

    graph_size: int = 8
    train: int = 2000
    val: int = 200
    test: int = 1000
    # Scenes with graphs of this size; ``None`` = every scene of the dataset.
    scenes: list[str] | None = None


@dataclass
class SequenceOptions:
    """Handheld sequences (7-Scenes: 1000 frames at 30 Hz per sequence, 500 for stairs)."""

    frames_per_sequence: int = 250  # simulated frames of a 1000-frame sequence (sub-sampling)
    duration_s: float = 33.0  # capture time of a 1000-frame sequence
    speed: float = 0.18  # mean camera speed (m/s), slow handheld motion
    waypoint_s: float = 2.5  # time between trajectory waypoints (s)
    shake_m: float = 0.008  # hand-shake amplitude (m)
    shake_deg: float = 0.8  # hand-shake rotation amplitude (deg)
    val_fraction: float = 0.2  # tail of every training sequence kept for validation
    # Cap on sequences per split and scene (``None``: the 7-Scenes numbers); for tiny presets.
    max_sequences: int | None = None


@dataclass
class CameraOptions:
    """Kinect v1 RGB camera of 7-Scenes."""

    width: int = 640
    height: int = 480
    focal: float = 585.0
    k1: float = 0.0  # radial distortion of the simulated images (not corrected by 5-point)
    near: float = 0.1
    far: float = 8.0


@dataclass
class DetectorOptions:
    """Objectness detector (OLN-like): box noise, misses, part boxes and false positives."""

    box_jitter: float = 0.08  # std of each box edge, as a fraction of the box side
    miss_rate: float = 0.1  # probability of missing a visible object
    part_rate: float = 0.15  # probability that a box covers only a part of its object
    false_positives: float = 4.0  # mean number of spurious boxes per image (Poisson)
    min_visible: float = 0.3  # fraction of an object's surface that must be unoccluded
    min_box_px: float = 10.0  # smaller boxes are not detected
    max_boxes: int = 50  # keep the best-scoring boxes (paper: 50)
    max_area: float = 0.25  # drop boxes larger than this fraction of the image (paper: 25%)


@dataclass
class KeypointOptions:
    """SuperPoint/SuperGlue-like keypoints on object surfaces and their matches."""

    density: float = 700.0  # keypoints per m^2 on textured object surfaces
    furniture_density: float = 150.0  # per m^2 on tables and shelves
    background_density: float = 25.0  # per m^2 on floor and walls
    max_per_object: int = 400
    detect_prob: float = 0.8  # repeatability of a visible keypoint in one image
    match_prob: float = 0.9  # probability that a keypoint seen in both images is matched
    max_view_angle: float = 50.0  # (deg) matching fades with the change of viewing direction
    max_scale_change: float = 2.5  # no match beyond this ratio of distances
    pixel_noise: float = 1.0  # std of keypoint positions (px)
    outlier_rate: float = 0.15  # fraction of matches that are wrong
    twin_fraction: float = 0.0  # fraction of objects that are copies of another (repetition)
    confusion: float = 0.0  # chance that a twin's keypoints match its look-alike instead


@dataclass
class MatchOptions:
    """Box matching rules of the paper (supplementary, "ROIs matching")."""

    min_keypoints: int = 15  # a box pair needs this many shared matched keypoints
    min_span: float = 0.3  # ... spanning this fraction of each box's area
    min_boxes: int = 5  # two images are connected with this many matched boxes
    wrong_match_rate: float = 0.05  # matched box pairs re-assigned to a wrong box
    # KP 5-point input: keypoints inside a matched box pair ("matched") or inside any box of
    # each image ("boxes")
    kp_source: str = "matched"
    # With ``kp_source: matched``: only the keypoints of the ``kp_boxes`` matched box pairs that
    # share the most matches feed the KP 5-point (0: all matched pairs). Real SuperGlue matches
    # concentrate on the one or two most textured objects (a poster, a screen, a chessboard):
    # a small, clustered point set on few faces, which leaves 5-point ill-conditioned.
    kp_boxes: int = 0


@dataclass
class SamplingOptions:
    """How small graphs pick their images (large graphs are uniform)."""

    # Probability that a candidate image is taken close in time to an image already in the
    # graph (a panning handheld camera: short baselines) instead of anywhere in the split.
    locality: float = 0.0
    window_s: float = 2.0  # "close in time": within this many seconds of sequence


@dataclass
class DatasetOptions:
    """Everything that defines a synthetic dataset (besides the seed)."""

    name: str = "custom"
    scenes: list[str] = field(default_factory=lambda: list(SCENES))
    small: GraphCounts = field(default_factory=GraphCounts)
    large: GraphCounts = field(
        default_factory=lambda: GraphCounts(
            graph_size=125, train=1, val=0, test=1,
            scenes=list(LARGE_SCENES),
        )
    )  # fmt: skip
    sequences: SequenceOptions = field(default_factory=SequenceOptions)
    camera: CameraOptions = field(default_factory=CameraOptions)
    detector: DetectorOptions = field(default_factory=DetectorOptions)
    keypoints: KeypointOptions = field(default_factory=KeypointOptions)
    matching: MatchOptions = field(default_factory=MatchOptions)
    pose: PoseOptions = field(default_factory=PoseOptions)
    sampling: SamplingOptions = field(default_factory=SamplingOptions)
    # Sampling gives up on a small graph after this many rejected candidate images per node.
    max_tries_per_node: int = 200

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (JSON/YAML ready)."""
        return dataclasses.asdict(self)

    def scenes_for(self, size: str) -> list[str]:
        """Scenes that get graphs of ``size`` (``small``/``large``)."""
        counts: GraphCounts = getattr(self, size)
        if counts.scenes is None:
            return list(self.scenes)
        return [s for s in counts.scenes if s in self.scenes]

    def validate(self) -> DatasetOptions:
        """Check ranges; raise :class:`ConfigError` naming the field. Returns ``self``."""
        _validate(self)
        return self


# --------------------------------------------------------------------------- validation


def _fail(path: str, msg: str) -> None:
    raise ConfigError(f"invalid dataset option {path}: {msg}")


def _check_int(path: str, v: Any, lo: int | None = None, hi: int | None = None) -> None:
    if isinstance(v, bool) or not isinstance(v, int):
        _fail(path, f"must be an integer, got {v!r}")
    if lo is not None and v < lo:
        _fail(path, f"must be >= {lo}, got {v}")
    if hi is not None and v > hi:
        _fail(path, f"must be <= {hi}, got {v}")


def _check_float(
    path: str, v: Any, lo: float | None = None, hi: float | None = None, lo_open: bool = False
) -> None:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        _fail(path, f"must be a finite number, got {v!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        _fail(path, f"must be {'>' if lo_open else '>='} {lo}, got {v}")
    if hi is not None and v > hi:
        _fail(path, f"must be <= {hi}, got {v}")


def _check_scenes(path: str, scenes: Any, allow_empty: bool = False) -> None:
    if not isinstance(scenes, list | tuple) or (not scenes and not allow_empty):
        _fail(path, f"must be a non-empty list of scene names from {list(SCENES)}")
    for s in scenes:
        if s not in SCENES:
            _fail(path, f"unknown scene {s!r}; choose from {list(SCENES)}")
    if len(set(scenes)) != len(scenes):
        _fail(path, f"lists a scene twice: {list(scenes)}")


def _validate(o: DatasetOptions) -> None:
    p = "dataset"
    if not isinstance(o.name, str) or not o.name:
        _fail(f"{p}.name", "must be a non-empty string")
    _check_scenes(f"{p}.scenes", o.scenes)
    for size in SIZES:
        c: GraphCounts = getattr(o, size)
        _check_int(f"{p}.{size}.graph_size", c.graph_size, lo=2, hi=1000)
        for split in SPLITS:
            _check_int(f"{p}.{size}.{split}", getattr(c, split), lo=0)
        if c.scenes is not None:
            _check_scenes(f"{p}.{size}.scenes", c.scenes, allow_empty=True)
            missing = [s for s in c.scenes if s not in o.scenes]
            if missing:
                _fail(f"{p}.{size}.scenes", f"{missing} not in dataset.scenes {list(o.scenes)}")
    if o.small.graph_size > 64:
        _fail(
            f"{p}.small.graph_size",
            f"small graphs are sampled connected; use at most 64 "
            f"images (got {o.small.graph_size}); use dataset.large for big graphs",
        )
    s = o.sequences
    _check_int(f"{p}.sequences.frames_per_sequence", s.frames_per_sequence, lo=10, hi=100000)
    _check_float(f"{p}.sequences.duration_s", s.duration_s, lo=1.0)
    _check_float(f"{p}.sequences.speed", s.speed, lo=0.0, hi=3.0, lo_open=True)
    _check_float(f"{p}.sequences.waypoint_s", s.waypoint_s, lo=0.1)
    _check_float(f"{p}.sequences.shake_m", s.shake_m, lo=0.0, hi=0.2)
    _check_float(f"{p}.sequences.shake_deg", s.shake_deg, lo=0.0, hi=10.0)
    _check_float(f"{p}.sequences.val_fraction", s.val_fraction, lo=0.0, hi=0.9)
    if s.max_sequences is not None:
        _check_int(f"{p}.sequences.max_sequences", s.max_sequences, lo=1)
    c = o.camera
    _check_int(f"{p}.camera.width", c.width, lo=32, hi=10000)
    _check_int(f"{p}.camera.height", c.height, lo=32, hi=10000)
    _check_float(f"{p}.camera.focal", c.focal, lo=1.0)
    _check_float(f"{p}.camera.k1", c.k1, lo=-0.3, hi=0.3)
    _check_float(f"{p}.camera.near", c.near, lo=0.0, lo_open=True)
    _check_float(f"{p}.camera.far", c.far, lo=c.near, lo_open=True)
    d = o.detector
    _check_float(f"{p}.detector.box_jitter", d.box_jitter, lo=0.0, hi=1.0)
    _check_float(f"{p}.detector.miss_rate", d.miss_rate, lo=0.0, hi=1.0)
    _check_float(f"{p}.detector.part_rate", d.part_rate, lo=0.0, hi=1.0)
    _check_float(f"{p}.detector.false_positives", d.false_positives, lo=0.0, hi=100.0)
    _check_float(f"{p}.detector.min_visible", d.min_visible, lo=0.0, hi=1.0)
    _check_float(f"{p}.detector.min_box_px", d.min_box_px, lo=0.0)
    _check_int(f"{p}.detector.max_boxes", d.max_boxes, lo=1, hi=1000)
    _check_float(f"{p}.detector.max_area", d.max_area, lo=0.0, hi=1.0, lo_open=True)
    k = o.keypoints
    _check_float(f"{p}.keypoints.density", k.density, lo=0.0)
    _check_float(f"{p}.keypoints.furniture_density", k.furniture_density, lo=0.0)
    _check_float(f"{p}.keypoints.background_density", k.background_density, lo=0.0)
    _check_int(f"{p}.keypoints.max_per_object", k.max_per_object, lo=1)
    _check_float(f"{p}.keypoints.detect_prob", k.detect_prob, lo=0.0, hi=1.0)
    _check_float(f"{p}.keypoints.match_prob", k.match_prob, lo=0.0, hi=1.0)
    _check_float(f"{p}.keypoints.max_view_angle", k.max_view_angle, lo=0.0, hi=180.0, lo_open=True)
    _check_float(f"{p}.keypoints.max_scale_change", k.max_scale_change, lo=1.0)
    _check_float(f"{p}.keypoints.pixel_noise", k.pixel_noise, lo=0.0, hi=100.0)
    _check_float(f"{p}.keypoints.outlier_rate", k.outlier_rate, lo=0.0, hi=1.0)
    _check_float(f"{p}.keypoints.twin_fraction", k.twin_fraction, lo=0.0, hi=1.0)
    _check_float(f"{p}.keypoints.confusion", k.confusion, lo=0.0, hi=1.0)
    m = o.matching
    _check_int(f"{p}.matching.min_keypoints", m.min_keypoints, lo=1)
    _check_float(f"{p}.matching.min_span", m.min_span, lo=0.0, hi=1.0)
    _check_int(f"{p}.matching.min_boxes", m.min_boxes, lo=1)
    if m.kp_source not in ("matched", "boxes"):
        _fail(f"{p}.matching.kp_source", f"must be 'matched' or 'boxes', got {m.kp_source!r}")
    _check_float(f"{p}.matching.wrong_match_rate", m.wrong_match_rate, lo=0.0, hi=1.0)
    _check_int(f"{p}.matching.kp_boxes", m.kp_boxes, lo=0)
    check_options(o.pose, f"{p}.pose")  # the two-view options declare their own rules
    _check_float(f"{p}.sampling.locality", o.sampling.locality, lo=0.0, hi=1.0)
    _check_float(f"{p}.sampling.window_s", o.sampling.window_s, lo=0.0)
    _check_int(f"{p}.max_tries_per_node", o.max_tries_per_node, lo=1)


# --------------------------------------------------------------------------- from dicts


def _build(cls: type, data: Any, path: str) -> Any:
    """Dataclass ``cls`` from a mapping, recursing into nested dataclasses; unknown keys fail."""
    if data is None:
        return cls()
    if not isinstance(data, Mapping):
        _fail(path, f"must be a mapping of options, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        _fail(f"{path}.{unknown[0]}", f"unknown option (known: {sorted(fields)})")
    defaults = cls()
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        current = getattr(defaults, name)
        if dataclasses.is_dataclass(current):
            # Nested group: merge over that group's defaults in *this* class (e.g. ``large``).
            base = dataclasses.asdict(current)
            if value is not None and not isinstance(value, Mapping):
                _fail(f"{path}.{name}", f"must be a mapping, got {type(value).__name__}")
            base.update(dict(value or {}))
            kwargs[name] = _build(type(current), base, f"{path}.{name}")
        elif isinstance(value, list | tuple):
            kwargs[name] = list(value)
        else:
            kwargs[name] = value
    try:
        return cls(**kwargs)
    except ConfigValueError as exc:  # a dataclass checking its own options: name the field
        label = f"{cls.__name__}."
        msg = str(exc)
        raise ConfigError(f"{path}.{msg[len(label):]}" if msg.startswith(label) else msg) \
            from None


def options_from_dict(data: Mapping[str, Any] | None) -> DatasetOptions:
    """:class:`DatasetOptions` from a (possibly partial) nested mapping, validated."""
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(data, DictConfig):
            data = OmegaConf.to_container(data, resolve=True)  # type: ignore[assignment]
    except ImportError:  # pragma: no cover - omegaconf ships with hydra-core
        pass
    return _build(DatasetOptions, data, "dataset").validate()


def _preset_dir() -> Traversable:
    # a resource folder of the package (or $POSERNET_CONFIG_DIR), as Hydra's dataset group
    return config_root() / "dataset"


def available_presets() -> list[str]:
    """Names of the preset files in ``posernet/conf/dataset/``."""
    d = _preset_dir()
    if not d.is_dir():
        return []
    return sorted(p.name[: -len(".yaml")] for p in d.iterdir()
                  if p.name.endswith(".yaml") and p.is_file())


def load_preset(name: str) -> DatasetOptions:
    """Options of preset ``name`` (``paper``, ``easy``, ``demo``, ``tiny``)."""
    bad = not isinstance(name, str) or not name or "/" in name or "\\" in name
    resource = None if bad else _preset_dir() / f"{name}.yaml"
    if resource is None or not resource.is_file():
        raise ConfigError(
            f"unknown dataset preset {name!r}; available: {available_presets()} "
            f"(looked in {_preset_dir()})"
        )
    from omegaconf import OmegaConf

    text = resource.read_text(encoding="utf-8")
    data = OmegaConf.to_container(OmegaConf.create(text), resolve=True)
    opts = options_from_dict(data)  # type: ignore[arg-type]
    return opts


def resolve_options(spec: DatasetOptions | str | Mapping[str, Any]) -> DatasetOptions:
    """Accept a preset name, a mapping (e.g. Hydra's ``cfg.dataset``) or ready options."""
    if isinstance(spec, DatasetOptions):
        return spec.validate()
    if isinstance(spec, str):
        return load_preset(spec)
    return options_from_dict(spec)

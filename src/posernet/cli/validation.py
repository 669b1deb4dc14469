"""One config check for every ``posernet-*`` command, run before any work or output.

:func:`check_config` takes a command's composed config and checks, in this order:

1. every plain value of the command's top-level keys and of its groups (``model``, ``data``,
   ``trainer``, ``sync``, the front end's ``proposals``/``matcher``/``box_matching``/
   ``relpose``, the demo's ``images``) against a small schema: type, range or choices, and that
   a required value (``???``) was given. Groups backed by a dataclass or a constructor
   (``bundle``, ``verify``, ``pairs``, ``relpose``, ``box_matching``, ``model.net``) take their
   keys and types from it (:func:`typed`), and groups Hydra builds from a ``_target_``
   (``sync``, ``matcher``, ``proposals``, ``data``) from that target's arguments or options
   dataclass (:func:`targeted`), so the schema cannot drift from the code; only the ranges
   and choices are written here;
2. what a group's own constructor checks across fields (the sync backend: its scale policy,
   gtsam installed; the demo's synthetic dataset options), by building it early;
3. the machine: ``device=cuda`` (``trainer.accelerator=gpu``) needs CUDA;
4. the outputs: every folder or file the command will write can be written (nothing is
   created: a probe file in the nearest existing folder is removed at once).

Any failure is one :class:`ConfigValueError` whose message names the key, the value and what
is expected: ``model.net.depth: 'abc' is not an integer >= 1``. Keys absent from a config (a
group without that option) are skipped; the input files themselves are read, and reported, by
the loaders.
"""

from __future__ import annotations

import math
import os
import re
import tempfile
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["COMMANDS", "ConfigValueError", "check_config", "writable_dir", "writable_file"]


class ConfigValueError(ValueError):
    """A config value of the wrong type, out of range, not a valid choice or not usable here."""


# --------------------------------------------------------------------------- rules


@dataclass(frozen=True)
class Rule:
    """What one key accepts: ``expected`` says it in words, ``test`` checks a value."""

    expected: str
    test: Callable[[Any], bool]
    null: bool = False  # None accepted

    def ok(self, value: Any) -> bool:
        return (value is None and self.null) or (value is not None and self.test(value))

    def describe(self) -> str:
        return f"{self.expected} or null" if self.null else self.expected


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return (isinstance(v, int | float) and not isinstance(v, bool)) and math.isfinite(v)


def _bounds(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> str:
    if lo is not None and hi is not None:
        return f" in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if lo is not None:
        return f" {'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        return f" {'<' if hi_open else '<='} {hi:g}"
    return ""


def _within(v: float, lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> bool:
    if lo is not None and (v <= lo if lo_open else v < lo):
        return False
    return not (hi is not None and (v >= hi if hi_open else v > hi))


def integer(lo: int | None = None, hi: int | None = None, *, null: bool = False) -> Rule:
    return Rule(f"an integer{_bounds(lo, hi, False, False)}",
                lambda v: _is_int(v) and _within(v, lo, hi, False, False), null)


def number(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
           hi_open: bool = False, null: bool = False) -> Rule:
    return Rule(f"a number{_bounds(lo, hi, lo_open, hi_open)}",
                lambda v: _is_number(v) and _within(v, lo, hi, lo_open, hi_open), null)


def positive(*, null: bool = False) -> Rule:
    return number(0, lo_open=True, null=null)


def boolean(*, null: bool = False) -> Rule:
    return Rule("true or false", lambda v: isinstance(v, bool), null)


def choice(*options: str, null: bool = False) -> Rule:
    return Rule(f"one of {', '.join(options)}", lambda v: isinstance(v, str) and v in options,
                null)


def auto_or_bool() -> Rule:
    return Rule("auto, true or false",
                lambda v: isinstance(v, bool) or (isinstance(v, str) and v == "auto"), False)


def text(*, null: bool = False) -> Rule:
    return Rule("a string", lambda v: isinstance(v, str) and v != "", null)


def path(*, null: bool = False) -> Rule:
    """A file or folder name (a number is a valid name too: ``out_dir=2024``)."""
    return Rule("a path", lambda v: (isinstance(v, str) and v != "") or _is_int(v), null)


def paths() -> Rule:
    """A path or a non-empty list of paths (e.g. several datasets to train on)."""
    one = path()
    return Rule("a path or a list of paths",
                lambda v: one.ok(v) or (isinstance(v, list) and bool(v)
                                        and all(one.ok(x) for x in v)))


def anything(expected: str = "a value") -> Rule:
    """Checked by the command itself (e.g. intrinsics: a string, a list or a file)."""
    return Rule(expected, lambda v: True, True)


def one_of(*rules: Rule, expected: str | None = None) -> Rule:
    """A value any of ``rules`` accepts."""
    null = any(r.null for r in rules)
    return Rule(expected or " or ".join(r.expected for r in rules),
                lambda v: any(r.ok(v) for r in rules), null)


def typed(owner: Any, prefix: str = "", **specific: Rule) -> dict[str, Rule]:
    """A rule for every argument of ``owner`` (a dataclass or a class's constructor), from its
    type annotation (``int``, ``float``, ``bool``, ``str``, ``... | None``); ``specific`` rules
    (ranges, choices; keys without ``prefix``) take precedence. The schema thus follows the
    code: an option added there is checked here (by type at least), and the owner's own range
    checks run when the command builds it."""
    import dataclasses
    import inspect
    import typing

    if dataclasses.is_dataclass(owner):
        names = [f.name for f in dataclasses.fields(owner)]
        hints = typing.get_type_hints(owner)
    else:
        names = _parameters(owner)
        hints = typing.get_type_hints(owner if inspect.isfunction(owner) else owner.__init__)
    out: dict[str, Rule] = {}
    for name in names:
        if name in specific:
            out[prefix + name] = specific[name]
            continue
        hint = hints.get(name, Any)
        args = set(typing.get_args(hint)) if typing.get_origin(hint) in (
            typing.Union, __import__("types").UnionType) else {hint}
        null = type(None) in args
        args.discard(type(None))
        base = args.pop() if len(args) == 1 else None
        out[prefix + name] = ({bool: boolean, int: integer, float: number, str: text}
                              .get(base, lambda null=False: anything())(null=null))
    unknown = set(specific) - set(names)
    if unknown:
        raise TypeError(f"typed({getattr(owner, '__name__', owner)}): no such argument(s) "
                        f"{sorted(unknown)}")
    return out


def _parameters(owner: Any) -> list[str]:
    """Named arguments of a function or a class's constructor (not ``self``, ``*a``, ``**k``)."""
    import inspect

    return [n for n, p in inspect.signature(owner).parameters.items()
            if n != "self" and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]


def _takes_any_keyword(owner: Any) -> bool:
    import inspect

    return any(p.kind == p.VAR_KEYWORD for p in inspect.signature(owner).parameters.values())


def targeted(group: str, ranges: Schema) -> Callable[[Any], Schema]:
    """Schema of a group that Hydra builds from its ``_target_`` (sync backends, matchers,
    proposals, the datamodule): a rule for every argument of that target (:func:`typed`, so
    the keys and types follow the code), the ranges and choices of ``ranges`` where they
    apply (every one for a target taking ``**kwargs``), and ``_target_`` / ``name`` (a label).
    A target with an ``Options`` dataclass (the sync backends) is checked against its fields.
    Without a target it can import, the group gets ``ranges`` as they are (building it then
    reports the bad target)."""

    def schema(cfg: Any) -> Schema:
        from hydra.utils import get_object

        target = None if cfg is None else _value(cfg, f"{group}._target_")
        try:
            owner = get_object(target) if isinstance(target, str) else None
        except Exception:  # a bad target: instantiating it says so
            owner = None
        base: Schema = {"_target_": text(), "name": text()}
        if owner is None:
            return {**base, **ranges}
        import dataclasses

        options = getattr(owner, "Options", None)  # a sync backend's options dataclass
        if dataclasses.is_dataclass(options):
            owner = options
        names = ({f.name for f in dataclasses.fields(owner)} if dataclasses.is_dataclass(owner)
                 else set(_parameters(owner)))
        extra = ({k: r for k, r in ranges.items() if k not in names}
                 if not dataclasses.is_dataclass(owner) and _takes_any_keyword(owner) else {})
        return {**base, **extra, **typed(owner, **{k: r for k, r in ranges.items()
                                                     if k in names})}

    schema.ranges = ranges  # type: ignore[attr-defined]
    return schema


DEVICE = Rule("one of cpu, cuda, cuda:N, auto",
              lambda v: isinstance(v, str) and bool(re.fullmatch(r"cpu|cuda|cuda:\d+|auto", v)))
THREADS = integer(1, null=True)
DIGITS = integer(0, 12)
SEED = integer(0)
ESTIMATE = choice("kp", "bb")
#: initial poses read from graph files (``.json``: also the free keypoint 5-point; null: the
#: stored edge_pose)
ESTIMATE_IN = choice("kp", "bb", "free", "gt", null=True)
SIZE = choice("small", "large")
INTRINSICS = "FX,FY,CX,CY, [FX,FY,CX,CY], a JSON / 3x3 text file, or auto"


# --------------------------------------------------------------------------- schema

Schema = Mapping[str, Rule]


def _model(cfg: Any) -> Schema:
    """``model``: the network's arguments from its constructor (:func:`typed`), the training
    sections' values here."""
    from ..nn import PoserNet

    return {**typed(PoserNet, "net.", depth=integer(1), node_hidden=integer(1),
                    edge_hidden=integer(0), mlp_hidden=integer(1), mlp_layers=integer(1),
                    node_in=integer(1), head_hidden=integer(1)),
            **MODEL_TRAINING}


#: the training sections of ``model`` (loss, optimizer, scheduler)
MODEL_TRAINING: Schema = {
    "loss.alpha": number(0), "loss.end_to_end": boolean(),
    "loss.raw": number(0), "loss.confidence": number(0), "loss.correction": number(0),
    "loss.harm": number(0), "loss.harm_scale": number(0),
    "loss.relative_weight": number(0), "loss.absolute_weight": number(0),
    "loss.position_weight": number(0), "optimizer.lr": positive(),
    "optimizer.weight_decay": number(0), "scheduler.patience": integer(0),
    "scheduler.factor": number(0, 1, lo_open=True, hi_open=True), "scheduler.min_lr": number(0),
}

#: ``data``: the datamodule's arguments (:func:`targeted`), with these ranges and choices
DATA = targeted("data", {
    "root": paths(), "estimate": ESTIMATE, "size": SIZE, "batch_size": integer(1),
    "eval_batch_size": integer(1, null=True), "num_workers": integer(0),
    "test_size": choice("small", "large", null=True),
    "val_size": choice("small", "large", null=True), "seed": SEED,
    "init_mix": Rule("a mapping of initial-pose sources (kp, bb, gt, recorrupt) to "
                     "weights >= 0, not all 0", lambda v: _mixture_ok(v), True),
    "gt_noise_deg": number(0), "recorrupt_deg": number(0), "mix_edge_fraction": number(0, 1),
})


def _mixture_ok(v: Any) -> bool:
    from ..data.mixture import check_mixture

    try:
        check_mixture(v)
    except (ValueError, TypeError):
        return False
    return True

#: the Lightning Trainer arguments of posernet/conf/trainer/*.yaml (others pass through unchecked)
TRAINER: Schema = {
    "accelerator": choice("auto", "cpu", "gpu", "cuda", "mps"),
    "devices": one_of(Rule("", lambda v: _is_int(v) and (v == -1 or v >= 1)), choice("auto"),
                      Rule("a list of integers", lambda v: isinstance(v, list) and bool(v)
                           and all(_is_int(x) for x in v)),
                      expected="an integer >= 1 (or -1: all), a list of integers or auto"),
    "precision": one_of(choice("64", "32", "16", "bf16", "64-true", "32-true", "16-true",
                               "bf16-true", "16-mixed", "bf16-mixed"),
                        Rule("", lambda v: _is_int(v) and v in (16, 32, 64)),
                        expected="one of 64, 32, 16, bf16, 64-true, 32-true, 16-true, bf16-true, "
                                 "16-mixed, bf16-mixed"),
    "strategy": text(),
    "max_epochs": Rule("an integer >= 1 (or -1: no limit)",
                       lambda v: _is_int(v) and (v == -1 or v >= 1), True),
    "min_epochs": integer(0, null=True),
    "max_steps": integer(-1), "fast_dev_run": one_of(boolean(), integer(0)),
    "gradient_clip_val": number(0, null=True),
    "gradient_clip_algorithm": choice("norm", "value", null=True),
    "deterministic": one_of(boolean(null=True), choice("warn")),
    "log_every_n_steps": integer(1), "check_val_every_n_epoch": integer(1, null=True),
    "num_sanity_val_steps": integer(-1), "enable_progress_bar": boolean(),
    "enable_model_summary": boolean(), "enable_checkpointing": boolean(),
    "default_root_dir": path(null=True),
}

#: ``sync``: the backend's arguments (:func:`targeted`), with these ranges and choices;
#: cross-field rules (the scale policies a backend supports, p_min <= p_max) are the backend's
#: own, checked by building it
SYNC = targeted("sync", {
    "scale": choice("unit", "given", "oracle", "free"),
    "disconnected": choice("components", "error"),
    "max_iters": integer(1), "tol": positive(), "theta": positive(),
    "solver": choice("auto", "dense", "krylov"), "dense_max_nodes": integer(1),
    "krylov_tol": positive(), "krylov_max_cycles": integer(1), "seed": integer(),
    "refine_iters": integer(0), "translation_iters": integer(1),
    "weight_mode": choice("start", "prior"), "translation": choice("bata", "lud", "linear"),
    "max_rotation_residual_deg": number(0, null=True),
    "max_direction_residual_deg": number(0, null=True), "outlier_mad": positive(),
    "rotation_sigma": positive(), "direction_sigma": positive(), "p_min": integer(3),
    "p_max": integer(3), "lm_tol": positive(), "max_iterations": integer(1),
    "ckpt_path": path(), "device": DEVICE,  # the learned backend's
})

#: ``proposals``: the proposal source's arguments (:func:`targeted`), with these ranges
PROPOSALS = targeted("proposals", {
    "path": path(), "top_k": integer(1, null=True),
    "max_area": number(0, 1, lo_open=True, null=True), "min_size": number(0),
    "strategy": choice("single", "fast", "quality"), "resize": integer(32, null=True),
})


def _pairs(cfg: Any) -> Schema:
    """``pairs``: every option of :class:`posernet.frontend.PairOptions`
    (:func:`typed`), with its ranges."""
    from ..frontend.pairs import PairOptions

    return {**typed(PairOptions,
                  mode=choice("auto", "exhaustive", "sequential", "retrieval"),
                  auto_max=integer(1),
                  k=integer(1),
                  window=integer(1),
                  loop_k=integer(0),
                  words=integer(1),
                  sample=integer(1),
                  seed=SEED, repair_links=integer(0))}

#: ``matcher``: the matcher's arguments (:func:`targeted`), with these ranges and choices
MATCHER = targeted("matcher", {
    "name": choice("auto", "sift", "xfeat", "xfeat+lighterglue"),
    "max_features": integer(1), "ratio": number(0, 1, lo_open=True),
    "contrast_threshold": number(0, 1), "min_features": integer(0), "top_k": integer(1),
    "min_cossim": number(-1, 1), "device": DEVICE,
})


def _box_matching(cfg: Any) -> Schema:
    """``box_matching``: every option of :class:`posernet.frontend.BoxMatchRules`
    (:func:`typed`), with its ranges."""
    from ..frontend.boxmatch import BoxMatchRules

    return {**typed(BoxMatchRules,
                  min_keypoints=integer(1),
                  min_span=number(0, 1),
                  min_boxes=integer(1),
                  one_to_one=boolean())}


def _relpose(cfg: Any) -> Schema:
    """``relpose``: every option of :class:`posernet.frontend.PoseOptions`
    (:func:`typed`), with its ranges."""
    from ..frontend.relpose import PoseOptions

    return {**typed(PoseOptions,
                  method=choice("usac", "ransac"),
                  ransac_prob=number(0, 1, lo_open=True, hi_open=True),
                  kp_threshold=positive(),
                  bb_threshold=positive(),
                  max_iters=integer(1))}

FRONTEND = {"proposals": PROPOSALS, "matcher": MATCHER, "box_matching": _box_matching,
            "relpose": _relpose}


def _verify(cfg: Any) -> Schema:
    """``verify``: every option of :class:`posernet.frontend.VerifyRules`
    (:func:`typed`), with its ranges."""
    from ..frontend.verify import VerifyRules

    return {**typed(VerifyRules,
                  min_inliers=integer(5),
                  min_inlier_ratio=number(0, 1),
                  min_front=number(0, 1),
                  max_rotation_ratio=number(0, 1),
                  min_tri_angle=number(0),
                  static_px=number(0),
                  max_static_ratio=number(0, 1),
                  min_contrast=number(0),
                  contrast_radius=integer(1),
                  min_spread=number(0, 1),
                  max_loop_deg=number(0, 180),
                  max_loop_share=number(0, 1)), "_target_": text()}


def _bundle(cfg: Any) -> Schema:
    """``bundle``: every option of :class:`posernet.sfm.BundleOptions`
    (:func:`typed`), with its ranges."""
    from ..sfm.bundle import BundleOptions

    return {**typed(BundleOptions,
                  loss=choice("cauchy", "huber", "soft_l1", "linear", "arctan"),
                  f_scale=positive(),
                  max_nfev=integer(1),
                  ftol=positive(),
                  xtol=positive(),
                  gtol=positive(),
                  refine_focal=choice("auto", "none", "shared", "per_camera"),
                  gauge=choice("max_degree", "first"),
                  accept_unconverged=boolean(),
                  anneal_factor=number(0),
                  anneal_step=number(1, lo_open=True),
                  robust=choice("lm", "irls", "scipy"),
                  max_outer=integer(1),
                  inner_nfev=integer(1),
                  irls_tol=positive(),
                  max_reproj_px=positive(),
                  initial_reproj_factor=positive(),
                  min_angle_deg=number(0),
                  rounds=integer(1),
                  min_points_per_camera=integer(0),
                  start=choice("auto", "averaged", "positioning", "incremental"),
                  incremental_max_cameras=integer(2), explained_min=number(0, 1)),
            "_target_": text()}


def _check(cfg: Any) -> Schema:
    """``check``: every option of :class:`posernet.sfm.selfcheck.CheckOptions`, with its
    ranges."""
    from ..sfm.selfcheck import CheckOptions

    return {**typed(CheckOptions, max_epipolar_px=positive(), min_inlier_share=number(0, 1),
                    max_rotation_deg=number(0, 180, lo_open=True),
                    max_direction_deg=number(0, 180, lo_open=True),
                    min_agreeing_share=number(0, 1), min_points=integer(0),
                    min_single_pair_inliers=integer(0), min_single_pair_kept=number(0, 1),
                    min_triangulation_deg=number(0, 90, hi_open=True),
                    coincide_ratio=number(0, 1, hi_open=True)),
            "_target_": text()}


def _matcher_configs() -> tuple[str, ...]:
    from . import CONFIG_DIR

    return tuple(sorted(p.stem for p in Path(CONFIG_DIR, "matcher").glob("*.yaml"))) or (
        "auto", "sift", "xfeat", "xfeat_lighterglue")


def _images(cfg: Any) -> Schema:  # posernet-demo's part 1
    from ..data.synthetic.scenes import SCENE_PRESETS

    return {"enabled": boolean(), "scene": choice(*sorted(SCENE_PRESETS)), "seed": SEED,
            "frames": integer(2), "width": integer(16), "height": integer(16),
            "focal": positive(), "matcher": choice(*_matcher_configs()), "refine": boolean()}


@dataclass(frozen=True)
class Command:
    """A command's schema: its top-level keys, its groups, and what it writes."""

    keys: Schema
    groups: Mapping[str, Schema | Callable[[Any], Schema]]
    #: the outputs, ``(key, path, "dir" | "file")``, from the config
    outputs: Callable[[Any], Iterable[tuple[str, Any, str]]]
    #: groups checked only when this function of the config says so
    when: Mapping[str, Callable[[Any], bool]] | None = None
    #: keys naming a device (a CUDA one needs CUDA)
    devices: tuple[str, ...] = ("device",)
    #: checks across fields that a group's own constructor makes (run before any work)
    checks: tuple[Callable[[Any], None], ...] = ()


def _outputs(*pairs: tuple[str, str]) -> Callable[[Any], list[tuple[str, Any, str]]]:
    def get(cfg: Any) -> list[tuple[str, Any, str]]:
        return [(k, v, kind) for k, kind in pairs
                if (v := _value(cfg, k)) not in (_ABSENT, _MISSING, None)]
    return get


def _make_data_outputs(cfg: Any) -> list[tuple[str, Any, str]]:
    out = _value(cfg, "out_dir")
    # default outputs/data/<preset name>: its nearest existing folder is the same one
    return [("out_dir", out if out not in (None, _ABSENT) else "outputs/data", "dir")]


def _sevenscenes(cfg: Any) -> bool:
    return _value(cfg, "source") == "sevenscenes"


def _check_init(cfg: Any) -> None:
    """Resuming a run and fine-tuning from weights are two different starts."""
    init, resume = _value(cfg, "init_from"), _value(cfg, "ckpt_path")
    if init not in (None, _ABSENT) and resume not in (None, _ABSENT):
        raise ConfigValueError(f"init_from={init} and ckpt_path={resume}: give one (ckpt_path "
                               f"resumes a run, init_from starts a new one from its weights)")


def _check_sync(cfg: Any) -> None:
    """Build the backend: its own cross-field rules, before any work."""
    sync = _value(cfg, "sync")
    if not isinstance(sync, dict) or sync.get("name") == "none" or \
            (sync.get("name") is None and sync.get("_target_") is None):
        return
    from .build import backend_from_config

    try:
        backend_from_config(sync)
    except ValueError as exc:
        label = sync.get("name") or sync.get("_target_")
        raise ConfigValueError(f"sync={label}: {_first_line(exc)}") from None


def _check_dataset(cfg: Any) -> None:
    """The demo's synthetic dataset options (their ConfigError names the bad key)."""
    dataset = _value(cfg, "dataset")
    if isinstance(dataset, dict):
        from ..data.synthetic.config import resolve_options

        resolve_options(dataset)


COMMANDS: dict[str, Command] = {
    "train": Command(
        keys={"seed": SEED, "ckpt_path": path(null=True), "init_from": path(null=True),
              "optimized_metric": Rule(
                  "a metric the training logs (val/loss, val/loss_<term>, val/rot_err_deg, "
                  "val/tdir_err_deg, val/abs_rot_err_deg, val/abs_pos_err, their _init)",
                  lambda v: isinstance(v, str) and re.fullmatch(
                      r"(val|train)/(loss(_\w+)?|(abs_)?(rot|tdir)_err_deg(_init)?"
                      r"|abs_pos_err(_init)?)", v) is not None),
              "test_after_training": boolean(),
              "num_threads": THREADS, "out_dir": path()},
        groups={"data": DATA, "model": _model, "trainer": TRAINER, "sync": SYNC},
        outputs=_outputs(("out_dir", "dir")), devices=("trainer.accelerator",),
        checks=(_check_sync, _check_init)),
    "eval": Command(
        keys={"seed": SEED, "ckpt_path": path(), "graphs": path(null=True),
              "estimate": ESTIMATE_IN, "batch_size": integer(1), "device": DEVICE,
              "digits": DIGITS, "num_threads": THREADS, "out_dir": path()},
        groups={"data": DATA, "sync": SYNC}, outputs=_outputs(("out_dir", "dir")),
        checks=(_check_sync,)),
    "refine": Command(
        keys={"input": path(), "split": text(), "size": choice("small", "large", "all"),
              "estimate": ESTIMATE_IN, "strict": boolean(),
              "ckpt_path": path(null=True), "output": path(), "batch_size": integer(1),
              "guard": boolean(), "confidence_weights": boolean(), "check_inputs": boolean(),
              "device": DEVICE, "num_threads": THREADS, "digits": DIGITS, "out_dir": path()},
        groups={"sync": SYNC}, outputs=_outputs(("output", "file")), checks=(_check_sync,)),
    "demo": Command(
        keys={"out_dir": path(), "seed": SEED, "workers": integer(1), "estimate": ESTIMATE,
              "ckpt_path": path(null=True), "train_epochs": integer(1),
              "camera_plots": integer(0), "batch_size": integer(1), "device": DEVICE,
              "num_threads": THREADS, "digits": DIGITS},
        groups={"images": _images, "sync": SYNC}, outputs=_outputs(("out_dir", "dir")),
        checks=(_check_sync, _check_dataset)),
    "reconstruct": Command(
        keys={"images": path(), "pattern": text(null=True), "intrinsics": anything(INTRINSICS),
              "gt_poses": path(null=True), "out_dir": path(), "refine": boolean(), "ba": boolean(),
              "guard": boolean(), "check_inputs": boolean(), "cache": boolean(),
              "boxes": auto_or_bool(), "max_image_size": integer(32, null=True),
              "strict": boolean(), "overwrite": boolean(), "self_check": boolean(),
              "ckpt_path": path(null=True), "estimate": ESTIMATE, "kp_top_pairs": integer(0),
              "edge_rule": choice("verified", "boxes"),
              "seed": SEED, "workers": integer(0), "pictures": integer(0), "device": DEVICE,
              "num_threads": THREADS, "progress": boolean(), "digits": DIGITS},
        groups={**FRONTEND, "verify": _verify, "bundle": _bundle, "sync": SYNC, "pairs": _pairs,
                "check": _check},
        outputs=_outputs(("out_dir", "dir")),
        devices=("device", "matcher.device"), checks=(_check_sync,)),
    "make_data": Command(
        keys={"source": choice("synthetic", "sevenscenes"), "out_dir": path(null=True),
              "preset": text(null=True), "seed": SEED, "workers": integer(1),
              "overwrite": boolean(), "resume": boolean(), "export_json": boolean(),
              "progress": boolean(), "root": path(null=True),
              "scenes": anything("a list of scene folders"), "intrinsics": anything(INTRINSICS),
              "frame_step": integer(1)},
        groups=FRONTEND, when=dict.fromkeys(FRONTEND, _sevenscenes),
        outputs=_make_data_outputs, devices=()),
}


# --------------------------------------------------------------------------- reading values

_ABSENT = object()  # the config has no such key
_MISSING = object()  # a required value (???) that was not given


def _value(cfg: Any, key: str) -> Any:
    """``cfg``'s value at dotted ``key`` as plain Python, or ``_ABSENT`` / ``_MISSING``."""
    from omegaconf import DictConfig, ListConfig, OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    node = cfg
    *parents, leaf = key.split(".")
    for p in parents:
        if not isinstance(node, DictConfig) or p not in node:
            return _ABSENT
        node = node[p]
    if not isinstance(node, DictConfig):
        return _ABSENT
    if leaf not in node:
        return _MISSING if leaf in node.keys() and OmegaConf.is_missing(node, leaf) else _ABSENT
    try:
        value = node[leaf]
        if isinstance(value, DictConfig | ListConfig):
            value = OmegaConf.to_container(value, resolve=True)
    except OmegaConfBaseException as exc:
        if "HydraConfig was not set" in str(exc):  # ${hydra:...} outside a Hydra run
            return _ABSENT
        raise ConfigValueError(f"{key}: cannot resolve its value ({_first_line(exc)})") from None
    return value


def _first_line(exc: BaseException) -> str:
    return next((ln.strip() for ln in str(exc).splitlines() if ln.strip()), type(exc).__name__)


def _check_schema(cfg: Any, schema: Schema, prefix: str = "") -> None:
    for key, rule in schema.items():
        full = prefix + key
        value = _value(cfg, full)
        if value is _ABSENT:
            continue
        if value is _MISSING:
            raise ConfigValueError(f"{full}: a value is required ({full}=<{rule.expected}>)")
        if not rule.ok(value):
            raise ConfigValueError(f"{_source_key(cfg, full)}: {value!r} is not "
                                   f"{rule.describe()}")


def _source_key(cfg: Any, full: str) -> str:
    """The key the user set for ``full``: ``seed`` when ``data.seed`` is ``${seed}``."""
    from omegaconf import OmegaConf

    parent, _, leaf = full.rpartition(".")
    try:
        node = OmegaConf.select(cfg, parent) if parent else cfg
        raw = node._get_node(leaf)._value() if node is not None else None
    except Exception:  # any odd node: keep the name as it is
        return full
    m = re.fullmatch(r"\$\{([\w.]+)\}", raw) if isinstance(raw, str) else None
    return m.group(1) if m else full


def _check_required(cfg: Any, group: str) -> None:
    """Every ``???`` of a group, also options the schema does not list."""
    from omegaconf import OmegaConf

    # full keys ("proposals.path") or relative ones, depending on the OmegaConf version
    missing = sorted(k if k.startswith(f"{group}.") else f"{group}.{k}"
                     for k in OmegaConf.missing_keys(cfg[group]))
    if missing:
        raise ConfigValueError(f"{missing[0]}: a value is required ({missing[0]}=...)")


# --------------------------------------------------------------------------- checks


def check_config(cfg: Any, command: str) -> None:
    """Check the composed config of ``command`` (a key of :data:`COMMANDS`) before any work;
    :class:`ConfigValueError` (one line) for the first problem found."""
    spec = COMMANDS[command]
    # groups first: a top-level value may be one of theirs (eval's estimate: ${data.estimate})
    for group, schema in spec.groups.items():
        if spec.when and group in spec.when and not spec.when[group](cfg):
            continue
        value = _value(cfg, group)
        if value is _ABSENT or value is None:
            continue
        rules = schema(cfg) if callable(schema) else schema
        if not isinstance(value, dict):  # e.g. pairs=exhaustive for pairs.mode=exhaustive
            fits = [k for k, r in rules.items() if not k.startswith("_") and r.ok(value)
                    and r.expected.startswith("one of")]
            hint = (f"did you mean {group}.{fits[0]}={value}?" if fits
                    else f"set its options as {group}.<option>=...")
            raise ConfigValueError(f"{group}: {value!r} is not a group of options; {hint}")
        _check_schema(cfg, rules, group + ".")
        _check_required(cfg, group)
    _check_schema(cfg, spec.keys)
    for check in spec.checks:
        check(cfg)
    for key in spec.devices:
        _check_cuda(key, _value(cfg, key))
    for key, value, kind in spec.outputs(cfg):
        (writable_dir if kind == "dir" else writable_file)(value, key)


def _check_cuda(key: str, value: Any) -> None:
    if not isinstance(value, str) or not (value.startswith("cuda") or value == "gpu"):
        return
    import torch

    if not torch.cuda.is_available():
        raise ConfigValueError(f"{key}={value} but CUDA is not available")


# --------------------------------------------------------------------------- outputs


def _nearest_existing(p: Path) -> Path:
    q = p
    while not os.path.lexists(q) and q.parent != q:
        q = q.parent
    return q


def writable_dir(folder: Any, key: str = "out_dir") -> Path:
    """Check that ``folder`` is (or can be made) a folder that takes files; creates nothing.

    The nearest existing folder on its path gets a probe file, removed at once. Raises
    :class:`ConfigValueError` naming ``key`` and the path as given.
    """
    p = Path(str(folder))
    q = _nearest_existing(p.absolute())
    where = "it" if q == p.absolute() else str(q)
    if not q.is_dir():
        raise ConfigValueError(f"{key}: {str(folder)!r} is not a writable folder "
                               f"({where} is not a folder)")
    try:
        fd, probe = tempfile.mkstemp(prefix=".posernet-write-test-", dir=q)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise ConfigValueError(f"{key}: {str(folder)!r} is not a writable folder "
                               f"(cannot write in {q}: {exc.strerror})") from None
    return p


def writable_file(file: Any, key: str = "output") -> Path:
    """Check that file ``file`` can be written (created or replaced); creates nothing."""
    p = Path(str(file))
    if p.is_dir():
        raise ConfigValueError(f"{key}: {str(file)!r} is not a writable file (it is a folder)")
    try:
        writable_dir(p.parent, key)
    except ConfigValueError as exc:
        detail = str(exc).split(" is not a writable folder ", 1)[-1]
        raise ConfigValueError(f"{key}: {str(file)!r} is not a writable file {detail}") from None
    return p

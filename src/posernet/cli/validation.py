"""One config check for every ``posernet-*`` command, run before any work or output.

:func:`check_config` takes a command's composed config and checks, in this order:

1. every plain value of the command's top-level keys and of its groups (``model``, ``data``,
   ``trainer``, ``sync``, the front end's ``proposals``/``matcher``/``box_matching``/
   ``relpose``, reconstruct's ``pairs``/``verify``/``bundle``/``check``, the demo's
   ``images``): type, range or choices, and that a required value (``???``) was given. A group
   built from a dataclass (``bundle``, ``verify``, ...) or from a constructor with an options
   dataclass (its ``Options``: the sync backends, the matchers, the proposal sources; the
   ``model`` sections: :data:`posernet.lit.posernet_module.SECTION_OPTIONS`) takes each key's
   rule from the field that declares it (:func:`posernet.options.option`), so nothing about those
   options is written here. Still tables here: ``data`` (the datamodule's keys and types from
   its signature, :func:`targeted`, its ranges in :data:`DATA`), the Lightning ``trainer``
   arguments (Lightning's, not the project's: :data:`TRAINER`) and the commands' own
   top-level keys (:data:`COMMANDS`);
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

import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..io import writable_dir, writable_file
from ..options import (
    DEVICE,
    ConfigValueError,
    Rule,
    anything,
    boolean,
    choice,
    field_rules,
    integer,
    is_int,
    number,
    path,
    positive,
    rule_for,
    text,
)

__all__ = ["COMMANDS", "ConfigValueError", "check_config"]


# --------------------------------------------------------------------------- rules


def auto_or_bool() -> Rule:
    return Rule("auto, true or false",
                lambda v: isinstance(v, bool) or (isinstance(v, str) and v == "auto"), False)


def paths() -> Rule:
    """A path or a non-empty list of paths (e.g. several datasets to train on)."""
    one = path()
    return Rule("a path or a list of paths",
                lambda v: one.ok(v) or (isinstance(v, list) and bool(v)
                                        and all(one.ok(x) for x in v)))


def one_of(*rules: Rule, expected: str | None = None) -> Rule:
    """A value any of ``rules`` accepts."""
    null = any(r.null for r in rules)
    return Rule(expected or " or ".join(r.expected for r in rules),
                lambda v: any(r.ok(v) for r in rules), null)


def typed(owner: Any, prefix: str = "", **specific: Rule) -> dict[str, Rule]:
    """A rule for every argument of ``owner`` (a dataclass or a class's constructor): a
    dataclass field's own rule (its :func:`posernet.options.option` metadata, else its type),
    a constructor argument's type annotation (``int``, ``float``, ``bool``, ``str``,
    ``... | None``); ``specific`` rules (ranges, choices; keys without ``prefix``) take
    precedence. The schema thus follows the code: an option added there is checked here."""
    import dataclasses
    import inspect
    import typing

    if dataclasses.is_dataclass(owner):
        own = field_rules(owner)
    else:
        hints = typing.get_type_hints(owner if inspect.isfunction(owner) else owner.__init__)
        own = {n: rule_for(hints.get(n, Any)) for n in _parameters(owner)}
    unknown = set(specific) - set(own)
    if unknown:
        raise TypeError(f"typed({getattr(owner, '__name__', owner)}): no such argument(s) "
                        f"{sorted(unknown)}")
    return {prefix + name: specific.get(name, rule) for name, rule in own.items()}


def _parameters(owner: Any) -> list[str]:
    """Named arguments of a function or a class's constructor (not ``self``, ``*a``, ``**k``)."""
    import inspect

    return [n for n, p in inspect.signature(owner).parameters.items()
            if n != "self" and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]


def _takes_any_keyword(owner: Any) -> bool:
    import inspect

    return any(p.kind == p.VAR_KEYWORD for p in inspect.signature(owner).parameters.values())


def targeted(group: str, ranges: Schema | None = None,
             default: str | None = None) -> Callable[[Any], Schema]:
    """Schema of a group that Hydra builds from its ``_target_`` (``default`` when the config
    names none): a rule for every argument of that target (:func:`typed`, so the keys and
    types follow the code), the ranges and choices of ``ranges`` where they apply (every one
    for a target taking ``**kwargs``), and ``_target_`` / ``name`` (a label). A dataclass
    target (``bundle``, ``verify``, ...) or a target with an ``Options`` dataclass (the sync
    backends) is checked against its fields' own rules, so such a group needs no ``ranges``.
    Without a target it can import, the group gets ``ranges`` as they are (building it then
    reports the bad target)."""
    ranges = dict(ranges or {})

    def schema(cfg: Any) -> Schema:
        from hydra.utils import get_object

        target = None if cfg is None else _value(cfg, f"{group}._target_")
        if not isinstance(target, str):
            target = default
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
    """``model``: each section's options dataclass (``net``:
    :class:`posernet.nn.PoserNetOptions`, ``loss``/``optimizer``/``scheduler``:
    :mod:`posernet.lit.posernet_module`'s), each field with its own rule.
    (``model=learned_sync`` has sections of its own: keys absent here are skipped.)"""
    from ..lit.posernet_module import SECTION_OPTIONS

    return {f"{section}.{k}": r for section, owner in SECTION_OPTIONS.items()
            for k, r in field_rules(owner).items()}


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

#: the Lightning Trainer arguments of posernet/conf/trainer/*.yaml (others pass through
#: unchecked). A table, not a dataclass: the arguments are Lightning's, which the project does
#: not own, and Hydra passes them to ``lightning.Trainer`` as they are
TRAINER: Schema = {
    "accelerator": choice("auto", "cpu", "gpu", "cuda", "mps"),
    "devices": one_of(Rule("", lambda v: is_int(v) and (v == -1 or v >= 1)), choice("auto"),
                      Rule("a list of integers", lambda v: isinstance(v, list) and bool(v)
                           and all(is_int(x) for x in v)),
                      expected="an integer >= 1 (or -1: all), a list of integers or auto"),
    "precision": one_of(choice("64", "32", "16", "bf16", "64-true", "32-true", "16-true",
                               "bf16-true", "16-mixed", "bf16-mixed"),
                        Rule("", lambda v: is_int(v) and v in (16, 32, 64)),
                        expected="one of 64, 32, 16, bf16, 64-true, 32-true, 16-true, bf16-true, "
                                 "16-mixed, bf16-mixed"),
    "strategy": text(),
    "max_epochs": Rule("an integer >= 1 (or -1: no limit)",
                       lambda v: is_int(v) and (v == -1 or v >= 1), True),
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

#: ``sync``: the backend's options dataclass (:func:`targeted`), each field with its own rule;
#: cross-field rules (the scale policies a backend supports, p_min <= p_max) are the backend's
#: own, checked by building it
SYNC = targeted("sync")

#: ``proposals`` and ``matcher``: each source's and matcher's options dataclass (its
#: ``Options``: :class:`~posernet.frontend.proposals.SelectiveSearchOptions`,
#: :class:`~posernet.frontend.features.SiftOptions`, ...), each field with its own rule
PROPOSALS = targeted("proposals")
MATCHER = targeted("matcher")


#: the image front end's groups; those built from a dataclass (``box_matching``, ``relpose``)
#: take every rule from its fields
FRONTEND = {"proposals": PROPOSALS, "matcher": MATCHER,
            "box_matching": targeted("box_matching",
                                     default="posernet.frontend.boxmatch.BoxMatchRules"),
            "relpose": targeted("relpose", default="posernet.frontend.relpose.PoseOptions")}

#: reconstruct's option blocks, each a dataclass whose fields hold their rules
PAIRS = targeted("pairs", default="posernet.frontend.pairs.PairOptions")
VERIFY = targeted("verify", default="posernet.frontend.verify.VerifyRules")
BUNDLE = targeted("bundle", default="posernet.sfm.BundleOptions")
CHECK = targeted("check", default="posernet.sfm.selfcheck.CheckOptions")


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
        groups={**FRONTEND, "verify": VERIFY, "bundle": BUNDLE, "sync": SYNC, "pairs": PAIRS,
                "check": CHECK},
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

"""One config check for every ``posernet-*`` command, run before any work or output.

No option is defined here. Each is a field of the dataclass that declares it
(:func:`posernet.options.option`): a command's own keys its settings dataclass (``TrainSettings``
in :mod:`posernet.cli.train`, ...); a group built from a ``_target_`` that dataclass or the
target's ``Options``; the demo's ``images``, the ``trainer`` and ``model``'s sections dataclasses
of their own. :func:`check_config` applies those rules to a composed config (type, range,
choices, a required ``???`` given), builds what checks itself across options (the sync backend,
the demo's dataset), then checks CUDA and that the output can be written (creating nothing).
Any failure is one :class:`ConfigValueError` naming key, value and expectation:
``model.net.depth: 'abc' is not an integer >= 1``. Keys a config lacks are skipped.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from ..io import writable_dir, writable_file
from ..options import ConfigValueError, Rule, field_rules, signature_rules, text

__all__ = ["COMMANDS", "ConfigValueError", "check_config", "group_rules"]

Schema = Mapping[str, Rule]
#: a group's rules: the dotted name of its dataclass, or a function of the config giving them
Group = str | Callable[[Any], Schema]


# --------------------------------------------------------------------------- where rules live


def targeted(group: str, default: str | None = None) -> Callable[[Any], Schema]:
    """Rules of a group built from its ``_target_`` (``default`` when none is named): its
    ``Options`` dataclass's fields', the target's own when it is a dataclass, else its
    arguments' annotations; plus ``_target_`` and ``name`` (a label), the only two for a target
    that does not import (building the group reports it)."""

    def schema(cfg: Any) -> Schema:
        from hydra.utils import get_object

        target = _value(cfg, f"{group}._target_") if cfg is not None else None
        target = target if isinstance(target, str) else default
        try:
            owner = get_object(target) if isinstance(target, str) else None
        except Exception:  # a bad target: instantiating it says so
            owner = None
        base: dict[str, Rule] = {"_target_": text(), "name": text()}
        if owner is None:
            return base
        options = getattr(owner, "Options", None)
        owner = options if dataclasses.is_dataclass(options) else owner
        return {**base, **(field_rules(owner) if dataclasses.is_dataclass(owner)
                           else signature_rules(owner))}

    return schema


def _model(cfg: Any) -> Schema:
    """``model``: each section's options dataclass (absent keys are skipped: learned_sync's)."""
    from ..lit.posernet_module import SECTION_OPTIONS

    return {f"{section}.{k}": r for section, owner in SECTION_OPTIONS.items()
            for k, r in field_rules(owner).items()}


def _declared(name: str) -> Any:
    from hydra.utils import get_object

    return get_object(name)


def group_rules(group: Group, cfg: Any) -> Schema:
    """The rules of one group of a :class:`Command`, for config ``cfg``."""
    return field_rules(_declared(group)) if isinstance(group, str) else group(cfg)


SYNC = targeted("sync")
FRONTEND: dict[str, Group] = {
    "proposals": targeted("proposals"), "matcher": targeted("matcher"),
    "box_matching": targeted("box_matching", "posernet.frontend.boxmatch.BoxMatchRules"),
    "relpose": targeted("relpose", "posernet.frontend.relpose.PoseOptions")}
DATA = targeted("data", "posernet.data.datamodule.PoserDataModule")


# --------------------------------------------------------------------------- the commands


@dataclass(frozen=True)
class Command:
    """What a command's config check walks: where its keys are declared, what it writes."""

    settings: str  # the dotted name of the dataclass of its top-level keys
    groups: Mapping[str, Group]
    output: tuple[str, str, str | None]  # its key, "dir" or "file", the path when null
    when: tuple[str, Any] | None = None  # (key, value): groups checked only then
    devices: tuple[str, ...] = ("device",)  # keys naming a device (CUDA needs CUDA)
    #: ``(group, dotted name of a function of its plain values)``: built early, so that what
    #: its own constructor checks across options runs before any work
    checks: tuple[tuple[str, str], ...] = ()


OUT_DIR = ("out_dir", "dir", None)
SYNC_CHECK = ("sync", "posernet.cli.build.check_sync_config")
COMMANDS: dict[str, Command] = {
    "train": Command(
        "posernet.cli.train.TrainSettings",
        {"data": DATA, "model": _model, "trainer": "posernet.lit.trainer.TrainerOptions",
         "sync": SYNC}, OUT_DIR, devices=("trainer.accelerator",), checks=(SYNC_CHECK,)),
    "eval": Command("posernet.cli.evaluate.EvalSettings", {"data": DATA, "sync": SYNC}, OUT_DIR,
                    checks=(SYNC_CHECK,)),
    "refine": Command("posernet.cli.refine.RefineSettings", {"sync": SYNC},
                      ("output", "file", None), checks=(SYNC_CHECK,)),
    "demo": Command("posernet.cli.demo.DemoSettings",
                    {"images": "posernet.cli.demo.ImagesOptions", "sync": SYNC}, OUT_DIR,
                    checks=(SYNC_CHECK,
                            ("dataset", "posernet.data.synthetic.config.resolve_options"))),
    "reconstruct": Command(
        "posernet.cli.reconstruct.ReconstructSettings",
        {**FRONTEND, "verify": targeted("verify", "posernet.frontend.verify.VerifyRules"),
         "bundle": targeted("bundle", "posernet.sfm.BundleOptions"), "sync": SYNC,
         "pairs": targeted("pairs", "posernet.frontend.pairs.PairOptions"),
         "check": targeted("check", "posernet.sfm.selfcheck.CheckOptions")},
        OUT_DIR, devices=("device", "matcher.device"), checks=(SYNC_CHECK,)),
    # null out_dir: outputs/data/<preset name>, whose nearest existing folder is the same
    "make_data": Command(
        "posernet.cli.make_data.MakeDataSettings", FRONTEND, ("out_dir", "dir", "outputs/data"),
        when=("source", "sevenscenes"), devices=()),
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
        first = next((ln.strip() for ln in str(exc).splitlines() if ln.strip()),
                     type(exc).__name__)
        raise ConfigValueError(f"{key}: cannot resolve its value ({first})") from None
    return value


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


def check_config(cfg: Any, command: str) -> None:
    """Check the composed config of ``command`` (a key of :data:`COMMANDS`) before any work;
    :class:`ConfigValueError` (one line) for the first problem found."""
    spec = COMMANDS[command]
    # groups first: a top-level value may be one of theirs (eval's estimate: ${data.estimate})
    groups = spec.groups if spec.when is None or _value(cfg, spec.when[0]) == spec.when[1] else {}
    for group, declared in groups.items():
        value = _value(cfg, group)
        if value is _ABSENT or value is None:
            continue
        rules = group_rules(declared, cfg)
        if not isinstance(value, dict):  # e.g. pairs=exhaustive for pairs.mode=exhaustive
            fits = [k for k, r in rules.items() if not k.startswith("_") and r.ok(value)
                    and r.expected.startswith("one of")]
            hint = (f"did you mean {group}.{fits[0]}={value}?" if fits
                    else f"set its options as {group}.<option>=...")
            raise ConfigValueError(f"{group}: {value!r} is not a group of options; {hint}")
        _check_schema(cfg, rules, group + ".")
        _check_required(cfg, group)
    settings = _declared(spec.settings)
    _check_schema(cfg, field_rules(settings))
    for group, check in spec.checks:
        if isinstance(value := _value(cfg, group), dict):
            _declared(check)(value)
    cross_check = getattr(settings, "cross_check", None)  # the settings' rules across keys
    if cross_check is not None:
        cross_check({k: v for k in field_rules(settings)
                     if (v := _value(cfg, k)) not in (_ABSENT, _MISSING)})
    for key in spec.devices:
        device = _value(cfg, key)
        if isinstance(device, str) and (device.startswith("cuda") or device == "gpu"):
            import torch

            if not torch.cuda.is_available():
                raise ConfigValueError(f"{key}={device} but CUDA is not available")
    key, kind, default = spec.output
    value = _value(cfg, key)
    value = default if value in (None, _ABSENT) else value
    if value not in (None, _ABSENT, _MISSING):
        (writable_dir if kind == "dir" else writable_file)(value, key)

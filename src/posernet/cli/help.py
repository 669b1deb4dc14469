"""``--help`` of a command, written from its own config: what it does (the config file's header
comments), the required keys, each config group with its choices, and every option of the
composed config (the groups' defaults included) with its default and its one-line meaning: for
an option declared on a dataclass field (the command's own keys on its settings dataclass,
``bundle``, ``verify``, ``check``, ``pairs``, ``relpose``, ``box_matching``, ``data``,
``trainer``, the demo's ``images``, the sync backends', matchers' and proposal sources'
options) its declared help and choices (:func:`posernet.options.option`); only for a key no
dataclass declares, the comment beside it, or the comment block right above it, in whichever
file sets it. Hydra's own
help (every group in the config folder, comments stripped, required keys as ``???``) stays at
``--hydra-help``.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

__all__ = ["command_help"]

_KEY = re.compile(r"^(?P<indent> *)(?P<key>[A-Za-z_][\w.]*):(?P<value>[^#]*?)\s*(#\s?(?P<c>.*))?$")
_GROUP = re.compile(r"^\s*-\s*(?P<group>[\w/]+):\s*(?P<choice>[\w.+-]+)")
#: a comment-only line indented this far continues the meaning of the key above it
_CONTINUATION = 10


def _choices(config_dir: Path, group: str) -> list[str]:
    folder = config_dir / group
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []


def _meanings(path: Path, prefix: str) -> dict[str, str]:
    """The meaning of each key (dotted, below ``prefix``) that one yaml file comments: the
    comment beside it (continued by comment-only lines indented at least
    ``_CONTINUATION``), else the comment lines right above it at its indentation."""
    out: dict[str, str] = {}
    stack: list[tuple[int, str]] = []  # the mappings enclosing the current line
    above: list[tuple[int, str]] = []  # comment-only lines since the last key or blank line
    last: str | None = None  # the key a continuation line extends
    for ln in path.read_text(encoding="utf-8").splitlines():
        stripped = ln.lstrip()
        indent = len(ln) - len(stripped)
        if not stripped:
            above, last = [], None
            continue
        if stripped.startswith("#"):
            text = stripped[1:].strip()
            if last is not None and indent >= _CONTINUATION and not above:
                out[last] = (out.get(last, "") + " " + text).strip()
            else:
                above.append((indent, text))
                last = None
            continue
        m = _KEY.match(ln)
        if not m:  # a list item (the defaults list, a block list): no option of its own
            above, last = [], None
            continue
        while stack and stack[-1][0] >= indent:
            stack.pop()
        key = ".".join([*(k for _, k in stack), m["key"]])
        comment = (m["c"] or "").strip() or " ".join(t for i, t in above if i == indent)
        if comment:
            out[f"{prefix}{key}"] = comment
        if m["value"].strip() == "":
            stack.append((indent, m["key"]))
        above, last = [], f"{prefix}{key}" if m["c"] else None
    return out


def options_owner(target: Any) -> Any:
    """The dataclass declaring the options of a group built from ``target`` (a dotted name):
    the target itself when it is a dataclass, a sync backend's ``Options``; ``None`` for a
    constructor or a target that does not import."""
    import dataclasses

    from hydra.utils import get_object

    try:
        owner = get_object(str(target))
    except Exception:  # a bad target: the config check reports it
        return None
    owner = getattr(owner, "Options", owner)
    return owner if isinstance(owner, type) and dataclasses.is_dataclass(owner) else None


def command_owners(config_name: str) -> dict[str, type]:
    """The dataclasses declaring options at a fixed place of command ``config_name``'s config
    (a key of :data:`posernet.cli.validation.COMMANDS`), by prefix: ``""`` its own top-level
    keys (its settings dataclass), ``"images."`` a group declared by a dataclass of its own;
    ``{}`` for another config."""
    from hydra.utils import get_object

    from .validation import COMMANDS

    spec = COMMANDS.get(config_name)
    if spec is None:
        return {}
    own = {f"{g}.": get_object(o) for g, o in spec.groups.items() if isinstance(o, str)}
    return {"": get_object(spec.settings), **own}


def declared_meanings(cfg: Any) -> dict[str, str]:
    """The meaning of every option of a group built from a dataclass (``bundle``, ``sync``,
    ...): its :func:`posernet.options.option` help and choices."""
    from omegaconf import OmegaConf

    from ..options import option_help

    out: dict[str, str] = {}
    for group in cfg.keys():
        node = cfg._get_node(group)
        if not OmegaConf.is_dict(node) or "_target_" not in node:
            continue
        owner = options_owner(node._get_node("_target_")._value())
        if owner is not None:
            out.update({f"{group}.{k}": v for k, v in option_help(owner).items()})
    return out


def _leaves(node: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """Dotted key and raw value (interpolations and ``???`` as written) of every option of a
    composed config, without keys that start with ``_`` (``_target_``, ...)."""
    from omegaconf import OmegaConf

    for k in node.keys():
        if str(k).startswith("_"):
            continue
        child = node._get_node(k)
        if OmegaConf.is_dict(child) and len(child) > 0:
            yield from _leaves(child, f"{prefix}{k}.")
        elif OmegaConf.is_config(child):
            yield f"{prefix}{k}", OmegaConf.to_container(child, resolve=False)
        else:
            yield f"{prefix}{k}", child._value()


def _text(value: Any) -> str:
    """A default as a user writes it on the command line."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, str):
        return value if value else '""'
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(_text(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {_text(v)}" for k, v in value.items()) + "}"
    return str(value)


def _composed(config_dir: Path, config_name: str) -> tuple[Any, list[tuple[Path, str]]]:
    """The composed config (no ``hydra`` node) and the files it was composed from, in order,
    each with the package (dotted prefix) its keys land in."""
    from hydra import compose
    from hydra.core.global_hydra import GlobalHydra
    from hydra.types import RunMode

    from ..conf import initialized

    with initialized(config_name, config_dir):
        cfg = compose(config_name)
        defaults = GlobalHydra.instance().config_loader().compute_defaults_list(
            config_name, [], RunMode.RUN).defaults
    files = [(config_dir / f"{d.config_path}.yaml", f"{d.package}." if d.package else "")
             for d in defaults
             if d.config_path and not d.config_path.startswith("hydra/")
             and not (d.package or "").startswith("hydra")]
    return cfg, files


def command_help(prog: str, config_dir: str | Path, config_name: str, width: int = 100) -> str:
    """The help text of ``prog`` from ``config_dir/config_name.yaml`` (see the module)."""
    config_dir = Path(config_dir)
    lines = (config_dir / f"{config_name}.yaml").read_text(encoding="utf-8").splitlines()
    header = []
    for ln in lines:
        if not ln.startswith("#"):
            break
        header.append(ln[1:].strip())
    groups: list[tuple[str, str]] = []
    in_defaults = False
    for ln in lines:
        if ln.startswith("defaults:"):
            in_defaults = True
        elif in_defaults and ln.strip() and not ln.startswith((" ", "-", "#")):
            break
        elif in_defaults and (g := _GROUP.match(ln)) and \
                not g["group"].startswith(("override", "hydra")):
            groups.append((g["group"], g["choice"]))
    cfg, files = _composed(config_dir, config_name)
    meanings: dict[str, str] = {}
    for path, prefix in files:  # a later file's comment wins, as its value does
        meanings.update(_meanings(path, prefix))
    meanings.update(declared_meanings(cfg))  # an option's own declaration wins over both
    from ..options import option_help

    for prefix, owner in command_owners(config_name).items():
        meanings.update({f"{prefix}{k}": v for k, v in option_help(owner).items()})
    grouped = {prefix.split(".")[0] for _, prefix in files if prefix}
    options = [(k, _text(v), meanings.get(k, "")) for k, v in _leaves(cfg)]
    options.sort(key=lambda o: o[0].split(".")[0] in grouped)  # the command's own keys first
    required = [(k, m) for k, d, m in options if d == "???"]
    rest = [(k, d, m) for k, d, m in options if d != "???"]
    usage = " ".join(f"{k}=..." for k, _ in required)
    out = [" ".join(x for x in ("usage:", prog, usage, "[key=value ...]") if x), ""]
    out += [h for h in header if h] + [""]
    if required:
        out.append("required:")
        out += [f"  {k:<24} {m}" for k, m in required]
        out.append("")
    if groups:
        out.append("config groups (group=choice; default first; their options below):")
        for g, default in groups:
            others = [c for c in _choices(config_dir, g) if c != default]
            out.append(f"  {g:<24} {', '.join([default, *others])}")
        out.append("")
    out.append("options (key, default, meaning):")
    kw = min(max((len(k) for k, _, _ in rest), default=10), 36)
    dw = min(max((len(d) for _, d, _ in rest), default=4), 24)
    for k, d, m in rest:
        d = d if len(d) <= dw else d[: dw - 3] + "..."
        out.append(f"  {k:<{kw}} {d:<{dw}} {m}".rstrip())
    out += ["", f"Config files, with their comments: {config_dir} ({config_name}.yaml and the "
            "groups' folders); Hydra's own help: --hydra-help."]
    return "\n".join(out) + "\n"

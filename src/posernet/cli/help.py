"""``--help`` of a command, written from its own config file: what it does (the file's header
comments), the required keys, each option with its default and its one-line meaning (the
comment beside it), and each config group with its choices. Hydra's own help (every group in
the config folder, comments stripped, required keys as ``???``) stays at ``--hydra-help``.
"""

from __future__ import annotations

import re
from pathlib import Path

__all__ = ["command_help"]

_KEY = re.compile(r"^(?P<indent> *)(?P<key>[A-Za-z_][\w.]*):(?P<value>[^#]*?)\s*(#\s?(?P<c>.*))?$")
_GROUP = re.compile(r"^\s*-\s*(?P<group>[\w/]+):\s*(?P<choice>[\w.+-]+)")


def _choices(config_dir: Path, group: str) -> list[str]:
    folder = config_dir / group
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []


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
    options: list[tuple[str, str, str]] = []  # key, default, meaning
    block: str | None = None
    in_defaults = False
    above: list[str] = []  # a comment block right above a key is its meaning
    for ln in lines:
        if not ln.strip():
            above = []
            continue
        if ln.lstrip().startswith("#"):
            # an indented comment-only line continues the meaning of the option above it
            if options and ln.startswith(" " * 10):
                k, d, m = options[-1]
                options[-1] = (k, d, (m + " " + ln.strip()[1:].strip()).strip())
            elif ln.startswith("#"):
                above.append(ln[1:].strip())
            continue
        if ln.startswith("defaults:"):
            in_defaults = True
            continue
        if in_defaults:
            g = _GROUP.match(ln)
            if g and not g["group"].startswith(("override", "hydra")):
                groups.append((g["group"], g["choice"]))
                continue
            if ln.startswith(" ") or ln.lstrip().startswith("-"):
                continue
            in_defaults = False
        m = _KEY.match(ln)
        if not m:
            continue
        key, value, comment = m["key"], m["value"].strip(), (m["c"] or "").strip()
        if not comment and not m["indent"] and above:
            comment = " ".join(above)
        if not m["indent"]:
            above = []
        if key in ("hydra", "_target_") or key.startswith("_"):
            block = None if not m["indent"] else block
            if not m["indent"]:
                block = "hydra" if key == "hydra" else None
            continue
        if not m["indent"]:
            block = key if value == "" else None
            if value != "":
                options.append((key, value, comment))
            continue
        if block and block != "hydra" and len(m["indent"]) == 2 and key != "_target_":
            options.append((f"{block}.{key}", value, comment))
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
        out.append("config groups (group=choice; default first):")
        for g, default in groups:
            others = [c for c in _choices(config_dir, g) if c != default]
            out.append(f"  {g:<24} {', '.join([default, *others])}")
        out.append("")
    out.append("options (key, default, meaning):")
    kw = max(len(k) for k, _, _ in rest) if rest else 10
    dw = min(max((len(d) for _, d, _ in rest), default=4), 24)
    for k, d, m in rest:
        d = d if len(d) <= dw else d[: dw - 3] + "..."
        out.append(f"  {k:<{kw}} {d:<{dw}} {m}".rstrip())
    out += ["", f"Every option: {config_dir / (config_name + '.yaml')} (with its comments); "
            "Hydra's own help: --hydra-help."]
    return "\n".join(out) + "\n"

"""Options declared once (posernet.options): the field rules, the checks built from them, and the
shipped YAML files and ``--help`` agreeing with the declarations."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from posernet.cli import CONFIG_DIR
from posernet.cli.help import _meanings, command_help, command_owners, options_owner
from posernet.cli.validation import COMMANDS
from posernet.options import (
    ConfigValueError,
    check_options,
    field_rules,
    option,
    option_help,
)

# --------------------------------------------------------------------------- the helper


@dataclasses.dataclass(frozen=True)
class _Opts:
    n: int = option(1, ge=1, help="how many")
    ratio: float = option(0.5, gt=0, le=1)
    limit: float | None = option(None, ge=0, lt=180)
    mode: str = option("a", choices=("a", "b"), help="the mode")
    flag: bool = option(True)
    plain: int = 3  # no metadata: its type alone

    def __post_init__(self) -> None:
        check_options(self)


def test_field_rules_follow_the_declaration():
    rules = {k: r.describe() for k, r in field_rules(_Opts).items()}
    assert rules == {"n": "an integer >= 1", "ratio": "a number in (0, 1]",
                     "limit": "a number in [0, 180) or null", "mode": "one of a, b",
                     "flag": "true or false", "plain": "an integer"}


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"n": 0}, "_Opts.n: 0 is not an integer >= 1"),
    ({"n": 1.5}, "_Opts.n: 1.5 is not an integer >= 1"),
    ({"ratio": 0}, r"_Opts.ratio: 0 is not a number in \(0, 1\]"),
    ({"ratio": float("nan")}, "_Opts.ratio: nan is not"),
    ({"limit": 180}, r"_Opts.limit: 180 is not a number in \[0, 180\) or null"),
    ({"mode": "c"}, "_Opts.mode: 'c' is not one of a, b"),
    ({"flag": 1}, "_Opts.flag: 1 is not true or false"),
    ({"plain": "x"}, "_Opts.plain: 'x' is not an integer"),
])
def test_check_options_names_the_field_value_and_rule(kwargs, message):
    with pytest.raises(ConfigValueError, match=f"^{message}"):
        _Opts(**kwargs)


def test_numpy_numbers_and_null_pass():
    np = pytest.importorskip("numpy")
    _Opts(n=np.int64(3), ratio=np.float32(0.25), limit=None)
    _Opts(limit=10)


def test_help_lists_the_choices():
    assert option_help(_Opts) == {"n": "how many", "mode": "the mode [a | b]"}


def test_one_error_type():
    from posernet.cli.validation import ConfigValueError as cli_error
    from posernet.data.synthetic import ConfigError

    assert ConfigError is ConfigValueError is cli_error
    assert issubclass(ConfigValueError, ValueError)


# --------------------------------------------------------------------------- the shipped YAML

#: where a shipped file deliberately sets another value than the field's default (the library
#: default suits a caller in Python; the command's file picks what suits that command)
COMMAND_DEFAULTS = {
    ("reconstruct.yaml", "pairs.mode"): "auto: retrieval for large image sets",
    ("reconstruct.yaml", "bundle.refine_focal"): "auto: the command knows whether the "
                                                  "intrinsics were guessed",
    ("relpose/ransac.yaml", "method"): "the classic-RANSAC choice of the group",
    ("matcher/xfeat_lighterglue.yaml", "lighterglue"): "the group's choice: LighterGlue",
    ("matcher/sift_xfeat.yaml", "lighterglue"): "the fallback matches with LighterGlue",
    ("data/synthetic.yaml", "root"): "the library needs a folder; the command names "
                                     "posernet-make-data's default one",
}


def _dataclass_blocks():
    """``(file, prefix, owner, node)`` for every block of a shipped YAML file built from a
    dataclass (its ``_target_``): a whole group file or a block of a command's file; and every
    block of a command's file that a dataclass of its own declares (the demo's ``images``)."""
    root = Path(CONFIG_DIR)
    for command in sorted(COMMANDS):
        node = OmegaConf.load(root / f"{command}.yaml")
        for prefix, owner in command_owners(command).items():
            if prefix and prefix[:-1] in node:
                yield f"{command}.yaml", prefix, owner, node[prefix[:-1]]
    for path in sorted(root.rglob("*.yaml")):
        node = OmegaConf.load(path)
        if not OmegaConf.is_dict(node):
            continue
        blocks = [("", node)] if "_target_" in node else []
        blocks += [(f"{k}.", node[k]) for k in node
                   if OmegaConf.is_dict(node._get_node(k)) and "_target_" in node[k]]
        for prefix, block in blocks:
            owner = options_owner(block._get_node("_target_")._value())
            if owner is not None:
                yield path.relative_to(root).as_posix(), prefix, owner, block


BLOCKS = list(_dataclass_blocks())


def test_the_dataclass_backed_blocks_are_found():
    found = {(f, p) for f, p, _, _ in BLOCKS}
    for block in [("reconstruct.yaml", "bundle."), ("reconstruct.yaml", "verify."),
                  ("reconstruct.yaml", "check."), ("reconstruct.yaml", "pairs."),
                  ("relpose/usac.yaml", ""), ("box_matching/paper.yaml", ""),
                  ("sync/eig_se3.yaml", ""), ("sync/rotation_translation.yaml", ""),
                  *((f"matcher/{m}.yaml", "") for m in ("auto", "sift", "sift_xfeat", "xfeat",
                                                         "xfeat_lighterglue")),
                  *((f"proposals/{p}.yaml", "") for p in ("selective_search", "edge_boxes",
                                                           "file")),
                  ("data/synthetic.yaml", ""), ("trainer/cpu.yaml", ""),
                  ("demo.yaml", "images.")]:
        assert block in found, block


def test_constructors_declare_their_options():
    """The network, each matcher and each proposal source checks its arguments against its
    options dataclass, whose fields are exactly the constructor's arguments and defaults (the
    datamodule's ``Options`` too, which the config check reads)."""
    import inspect

    from posernet.data.datamodule import PoserDataModule
    from posernet.frontend import features, proposals
    from posernet.nn import PoserNet

    for cls in (PoserNet, features.SiftMatcher, features.XFeatMatcher, features.FallbackMatcher,
                proposals.SelectiveSearch, proposals.EdgeBoxes, proposals.FileProposals,
                PoserDataModule):
        params = {k: p.default for k, p in inspect.signature(cls).parameters.items()}
        fields = {f.name: _default(f) for f in dataclasses.fields(cls.Options)}
        fields = {k: (inspect.Parameter.empty if v is dataclasses.MISSING else v)
                  for k, v in fields.items()}
        assert fields == params, cls.__name__
    shared = set(features.SiftOptions.__dataclass_fields__)
    assert shared < set(features.FallbackOptions.__dataclass_fields__)
    assert features.make_matcher.Options is features.MatcherOptions


def _default(f: dataclasses.Field):
    return f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default


@pytest.mark.parametrize(("file", "prefix", "owner", "node"), BLOCKS,
                         ids=[f"{f}:{p}" for f, p, _, _ in BLOCKS])
def test_yaml_defaults_are_the_fields_defaults(file, prefix, owner, node):
    fields = {f.name: f for f in dataclasses.fields(owner)}
    differ = []
    for key in node:
        if key in ("_target_", "name") or OmegaConf.is_missing(node, key):
            continue
        assert key in fields, f"{file}: {prefix}{key} is no option of {owner.__name__}"
        value = node._get_node(key)._value()
        if OmegaConf.is_interpolation(node, key):  # wired to another key (${seed}): no default
            continue
        if (file, f"{prefix}{key}") in COMMAND_DEFAULTS:
            assert value != _default(fields[key]), f"{file}: {prefix}{key} is the default now"
            continue
        if value != _default(fields[key]):
            differ.append(f"{prefix}{key}: {value!r} in the file, {_default(fields[key])!r} "
                          f"on {owner.__name__}")
    assert not differ, f"{file}: {differ}"


def _listed_choices(comment: str) -> set[str] | None:
    """The choices a comment lists as ``a | b (why) | c``, or None without such a list."""
    if "|" not in comment:
        return None
    flat = comment
    while re.search(r"\([^()]*\)", flat):
        flat = re.sub(r"\([^()]*\)", "", flat)
    parts = [p.strip() for p in flat.split("|")]
    words = [re.findall(r"[\w+-]+", p) for p in parts]
    return {*words[0][-1:], *(w[0] for w in words[1:] if w)}


@pytest.mark.parametrize(("file", "prefix", "owner", "node"), BLOCKS,
                         ids=[f"{f}:{p}" for f, p, _, _ in BLOCKS])
def test_yaml_comments_list_the_fields_choices(file, prefix, owner, node):
    from posernet.options import options_of

    comments = _meanings(Path(CONFIG_DIR) / file, "")
    wrong = []
    for name, meta in options_of(owner).items():
        comment = comments.get(f"{prefix}{name}")
        if meta.choices is None or comment is None:
            continue
        listed = _listed_choices(comment)
        if listed is not None and listed != set(meta.choices):
            wrong.append(f"{prefix}{name}: {sorted(listed)} in the comment, "
                         f"{sorted(meta.choices)} on {owner.__name__}")
    assert not wrong, f"{file}: {wrong}"


def test_help_shows_the_declared_help_and_choices():
    from posernet.sfm import BundleOptions

    text = command_help("posernet-reconstruct", CONFIG_DIR, "reconstruct")
    lines = {ln.split()[0]: ln for ln in text.splitlines() if ln.startswith("  ")}
    for key, owner in (("bundle.loss", BundleOptions),):
        assert option_help(owner)[key.split(".")[1]] in lines[key]
    assert "arctan" in lines["bundle.loss"]
    assert "[auto | exhaustive | sequential | retrieval]" in lines["pairs.mode"]
    assert "[unit | given | oracle | free]" in lines["sync.scale"]
    assert "[single | fast | quality]" in lines["proposals.strategy"]
    assert "keep the best this many boxes" in lines["proposals.top_k"]
    assert "Lowe's ratio" in lines["matcher.ratio"]
    assert "weakly textured" in lines["matcher.weak_share"]


# --------------------------------------------------------------------------- the commands' own keys

#: blocks of a command's file that something other than the config check builds, with the
#: dataclass declaring their keys
BUILT_ELSEWHERE = {("make_data", "sevenscenes"): "posernet.data.sevenscenes_graphs."
                                                 "SevenScenesOptions"}


def _settings(command: str) -> type:
    return command_owners(command)[""]


def _command_file(command: str):
    return OmegaConf.load(Path(CONFIG_DIR) / f"{command}.yaml")


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_key_of_a_command_file_is_declared(command):
    """Each top-level key of ``conf/<command>.yaml`` is a field of the command's settings
    dataclass, or a block whose keys a dataclass (or its target's constructor) declares; each
    settings field is in the file."""
    import inspect

    from hydra.utils import get_object

    node = _command_file(command)
    fields = {f.name for f in dataclasses.fields(_settings(command))}
    undeclared = []
    for key in node:
        if key in ("defaults", "hydra") or key in fields:
            continue
        block = node._get_node(key)
        if not OmegaConf.is_dict(block):
            undeclared.append(key)
            continue
        if (command, key) in BUILT_ELSEWHERE:
            owner = get_object(BUILT_ELSEWHERE[command, key])
        elif key in COMMANDS[command].groups and "_target_" not in block:
            owner = command_owners(command)[f"{key}."]
        else:  # built from its _target_: its options dataclass, or its constructor
            owner = get_object(str(block._get_node("_target_")._value()))
            owner = getattr(owner, "Options", owner)
        names = ({f.name for f in dataclasses.fields(owner)} if dataclasses.is_dataclass(owner)
                 else set(inspect.signature(owner).parameters))
        undeclared += [f"{key}.{k}" for k in block if k not in names | {"_target_", "name"}]
    assert not undeclared, f"{command}.yaml: declared nowhere: {undeclared}"
    assert fields <= set(node), f"{command}.yaml lacks {sorted(fields - set(node))}"


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_command_file_defaults_are_the_settings_defaults(command):
    """The file's value of each key (an interpolation as written) is its field's default; a
    required field (no default) is ``???`` in the file, and only such a field."""
    node = _command_file(command)
    differ = []
    for f in dataclasses.fields(_settings(command)):
        required = f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        if OmegaConf.is_missing(node, f.name) or required:
            if not (OmegaConf.is_missing(node, f.name) and required):
                differ.append(f"{f.name}: required in {'the field' if required else 'the file'}"
                              f" only")
            continue
        value = node._get_node(f.name)._value()
        if value != _default(f):
            differ.append(f"{f.name}: {value!r} in the file, {_default(f)!r} on the field")
    assert not differ, f"{command}.yaml: {differ}"


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_command_file_comments_list_the_settings_choices(command):
    from posernet.options import options_of

    comments = _meanings(Path(CONFIG_DIR) / f"{command}.yaml", "")
    wrong = []
    for name, meta in options_of(_settings(command)).items():
        listed = _listed_choices(comments.get(name, ""))
        if meta.choices is not None and listed is not None and listed != set(meta.choices):
            wrong.append(f"{name}: {sorted(listed)} in the comment, {sorted(meta.choices)} on "
                         f"the field")
    assert not wrong, f"{command}.yaml: {wrong}"


@pytest.mark.parametrize(("prog", "command"), [(f"posernet-{c.replace('_', '-')}", c)
                                               for c in sorted(COMMANDS)])
def test_help_shows_the_settings_help(prog, command):
    """Every top-level key has a one-line meaning on its field, and ``--help`` prints it."""
    owner = _settings(command)
    meanings = option_help(owner)
    assert set(meanings) == {f.name for f in dataclasses.fields(owner)}, "a field lacks help"
    text = command_help(prog, CONFIG_DIR, command)
    lines = {ln.split()[0]: ln for ln in text.splitlines() if ln.startswith("  ")}
    for key, meaning in meanings.items():
        assert meaning in lines[key], key

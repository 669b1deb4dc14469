"""Config options, each declared once: on the dataclass field that owns it.

An option is a dataclass field made with :func:`option`; its type is the field's annotation
and the rest -- range, choices, whether ``None`` is accepted, a one-line meaning -- sits in the
field's metadata::

    from dataclasses import dataclass
    from posernet.options import check_options, option

    @dataclass(frozen=True)
    class PoseOptions:
        method: str = option("usac", choices=("usac", "ransac"), help="the RANSAC variant")
        ransac_prob: float = option(0.999, gt=0, lt=1, help="RANSAC confidence")
        max_iters: int = option(1000, ge=1)
        seed: int | None = option(None, ge=0)  # ``| None``: null is accepted

        def __post_init__(self) -> None:
            check_options(self)  # every field against its rule; cross-field checks follow

Everything else reads that one declaration:

* :func:`check_options` checks an instance (the dataclass's ``__post_init__``, or a sync
  backend's ``check()``) and raises :class:`ConfigValueError`
  ``PoseOptions.max_iters: 0 is not an integer >= 1``;
* :func:`field_rules` gives each field's :class:`Rule`; the commands' config check
  (:mod:`posernet.cli.validation`) applies them to the composed config before any work, with the
  config's own key: ``relpose.max_iters: 0 is not an integer >= 1``;
* :func:`option_help` gives each field's meaning and choices, which ``--help``
  (:mod:`posernet.cli.help`) prints; the shipped YAML files repeat the defaults and choices in
  their comments, and a test fails when they disagree with the fields.

The type decides the kind of value: ``bool`` true or false, ``int`` an integer, ``float`` a
finite number (an integer too), ``str`` a non-empty string (one of ``choices`` when given);
``ge``/``gt``/``le``/``lt`` bound a number; ``rule=`` gives a :class:`Rule` of its own for values
no annotation describes (a device name, a path). This module imports neither torch nor
OmegaConf: options are plain Python.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
import re
import types
import typing
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

__all__ = [
    "DEVICE",
    "ConfigValueError",
    "Option",
    "Rule",
    "boolean",
    "check_options",
    "choice",
    "field_rules",
    "integer",
    "number",
    "one_of",
    "option",
    "option_help",
    "path",
    "paths",
    "positive",
    "rule_for",
    "signature_rules",
    "text",
]

#: the metadata key of an option's :class:`Option`
KEY = "posernet.option"


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
        """Whether ``value`` is accepted."""
        return (value is None and self.null) or (value is not None and self.test(value))

    def describe(self) -> str:
        """What is accepted, in words (``an integer >= 1 or null``)."""
        return f"{self.expected} or null" if self.null else self.expected


def is_int(v: Any) -> bool:
    """An integer (numpy's too), not a bool."""
    return isinstance(v, numbers.Integral) and not isinstance(v, bool)


def is_number(v: Any) -> bool:
    """A finite real number (numpy's too), not a bool."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)


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
    """An integer in ``[lo, hi]`` (either bound may be left out)."""
    return Rule(f"an integer{_bounds(lo, hi, False, False)}",
                lambda v: is_int(v) and _within(v, lo, hi, False, False), null)


def number(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
           hi_open: bool = False, null: bool = False) -> Rule:
    """A finite number between ``lo`` and ``hi`` (each bound closed unless ``*_open``)."""
    return Rule(f"a number{_bounds(lo, hi, lo_open, hi_open)}",
                lambda v: is_number(v) and _within(v, lo, hi, lo_open, hi_open), null)


def positive(*, null: bool = False) -> Rule:
    """A number > 0."""
    return number(0, lo_open=True, null=null)


def boolean(*, null: bool = False) -> Rule:
    """True or false."""
    return Rule("true or false", lambda v: isinstance(v, bool), null)


def choice(*options: str, null: bool = False) -> Rule:
    """One of ``options`` (strings)."""
    return Rule(f"one of {', '.join(options)}", lambda v: isinstance(v, str) and v in options,
                null)


def text(*, null: bool = False) -> Rule:
    """A non-empty string."""
    return Rule("a string", lambda v: isinstance(v, str) and v != "", null)


def path(*, null: bool = False) -> Rule:
    """A file or folder name (a number is a valid name too: ``out_dir=2024``)."""
    return Rule("a path", lambda v: (isinstance(v, str) and v != "") or is_int(v), null)


def paths() -> Rule:
    """A path or a non-empty list of paths (e.g. several datasets to train on)."""
    one = path()
    return Rule("a path or a list of paths",
                lambda v: one.ok(v) or (isinstance(v, list) and bool(v)
                                        and all(one.ok(x) for x in v)))


def one_of(*rules: Rule, expected: str | None = None) -> Rule:
    """A value any of ``rules`` accepts (``expected``: in words, else theirs joined by "or")."""
    null = any(r.null for r in rules)
    return Rule(expected or " or ".join(r.expected for r in rules),
                lambda v: any(r.ok(v) for r in rules), null)


#: a torch device name as the commands take it
DEVICE = Rule("one of cpu, cuda, cuda:N, auto", lambda v: isinstance(v, str) and re.fullmatch(
    r"cpu|cuda|cuda:\d+|auto", v) is not None)


def anything(expected: str = "a value") -> Rule:
    """Any value (checked by its user)."""
    return Rule(expected, lambda v: True, True)


# --------------------------------------------------------------------------- declaring


@dataclass(frozen=True)
class Option:
    """The metadata of one option (see :func:`option`)."""

    help: str = ""
    choices: tuple[str, ...] | None = None
    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    null: bool | None = None
    rule: Rule | None = None

    def rule_for(self, hint: Any) -> Rule:
        """The rule of a field annotated ``hint`` (a type, maybe ``X | None``)."""
        base, nullable = _split_optional(hint)
        null = nullable if self.null is None else self.null
        if self.rule is not None:
            return dataclasses.replace(self.rule, null=null or self.rule.null)
        if self.choices is not None:
            return choice(*self.choices, null=null)
        lo, lo_open = (self.gt, True) if self.gt is not None else (self.ge, False)
        hi, hi_open = (self.lt, True) if self.lt is not None else (self.le, False)
        if base is int:
            if lo_open or hi_open:
                raise TypeError("an integer option takes ge= and le=, not gt= or lt=")
            return integer(_as_int(lo), _as_int(hi), null=null)
        if base is float:
            return number(lo, hi, lo_open=lo_open, hi_open=hi_open, null=null)
        if lo is not None or hi is not None:
            raise TypeError(f"bounds on an option of type {hint!r}")
        return _plain(base, null)


def _as_int(v: float | None) -> int | None:
    return None if v is None else int(v)


def _split_optional(hint: Any) -> tuple[Any, bool]:
    """``(X, True)`` for ``X | None``, ``(X, False)`` for ``X``."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = set(typing.get_args(hint))
        null = type(None) in args
        args.discard(type(None))
        return (args.pop() if len(args) == 1 else None), null
    return hint, False


def _plain(base: Any, null: bool) -> Rule:
    """The rule of a type alone: bool, int, float, str, or anything."""
    make = {bool: boolean, int: integer, float: number, str: text}.get(base)
    return make(null=null) if make is not None else anything()


def rule_for(hint: Any) -> Rule:
    """The rule of an annotation alone (no metadata): its type, ``None`` when ``| None``."""
    base, null = _split_optional(hint)
    return _plain(base, null)


def option(default: Any = dataclasses.MISSING, *, help: str = "",
           choices: Iterable[str] | None = None, ge: float | None = None,
           gt: float | None = None, le: float | None = None, lt: float | None = None,
           null: bool | None = None, rule: Rule | None = None,
           default_factory: Any = dataclasses.MISSING) -> Any:
    """A dataclass field holding one option: its ``default`` (or ``default_factory``), its
    meaning ``help`` (one line: what ``--help`` prints), its ``choices``, its bounds
    (``ge``/``gt``: lowest, inclusive/exclusive; ``le``/``lt``: highest), whether ``null`` is
    accepted (default: when the annotation says ``| None``) or a :class:`Rule` of its own."""
    meta = Option(help=help, choices=None if choices is None else tuple(choices), ge=ge, gt=gt,
                  le=le, lt=lt, null=null, rule=rule)
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata={KEY: meta})
    return dataclasses.field(default=default, metadata={KEY: meta})


# --------------------------------------------------------------------------- reading


def options_of(owner: Any) -> dict[str, Option]:
    """The :class:`Option` of every field of dataclass ``owner`` made with :func:`option`."""
    return {f.name: f.metadata[KEY] for f in dataclasses.fields(owner) if KEY in f.metadata}


@functools.cache
def field_rules(owner: type) -> dict[str, Rule]:
    """A :class:`Rule` for every field of dataclass ``owner``: from its :func:`option`
    metadata, or from its annotation alone (``int``, ``float | None``, ...)."""
    hints = typing.get_type_hints(owner)
    out: dict[str, Rule] = {}
    for f in dataclasses.fields(owner):
        hint = hints.get(f.name, Any)
        meta = f.metadata.get(KEY)
        out[f.name] = meta.rule_for(hint) if meta is not None else rule_for(hint)
    return out


def signature_rules(owner: Any) -> dict[str, Rule]:
    """A :class:`Rule` for every named argument of function or class ``owner`` (not ``self``,
    ``*args``, ``**kwargs``), from its annotation alone: for a target that declares no options
    dataclass."""
    import inspect

    hints = typing.get_type_hints(owner if inspect.isfunction(owner) else owner.__init__)
    return {n: rule_for(hints.get(n, Any)) for n, p in inspect.signature(owner).parameters.items()
            if n != "self" and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)}


def option_help(owner: Any) -> dict[str, str]:
    """Each option's meaning as ``--help`` prints it: its ``help``, then its choices
    (``[auto | none | shared]``); options without either are left out."""
    out: dict[str, str] = {}
    for name, meta in options_of(owner).items():
        words = meta.help
        if meta.choices:
            words = f"{words} [{' | '.join(meta.choices)}]".strip()
        if words:
            out[name] = words
    return out


def check_options(obj: Any, prefix: str | None = None) -> None:
    """Check every field of dataclass instance ``obj`` against its rule (:func:`field_rules`);
    :class:`ConfigValueError` ``<prefix>.<field>: <value!r> is not <expected>`` for the first
    one that fails (``prefix``: the class's name unless given; ``""``: the field alone)."""
    owner = type(obj)
    label = owner.__name__ if prefix is None else prefix
    for name, rule in field_rules(owner).items():
        value = getattr(obj, name)
        if not rule.ok(value):
            key = f"{label}.{name}" if label else name
            raise ConfigValueError(f"{key}: {value!r} is not {rule.describe()}")

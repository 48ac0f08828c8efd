"""Nested configuration: recursive merge onto defaults, unknown keys rejected, values checked, YAML presets.

Every swappable unit (gate, feature extractor, matcher, index, ...) carries a ``default_conf`` dict with a comment
on each key and a ``conf_rules`` dict with the type and range of each key. A user's conf (from a YAML preset in
``configs/`` or a Python dict) is merged onto the defaults recursively; a key that the defaults do not know is an
error that names the key and the allowed ones, so a typo never silently falls back to a default; a value of the
wrong type or out of range is an error that names the key and what is allowed (``check_conf``, the one place where
values are validated). Both happen before anything is written.
"""

from __future__ import annotations

import copy
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Generic, Iterable, Mapping, TypeVar

import yaml

from .errors import ConfigError

__all__ = ["ConfigError", "merge_conf", "load_conf_file", "dump_conf", "Registry", "Rule", "Int", "Float", "Floats",
           "Bool", "Choice", "Text", "check_choice", "check_conf", "configure", "conf_diff", "conf_get", "presets", "PRESETS_DIR"]


def merge_conf(defaults: Mapping[str, Any], override: Mapping[str, Any] | None, where: str = "",
               strict: bool = True) -> dict[str, Any]:
    """Recursively merges ``override`` onto a deep copy of ``defaults``.

    Args:
        defaults: the unit's default conf; its keys are the only ones allowed.
        override: user values, possibly partial and nested; ``None`` means no change.
        where: dotted prefix used in error messages.
        strict: reject keys that ``defaults`` lacks. False merges two partial user confs (new keys are added; the
            result is checked later, when it is resolved onto real defaults).

    Returns:
        A new dict; neither input is modified.

    Raises:
        ConfigError: ``override`` names a key that ``defaults`` does not have (``strict``), or gives a plain value
            where a section (dict) is expected.
    """
    out = copy.deepcopy(dict(defaults))
    if override is None:
        return out
    if not isinstance(override, Mapping):
        raise ConfigError(f"config section '{where or '<root>'}' must be a mapping, got {type(override).__name__}")
    for key, value in override.items():
        name = f"{where}.{key}" if where else str(key)
        if key not in out and not strict:
            out[key] = copy.deepcopy(value)
            continue
        if key not in out:
            allowed = ", ".join(sorted(map(str, out))) or "(none)"
            raise ConfigError(f"unknown config key '{name}'; allowed here: {allowed}")
        if isinstance(out[key], Mapping):
            if value is None:
                continue
            out[key] = merge_conf(out[key], value, name, strict)
        else:
            out[key] = copy.deepcopy(value)
    return out


MAX_CONF_DEPTH = 32  #: a config file nested deeper than this is refused (the deepest conf has 4 levels)


class _UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a key given twice in one mapping (PyYAML would keep the last silently) and
    mappings or lists nested deeper than ``MAX_CONF_DEPTH`` (PyYAML would recurse until Python's stack runs out)."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        self._depth = getattr(self, "_depth", 0) + 1
        try:
            if self._depth > MAX_CONF_DEPTH:
                raise yaml.YAMLError(f"nested more than {MAX_CONF_DEPTH} levels deep")
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == "tag:yaml.org,2002:merge":
                continue  # ``<<: *anchor`` merges; a non-scalar key is refused by the merge onto the defaults
            key = self.construct_object(key_node, deep=True)
            if key in seen:
                raise yaml.YAMLError(f"key {key!r} given twice (line {key_node.start_mark.line + 1})")
            seen.add(key)
        return super().construct_mapping(node, deep)


#: the YAML presets shipped with the package (``--config paper`` = ``PRESETS_DIR / "paper.yaml"``): ``configs/``
#: beside the base layer's folder, in the repository and once installed
PRESETS_DIR = Path(__file__).resolve().parents[1] / "configs"


def presets() -> list[str]:
    """The names of the shipped presets (``default``, ``paper``, ``mild``, ...), sorted."""
    return sorted(p.stem for p in PRESETS_DIR.glob("*.yaml"))


def load_conf_file(path: str | Path) -> dict[str, Any]:
    """Reads a YAML (or JSON) config file into a dict; an empty file gives ``{}``. A bare name that is no file
    (``paper``) names a shipped preset (``presets``), so that ``--config paper`` works wherever the package is.

    Raises:
        ConfigError: the file is missing (and no preset of that name), unreadable, not YAML, not a mapping at the
            top level, a key given twice in one mapping, or nested deeper than ``MAX_CONF_DEPTH``.
    """
    path = Path(path)
    if not path.is_file() and len(path.parts) == 1 and not path.suffix and (PRESETS_DIR / f"{path}.yaml").is_file():
        path = PRESETS_DIR / f"{path}.yaml"
    if not path.is_file():
        hint = f" (presets: {', '.join(presets())})" if len(path.parts) == 1 and not path.suffix else ""
        raise ConfigError(f"config file not found: {path}{hint}")
    try:
        data = yaml.load(path.read_text(encoding="utf-8"), Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(f"cannot parse config file {path}: {first}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must hold a mapping at the top level")
    return data


def dump_conf(conf: Mapping[str, Any], path: str | Path) -> None:
    """Writes a resolved conf as YAML (keys in their default order), atomically."""
    from .files import write_text_atomic

    write_text_atomic(path, yaml.safe_dump(json.loads(json.dumps(conf)), sort_keys=False))


T = TypeVar("T")


class Registry(Generic[T]):
    """Name -> class table for swappable units, filled with the ``register`` decorator.

    Example:
        >>> FEATURES = Registry("features")
        >>> @FEATURES.register("sift")
        ... class SIFT: ...
        >>> FEATURES.get("sift")  # doctest: +SKIP
    """

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._table: dict[str, type[T]] = {}

    def register(self, name: str) -> Callable[[type[T]], type[T]]:
        def deco(cls: type[T]) -> type[T]:
            if name in self._table:
                raise ValueError(f"{self.kind} '{name}' registered twice")
            self._table[name] = cls
            return cls

        return deco

    def get(self, name: str) -> type[T]:
        """The class registered as ``name``.

        Raises:
            ConfigError: no such name (the message lists the available ones).
        """
        try:
            if not isinstance(name, str):
                raise KeyError(name)
            return self._table[name]
        except KeyError:
            raise ConfigError(f"unknown {self.kind} '{name}'; available: {', '.join(sorted(self._table))}") from None

    def names(self) -> list[str]:
        return sorted(self._table)


# ------------------------------------------------------------------------------------------- values: type and range
@dataclass(frozen=True)
class Rule:
    """The type and range one conf value must have; build with ``Int``, ``Float``, ``Bool``, ``Choice``, ``Text``."""

    kind: str  #: "int", "float", "bool", "choice" or "text"
    lo: float | None = None  #: lower bound (inclusive unless ``lo_open``)
    hi: float | None = None  #: upper bound (inclusive unless ``hi_open``)
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple[Any, ...] = ()  #: allowed values of a "choice"
    pattern: str | None = None  #: regular expression a "text" must match in full
    optional: bool = False  #: None is allowed
    auto: bool = False  #: the string "auto" is allowed (the value is then chosen by the code, e.g. calibrated)
    min_len: int = 1  #: fewest items of a "floats" list

    def describe(self) -> str:
        """What is allowed, in words: ``an integer >= 1``, ``one of ransac, magsac``, ..."""
        if self.kind == "choice":
            what = "one of " + ", ".join(map(str, self.choices))
        elif self.kind == "bool":
            what = "true or false"
        elif self.kind == "text":
            what = "a string" + (f" matching {self.pattern}" if self.pattern else "")
        else:
            what = {"int": "an integer", "float": "a finite number"}.get(
                self.kind, f"a list of at least {self.min_len} finite number(s), each")
            bounds = []
            if self.lo is not None:
                bounds.append(f"{'>' if self.lo_open else '>='} {self.lo:g}")
            if self.hi is not None:
                bounds.append(f"{'<' if self.hi_open else '<='} {self.hi:g}")
            what += (" " + " and ".join(bounds)) if bounds else ""
        return what + (" (or null)" if self.optional else "") + (" or 'auto'" if self.auto else "")

    def accepts(self, value: Any) -> bool:
        if value is None:
            return self.optional
        if self.auto and value == "auto":
            return True
        if self.kind == "floats":
            return isinstance(value, (list, tuple)) and len(value) >= self.min_len and all(
                Rule("float", self.lo, self.hi, self.lo_open, self.hi_open).accepts(v) for v in value)
        if self.kind == "bool":
            return isinstance(value, bool)
        if self.kind == "choice":
            return any(value == c and type(value) is type(c) for c in self.choices)
        if self.kind == "text":
            return isinstance(value, str) and (self.pattern is None or re.fullmatch(self.pattern, value) is not None)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        if self.kind == "int" and not isinstance(value, int):
            return False
        if not math.isfinite(value):
            return False
        if self.lo is not None and (value <= self.lo if self.lo_open else value < self.lo):
            return False
        return not (self.hi is not None and (value >= self.hi if self.hi_open else value > self.hi))


def Int(lo: int | None = None, hi: int | None = None, optional: bool = False, auto: bool = False) -> Rule:  # noqa: N802
    """An integer (not a bool, not 2.5) in ``[lo, hi]`` (or ``"auto"`` when ``auto``)."""
    return Rule("int", lo, hi, optional=optional, auto=auto)


def Float(lo: float | None = None, hi: float | None = None, lo_open: bool = False, hi_open: bool = False,  # noqa: N802
          optional: bool = False, auto: bool = False) -> Rule:
    """A finite number (an int is fine) between ``lo`` and ``hi``; ``*_open`` excludes the bound."""
    return Rule("float", lo, hi, lo_open, hi_open, optional=optional, auto=auto)


def Floats(lo: float | None = None, hi: float | None = None, min_len: int = 1) -> Rule:  # noqa: N802
    """A list of at least ``min_len`` finite numbers, each in ``[lo, hi]``."""
    return Rule("floats", lo, hi, min_len=min_len)


def Bool() -> Rule:  # noqa: N802
    """``true`` or ``false`` (not 0/1, not "yes")."""
    return Rule("bool")


def Choice(*choices: Any, optional: bool = False) -> Rule:  # noqa: N802
    """One of ``choices`` (same type: the string "1" is not the integer 1)."""
    return Rule("choice", choices=tuple(choices), optional=optional)


def check_choice(value: Any, choices: Iterable[Any], name: str) -> Any:
    """``value`` when it is one of ``choices`` (``Choice``'s rule: the same type too).

    Raises:
        ConfigError: another value, named as ``name`` (an option or a conf key).
    """
    rule = Choice(*choices)
    if not rule.accepts(value):
        raise ConfigError(f"{name} must be {rule.describe()}; got {value!r}")
    return value


def Text(pattern: str | None = None, optional: bool = False) -> Rule:  # noqa: N802
    """A string, matching ``pattern`` in full when given."""
    return Rule("text", pattern=pattern, optional=optional)


def check_conf(conf: Mapping[str, Any], rules: Mapping[str, Any], where: str = "") -> None:
    """Checks every value of a merged conf against its rule (nested dicts against nested rule dicts).

    Args:
        conf: a conf already merged onto its defaults (so it has exactly the default keys).
        rules: ``{key: Rule}`` or ``{section: {key: Rule}}``; the ``name`` key of a registry section needs none.
        where: dotted prefix for messages.

    Raises:
        ConfigError: ``'search.k' must be an integer >= 1; got 'ten' (str)``; or a key without a rule (a bug in the
            unit that declared it, caught by the tests).
    """
    for key, value in conf.items():
        name = f"{where}.{key}" if where else str(key)
        rule = rules.get(key)
        if isinstance(rule, Mapping):
            if not isinstance(value, Mapping):
                raise ConfigError(f"config section '{name}' must be a mapping, got {type(value).__name__}")
            check_conf(value, rule, name)
        elif rule is None:
            if key == "name":
                continue
            raise ConfigError(f"config key '{name}' has no validation rule (a bug: declare it in conf_rules)")
        elif not rule.accepts(value):
            raise ConfigError(f"'{name}' must be {rule.describe()}; got {value!r} ({type(value).__name__})")


def configure(unit: Any, conf: Mapping[str, Any] | None, where: str) -> dict[str, Any]:
    """A unit's conf: ``conf`` merged onto ``unit.default_conf`` and checked against ``unit.conf_rules``.

    Raises:
        ConfigError: an unknown key, or a value of the wrong type or range (named with ``where``).
    """
    merged = merge_conf(unit.default_conf, conf, where)
    check_conf(merged, getattr(unit, "conf_rules", {}), where)
    return merged


def conf_get(conf: Any, dotted: str) -> Any:
    """The value at a dotted key of a nested dict, None where a level is missing."""
    for key in dotted.split("."):
        conf = conf.get(key) if isinstance(conf, dict) else None
    return conf


def conf_diff(a: Any, b: Any, where: str = "") -> list[str]:
    """Dotted keys whose values differ between two nested dicts."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for k in sorted(set(a) | set(b), key=str)
                for d in conf_diff(a.get(k), b.get(k), f"{where}.{k}" if where else str(k))]
    return [] if a == b else [where]

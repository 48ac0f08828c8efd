"""Nested configuration: recursive merge onto defaults, unknown keys rejected, YAML presets.

Every swappable unit (gate, feature extractor, matcher, index, ...) carries a ``default_conf`` dict with a comment
on each key. A user's conf (from a YAML preset in ``configs/`` or a Python dict) is merged onto it recursively; a
key that the defaults do not know is an error that names the key and the allowed ones, so a typo never silently
falls back to a default.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any, Callable, Generic, Mapping, TypeVar

import yaml

__all__ = ["ConfigError", "merge_conf", "load_conf_file", "dump_conf", "Registry"]


class ConfigError(ValueError):
    """A configuration (or an input named by it) is invalid; the message says what and where."""


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


def load_conf_file(path: str | Path) -> dict[str, Any]:
    """Reads a YAML (or JSON) config file into a dict; an empty file gives ``{}``.

    Raises:
        ConfigError: the file is missing, unreadable, or not a mapping at the top level.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f"cannot parse config file {path}: {err}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must hold a mapping at the top level")
    return data


def dump_conf(conf: Mapping[str, Any], path: str | Path) -> None:
    """Writes a resolved conf as YAML (keys in their default order)."""
    Path(path).write_text(yaml.safe_dump(json.loads(json.dumps(conf)), sort_keys=False))


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
        try:
            return self._table[name]
        except KeyError:
            raise ConfigError(f"unknown {self.kind} '{name}'; available: {', '.join(sorted(self._table))}") from None

    def names(self) -> list[str]:
        return sorted(self._table)

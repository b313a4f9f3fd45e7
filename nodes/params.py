"""Typed node parameters: a dataclass per node holds the defaults; launch files and
`--param key=value` override them, checked by type before anything starts."""
from __future__ import annotations

import dataclasses
import math
import types
import typing
from typing import Any

import yaml

from fv_algos.yaml_loader import YamlLoader


class ParamError(ValueError):
    """A parameter that does not exist or has the wrong type; names the key (also in
    `key`, None when the error concerns the params as a whole)."""

    def __init__(self, message: str, key: str | None = None) -> None:
        super().__init__(message)
        self.key = key


def _accepts(tp: Any, value: Any) -> bool:
    origin = typing.get_origin(tp)
    if tp is Any:
        return True
    if origin in (typing.Union, types.UnionType):
        return any(_accepts(arg, value) for arg in typing.get_args(tp))
    if tp is type(None):
        return value is None
    if tp is bool:
        return isinstance(value, bool)
    if tp is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if origin in (list, tuple):
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            return False
        if origin is tuple and args and args[-1] is not Ellipsis:
            return len(value) == len(args) and all(_accepts(a, v) for a, v in zip(args, value))
        return all(_accepts(args[0], v) for v in value) if args else True
    if origin is dict:
        return isinstance(value, dict)
    return isinstance(value, tp)


def _coerce(tp: Any, value: Any) -> Any:
    if tp is float and isinstance(value, int):
        return float(value)
    if typing.get_origin(tp) is tuple and isinstance(value, list):
        return tuple(value)
    return value


def parse_text(text: str) -> Any:
    """A command-line value as YAML would read it ("0.5" -> 0.5, "1e-3" -> 0.001, "[1, 2]" -> list)."""
    try:
        return yaml.load(text, Loader=YamlLoader)
    except yaml.YAMLError:
        return text


def param_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def build_params(cls: type, overrides: dict[str, Any], where: str = "params", what: str = "param") -> Any:
    """An instance of dataclass `cls` with `overrides` applied; ParamError names the key (a `what`: "field"
    for a message's), the expected type and `where` the value came from."""
    hints = param_types(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    values = {}
    for key, value in overrides.items():
        if key not in names:
            raise ParamError(f"{where}: unknown {what} {key!r}; known: {sorted(names)}", key)
        if isinstance(value, str) and hints[key] is not str and not _accepts(hints[key], value):
            value = parse_text(value)
        if not _accepts(hints[key], value):
            raise ParamError(f"{where}: {what} {key!r} = {value!r} is not of type {_type_name(hints[key])}", key)
        if hints[key] is float and not math.isfinite(value):  # nan / inf: no rate, period or time means that
            raise ParamError(f"{where}: {what} {key!r} = {value!r} is not a finite number", key)
        values[key] = _coerce(hints[key], value)
    try:
        return cls(**values)
    except ValueError as exc:
        raise ParamError(f"{where}: {exc}") from None


def _type_name(tp: Any) -> str:
    """`tp` as written in the params dataclass: `float`, `list[int]` (a generic's __name__ is its origin's)."""
    if typing.get_origin(tp) is None and hasattr(tp, "__name__"):
        return tp.__name__
    return str(tp).replace("typing.", "")


def parse_assignments(items: list[str], where: str = "--param") -> dict[str, str]:
    """["k=v", ...] -> {k: v}; ParamError for an item without '='."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ParamError(f"{where}: {item!r} is not key=value")
        out[key.strip()] = value
    return out


def describe(cls: type) -> list[tuple[str, str, Any]]:
    """(name, type, default) of each param, for `fv node info`."""
    hints = param_types(cls)
    return [(f.name, _type_name(hints[f.name]), f.default if f.default is not dataclasses.MISSING
             else f.default_factory()) for f in dataclasses.fields(cls)]

"""Build frozen dataclasses from plain YAML data, with errors that name the field.

Every error is a ConfigError with one line: ``<origin>: <field>: expected <what>, got <value>``
where origin is the file (or ``--set``) the offending value came from.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import types
import typing
from collections.abc import Callable, Mapping
from typing import Any, Literal, TypeVar, Union, get_args, get_origin, get_type_hints

from redistro.errors import ConfigError, shown

T = TypeVar("T")
_INT_LIMIT = 2**63  # larger integers are refused before any conversion

# Maps a dotted field path to where its value came from (file name or "--set").
Origins = Mapping[str, str]


def _origin(origins: Origins, path: str, default: str) -> str:
    # The most specific origin that covers this path wins.
    best, best_len = default, -1
    for key, where in origins.items():
        if (path == key or path.startswith(key + ".")) and len(key) > best_len:
            best, best_len = where, len(key)
    return best


def _show(value: Any) -> str:
    return shown(value)


class _Ctx:
    def __init__(self, default_origin: str, origins: Origins) -> None:
        self.default_origin = default_origin
        self.origins = origins

    def fail(self, path: str, expected: str, got: Any) -> ConfigError:
        where = _origin(self.origins, path, self.default_origin)
        return ConfigError(f"{where}: {path or '<top>'}: expected {expected}, got {_show(got)}")

    def unknown(self, path: str, known: list[str]) -> ConfigError:
        where = _origin(self.origins, path, self.default_origin)
        if len(path) > 120:
            path = path[:117] + "..."
        return ConfigError(f"{where}: {path}: unknown key (known: {', '.join(sorted(known))})")


def build(cls: type[T], data: Any, *, origin: str, origins: Origins | None = None) -> T:
    """Validate ``data`` against dataclass ``cls`` and return an instance."""
    ctx = _Ctx(origin, origins or {})
    return typing.cast(T, _build_dataclass(cls, data, "", ctx))


@functools.cache
def _shape(cls: type) -> tuple[dict[str, Any], dict[str, dataclasses.Field[Any]]]:
    """A dataclass's resolved type hints and its fields (resolving string
    annotations compiles code: once per class)."""
    fields = {f.name: f for f in dataclasses.fields(cls) if not f.metadata.get("internal")}
    return get_type_hints(cls), fields


def _build_dataclass(cls: type, data: Any, path: str, ctx: _Ctx) -> Any:
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ctx.fail(path, f"a mapping of {cls.__name__} fields", data)
    hints, fields = _shape(cls)
    for key in data:
        if key not in fields:
            sub = f"{path}.{key}" if path else str(key)
            raise ctx.unknown(sub, list(fields))
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        sub = f"{path}.{name}" if path else name
        if name in data:
            kwargs[name] = _convert(hints[name], data[name], sub, ctx, dict(f.metadata))
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            where = _origin(ctx.origins, sub, ctx.default_origin)
            raise ConfigError(f"{where}: {sub}: missing (expected {_describe(hints[name])})")
    return cls(**kwargs)


def _describe(tp: Any) -> str:
    origin = get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in get_args(tp))
    if origin is list:
        return f"a list of {_describe(get_args(tp)[0])}"
    if origin is dict:
        return f"a mapping of {_describe(get_args(tp)[1])}"
    if origin in (Union, types.UnionType):
        return " or ".join(_describe(a) for a in get_args(tp))
    if tp is type(None):
        return "null"
    if dataclasses.is_dataclass(tp):
        return f"a mapping of {getattr(tp, '__name__', tp)} fields"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(
        tp, str(tp)
    )


def _bounds_text(meta: dict[str, Any]) -> str:
    parts = []
    for key, sym in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
        if key in meta:
            parts.append(f"{sym} {meta[key]}")
    return " and ".join(parts)


_CHECKS: dict[str, Callable[[float, float], bool]] = {
    "gt": lambda v, b: v > b,
    "ge": lambda v, b: v >= b,
    "lt": lambda v, b: v < b,
    "le": lambda v, b: v <= b,
}


def _check_bounds(value: float, path: str, ctx: _Ctx, meta: dict[str, Any], what: str) -> None:
    for key, check in _CHECKS.items():
        if key in meta and not check(value, meta[key]):
            raise ctx.fail(path, f"{what} {_bounds_text(meta)}", value)


def _convert(tp: Any, value: Any, path: str, ctx: _Ctx, meta: dict[str, Any]) -> Any:
    origin = get_origin(tp)
    if origin in (Union, types.UnionType):
        options = get_args(tp)
        if value is None and type(None) in options:
            return None
        for option in options:
            if option is type(None):
                continue
            try:
                return _convert(option, value, path, ctx, meta)
            except ConfigError:
                continue
        raise ctx.fail(path, _describe(tp), value)
    if origin is Literal:
        if value not in get_args(tp) or isinstance(value, bool):
            raise ctx.fail(path, _describe(tp), value)
        return value
    if origin is list:
        if not isinstance(value, list):
            raise ctx.fail(path, _describe(tp), value)
        if len(value) < meta.get("min_len", 0):
            raise ctx.fail(path, f"a list of at least {meta['min_len']} items", value)
        if "len" in meta and len(value) != meta["len"] and not (meta.get("optional") and not value):
            alt = " (or an empty list)" if meta.get("optional") else ""
            raise ctx.fail(path, f"a list of exactly {meta['len']} items{alt}", value)
        meta = {k: v for k, v in meta.items() if k not in ("len", "min_len", "optional")}
        (item_tp,) = get_args(tp)
        return [_convert(item_tp, v, f"{path}[{i}]", ctx, meta) for i, v in enumerate(value)]
    if origin is dict:
        if not isinstance(value, Mapping):
            raise ctx.fail(path, _describe(tp), value)
        _key_tp, val_tp = get_args(tp)
        allowed = meta.get("keys")
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise ctx.fail(path, "string keys", k)
            if allowed is not None and k not in allowed:
                raise ctx.unknown(f"{path}.{k}", list(allowed))
            out[k] = _convert(val_tp, v, f"{path}.{k}", ctx, meta)
        return out
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return _build_dataclass(tp, value, path, ctx)
    if tp is bool:
        if not isinstance(value, bool):
            raise ctx.fail(path, "true or false", value)
        return value
    if isinstance(value, int) and not -_INT_LIMIT <= value <= _INT_LIMIT:
        what = "an integer" if tp is int else "a number" if tp is float else "a value"
        raise ctx.fail(path, f"{what} within +-2^63", value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ctx.fail(path, "an integer" + _suffix(meta), value)
        _check_bounds(value, path, ctx, meta, "an integer")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ctx.fail(path, "a number" + _suffix(meta), value)
        if not math.isfinite(value):
            raise ctx.fail(path, "a finite number", value)
        _check_bounds(float(value), path, ctx, meta, "a number")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ctx.fail(path, "a string", value)
        return value
    raise TypeError(f"config model uses an unsupported type {tp!r} at {path}")


def _suffix(meta: dict[str, Any]) -> str:
    bounds = _bounds_text(meta)
    return f" {bounds}" if bounds else ""

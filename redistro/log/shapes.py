"""What the log tools read besides the messages, checked before it is used:
``summary.json`` and the session log's metadata.

A shape is a type (or a tuple of types) a value must be, a dict of the
shapes of the keys a mapping may hold (others are let through: the
documents grow), :class:`ListOf` a shape (of a given length, or any), or
``{"*": shape}`` for a mapping whose every value has that shape. :func:`check` raises a
:class:`~redistro.errors.ConfigError` of one line naming the document and
the key path of the first value that does not fit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from redistro.errors import ConfigError, shown


@dataclass(frozen=True)
class ListOf:
    item: Any
    length: int | None = None


NUM = (int, float)
OPT_NUM = (int, float, type(None))
OPT_STR = (str, type(None))
OPT_INT = (int, type(None))

SUMMARY: dict[str, Any] = {
    "task": OPT_STR,
    "kind": OPT_STR,
    "result": OPT_STR,
    "reason": OPT_STR,
    "started": (str, int, float, type(None)),
    "ended": (str, int, float, type(None)),
    "inserted": (bool, type(None)),
    "insertion_depth_m": OPT_NUM,
    "segments": ListOf(
        {
            "name": OPT_STR,
            "robot": OPT_STR,
            "scheme": OPT_STR,
            "duration_s": OPT_NUM,
            "cycle": OPT_INT,
            "final_pose_error": (
                {"position_m": NUM, "orientation_rad": NUM},
                type(None),
            ),
        }
    ),
    "nodes": {
        "*": {
            "result": OPT_STR,
            "cycles": OPT_INT,
            "rate_hz": OPT_NUM,
            "overruns": OPT_INT,
            "lateness_us": ({"p99": OPT_NUM}, type(None)),
        }
    },
    "log": {"nodes": {"*": {"recorded": OPT_INT, "dropped": OPT_INT}}},
}

# the session log's metadata records, by name
META: dict[str, Any] = {
    "redistro.meta": {
        "task": OPT_STR,
        "physics_hz": NUM,
        "hole_xyz_m": (ListOf(NUM, 3), type(None)),
        "robots": {"*": {"peg": (ListOf(NUM, 3), type(None)), "base_xyz_m": ListOf(NUM, 3)}},
    },
    "redistro.node": {"node": str, "processes": ListOf(str)},
}


def check(value: Any, shape: Any, where: str, path: str = "") -> None:
    """``value`` fits ``shape``, or ConfigError naming ``where`` and the path."""
    if isinstance(shape, tuple) and any(isinstance(s, dict | ListOf) for s in shape):
        # alternatives with structure (a mapping or null, ...): the first that fits
        errors = []
        for s in shape:
            try:
                check(value, s, where, path)
                return
            except ConfigError as exc:
                errors.append(exc)
        raise errors[0]
    if isinstance(shape, ListOf):
        if not isinstance(value, list) or shape.length not in (None, len(value)):
            _fail(where, path, f"a list of {shape.length or 'any number of'} items", value)
        for i, item in enumerate(value):
            check(item, shape.item, where, f"{path}[{i}]")
        return
    if isinstance(shape, dict):
        if not isinstance(value, dict):
            _fail(where, path, "a mapping", value)
        every = shape.get("*")
        for key, item in value.items():
            sub = shape.get(key, every)
            if sub is not None:
                check(item, sub, where, f"{path}.{key}" if path else str(key))
        return
    kinds = shape if isinstance(shape, tuple) else (shape,)
    # a bool is an int to Python, not to a document's reader
    if isinstance(value, bool) and bool not in kinds:
        _fail(where, path, _names(kinds), value)
    if not isinstance(value, kinds):
        _fail(where, path, _names(kinds), value)
    if isinstance(value, float) and value != value and float in kinds:
        return  # NaN is a number the tools print as nan


def _names(kinds: tuple[type, ...]) -> str:
    words = {int: "an integer", float: "a number", str: "a string", bool: "true or false"}
    out = [words.get(k, "null" if k is type(None) else k.__name__) for k in kinds]
    if "an integer" in out and "a number" in out:
        out.remove("an integer")
    return " or ".join(out)


def _fail(where: str, path: str, expected: str, value: Any) -> None:
    raise ConfigError(f"{where}: {path or '<top>'}: expected {expected}, got {shown(value)}")

"""Load the YAML config, apply ``--set dotted.key=value`` overrides, validate."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path
from typing import Any, TypeVar, get_args, get_origin, get_type_hints

from redistro.config.model import Config
from redistro.config.validate import build
from redistro.errors import ConfigError, clipped, shown

DEFAULT_CONFIG_PATH = Path("config/redistro.yaml")


def parse_override(text: str) -> tuple[list[str], Any]:
    """``a.b.c=value`` -> (["a", "b", "c"], value parsed as YAML), through the
    same loader as the files (:func:`redistro.config.inputs.load_yaml`:
    no aliases or anchors, nesting and integers bounded) and at most
    ``MAX_SET_BYTES`` long."""
    from redistro.config.inputs import MAX_SET_BYTES, load_yaml

    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or not key or any(not part for part in key.split(".")):
        raise ConfigError(f"--set {clipped(text)}: expected dotted.key=value")
    if len(raw) > MAX_SET_BYTES:
        raise ConfigError(
            f"--set {clipped(key)}: a value of {len(raw)} characters (at most {MAX_SET_BYTES})"
        )
    try:
        value = load_yaml(raw, "<value>") if raw.strip() else ""
    except ConfigError as exc:
        why = str(exc).partition("invalid YAML ")[2] or str(exc)
        raise ConfigError(f"--set {clipped(key)}: value is not valid YAML {why}") from None
    return key.split("."), value


def read_yaml(path: Path, what: str = "config") -> dict[str, Any]:
    """A YAML mapping from a regular file of at most 1 MiB of UTF-8, without
    aliases, anchors or duplicate keys (redistro/config/inputs.py)."""
    from redistro.config.inputs import load_yaml, read_text

    data = load_yaml(read_text(path, what), path)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: <top>: expected a mapping of {what} sections, got {_cut(data)}")
    return data


def _cut(value: Any, n: int = 60) -> str:
    return shown(value, n)


def _known_path(cls: type, parts: list[str]) -> bool:
    """Whether a dotted path names a field (or a key inside a dict field)."""
    tp: Any = cls
    for part in parts:
        if dataclasses.is_dataclass(tp) and isinstance(tp, type):
            names = {f.name: f for f in dataclasses.fields(tp) if not f.metadata.get("internal")}
            if part not in names:
                return False
            tp = get_type_hints(tp)[part]
        elif get_origin(tp) is dict:
            tp = get_args(tp)[1]  # any key is addressable; validation judges it
        else:
            return False
    return True


def load_config(path: Path | str | None = None, overrides: list[str] | None = None) -> Config:
    """Read ``path`` (default: config/redistro.yaml when present), apply overrides.

    Raises ConfigError with one line naming the file or ``--set``, the field,
    what was expected and what was found.
    """
    origin = "<defaults>"
    data: dict[str, Any] = {}
    origins: dict[str, str] = {}  # (--set)
    in_file: dict[str, str] = {}  # (a file that extends another: its own values)
    if path is None and DEFAULT_CONFIG_PATH.exists():
        path = DEFAULT_CONFIG_PATH
    if path is not None:
        path = Path(path)
        data = read_yaml(path)
        origin = str(path)
        if "extends" in data:
            data, origin = _extended(path, data, in_file)
    data = copy.deepcopy(data)
    origins.update(_apply_overrides(data, overrides or [], origin))
    cfg = build(Config, data, origin=origin, origins={**in_file, **origins})
    source = str(path) if path is not None else str(DEFAULT_CONFIG_PATH)
    cfg = dataclasses.replace(cfg, source=source, overridden=tuple(origins))
    from redistro.config.checks import check_config

    check_config(cfg)
    return cfg


def reload_config(data: dict[str, Any], overrides: list[str], origin: str) -> Config:
    """A config :func:`resolved` gave (a run folder's), ``overrides`` on top,
    checked as a loaded one (``redistro replay``)."""
    internal = {f.name for f in dataclasses.fields(Config) if f.metadata.get("internal")}
    base = copy.deepcopy({k: v for k, v in data.items() if k not in internal})
    origins = _apply_overrides(base, overrides, origin)
    cfg = build(Config, base, origin=origin, origins=origins)
    kept = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items() if k in internal}
    cfg = dataclasses.replace(cfg, **kept)  # type: ignore[arg-type]
    from redistro.config.checks import check_config

    check_config(cfg)
    return cfg


def _apply_overrides(data: dict[str, Any], overrides: list[str], origin: str) -> dict[str, str]:
    """``--set`` values into ``data`` (in place); their origins."""
    origins: dict[str, str] = {}
    defaults = dataclasses.asdict(Config())
    for text in overrides:
        parts, value = parse_override(text)
        dotted = ".".join(parts)
        if not _known_path(Config, parts):
            raise ConfigError(f"--set {clipped(dotted)}: no such config key")
        node = data
        default: Any = defaults
        for i, part in enumerate(parts[:-1]):
            default = default.get(part) if isinstance(default, dict) else None
            child = node.get(part)
            if child is None:
                # not in the file: start from the default (a dict of robots keeps the others)
                child = node[part] = copy.deepcopy(default) if isinstance(default, dict) else {}
            if not isinstance(child, dict):
                where = ".".join(parts[: i + 1])
                raise ConfigError(f"{origin}: {where}: expected a mapping, got {_cut(child)}")
            node = child
        node[parts[-1]] = value
        origins[dotted] = "--set"
    return origins


def _extended(path: Path, data: dict[str, Any], origins: dict[str, str]) -> tuple[Any, str]:
    """A config file that extends another (``extends: FILE``, relative to its
    own folder): the other's values with this file's on top, mappings merged
    key by key; an error names the file its value came from."""
    name = data.pop("extends")
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{path}: extends: expected a config file's name, got {_cut(name)}")
    base_path = path.parent / name
    base = read_yaml(base_path)
    if "extends" in base:
        raise ConfigError(f"{base_path}: extends: a config that {path} extends extends no other")

    def merge(under: Any, over: Any, at: str) -> Any:
        if isinstance(under, dict) and isinstance(over, dict):
            out = dict(under)
            for k, v in over.items():
                out[k] = merge(under.get(k), v, f"{at}.{k}" if at else str(k))
            return out
        origins[at] = str(path)
        return over

    return merge(base, data, ""), str(base_path)


T = TypeVar("T")


def resolved(obj: Any) -> dict[str, Any]:
    """A loaded, checked config or task as plain data (JSON), its internal
    fields included: what the session owner hands down to every process of
    a session, so that none of them reads the YAML again (a file edited
    during start-up cannot give two processes different limits)."""

    def plain(v: Any) -> Any:
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            out = {}
            for f in dataclasses.fields(v):
                x = getattr(v, f.name)
                if _is_default(f, x):
                    continue  # left out: rebuilt from the default, which may not pass as a value
                out[f.name] = plain(x)
            return out
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items()}
        if isinstance(v, list | tuple):
            return [plain(x) for x in v]
        return v

    out: dict[str, Any] = plain(obj)
    return out


def _is_default(f: dataclasses.Field[Any], value: Any) -> bool:
    """Whether ``value`` is an unset container field's default (an empty
    joint goal, say, which is unset and not a goal of no joints)."""
    if f.default_factory is not dataclasses.MISSING:
        default = f.default_factory()
    elif f.default is not dataclasses.MISSING:
        default = f.default
    else:
        return False
    return isinstance(default, list | dict | tuple) and not default and value == default


def from_resolved(cls: type[T], data: dict[str, Any]) -> T:
    """The config or task :func:`resolved` gave, rebuilt (and its types
    checked again, cheaply) without any file."""
    fields = dataclasses.fields(cls)  # type: ignore[arg-type]
    internal = {f.name for f in fields if f.metadata.get("internal")}
    obj = build(cls, {k: v for k, v in data.items() if k not in internal}, origin="<resolved>")
    kept = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items() if k in internal}
    return dataclasses.replace(obj, **kept)  # type: ignore[type-var]

"""Reading files that come from users: only regular files, with a size cap,
UTF-8, and YAML without the features that make it dangerous.

- ``read_text``: a regular file (a FIFO, a device such as /dev/zero or a
  folder is refused before it is opened for reading), at most ``limit``
  bytes, decoded as UTF-8.
- ``load_yaml``: YAML 1.1 through the safe loader, with anchors and aliases
  refused (an alias bomb expands a few hundred bytes into gigabytes) and a
  key given twice in one mapping refused (otherwise the last would win
  silently); nesting deeper than ``MAX_DEPTH`` is refused.
- ``load_json``: JSON nested no deeper than ``MAX_DEPTH``.

Every refusal is a ConfigError of one line naming the file.
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path
from typing import Any

import yaml

from redistro.errors import ConfigError, clipped, shown

MAX_BYTES = 1 << 20  # a config, task or positions file is a few kB
MAX_DEPTH = 64
MAX_DIGITS = 30  # an integer longer than this is refused before it is converted
MAX_SET_BYTES = 1 << 16  # one --set value


def read_text(path: Path | str, what: str = "file", limit: int = MAX_BYTES) -> str:
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read {what} ({exc.strerror})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise ConfigError(f"{path}: cannot read {what} (not a regular file)")
        if st.st_size > limit:
            raise ConfigError(f"{path}: cannot read {what} ({st.st_size} bytes, more than {limit})")
        data = os.read(fd, limit + 1)
        if len(data) > limit:
            raise ConfigError(f"{path}: cannot read {what} (more than {limit} bytes)")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read {what} ({exc.strerror})") from None
    finally:
        os.close(fd)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{path}: not UTF-8 text (byte {exc.start}: {data[exc.start : exc.start + 1]!r})"
        ) from None


_LOADER: Any = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml when present


class _Refused(Exception):
    def __init__(self, problem: str, mark: Any) -> None:
        super().__init__(problem)
        self.problem = problem
        self.problem_mark = mark


_INT_TAG = "tag:yaml.org,2002:int"
_RESOLVER = yaml.resolver.Resolver()


def _is_int(text: str) -> bool:
    """Whether YAML reads this plain scalar as an integer."""
    tag: str = _RESOLVER.resolve(yaml.ScalarNode, text, (True, False))  # type: ignore[no-untyped-call]
    return tag == _INT_TAG


def _scan_events(text: str) -> None:
    """Aliases, anchors, deep nesting and integers too long to convert, from
    the event stream (iterative: nothing recurses before the depth is known,
    nothing is converted before its size is)."""
    depth = 0
    for ev in yaml.parse(text, Loader=_LOADER):
        if (
            isinstance(ev, yaml.ScalarEvent)
            and ev.implicit[0]
            and len(ev.value) > MAX_DIGITS
            and _is_int(ev.value)
        ):
            raise _Refused(
                f"an integer of {len(ev.value)} characters (at most {MAX_DIGITS})",
                ev.start_mark,
            )
        if isinstance(ev, yaml.AliasEvent):
            raise _Refused("aliases (*name) are not allowed", ev.start_mark)
        if getattr(ev, "anchor", None) is not None:
            raise _Refused("anchors (&name) are not allowed", ev.start_mark)
        if isinstance(ev, yaml.MappingStartEvent | yaml.SequenceStartEvent):
            depth += 1
            if depth > MAX_DEPTH:
                raise _Refused(f"nested deeper than {MAX_DEPTH} levels", ev.start_mark)
        elif isinstance(ev, yaml.MappingEndEvent | yaml.SequenceEndEvent):
            depth -= 1


def _check_keys(node: Any) -> None:
    """No key given twice in one mapping."""
    if isinstance(node, yaml.MappingNode):
        seen: set[tuple[str, str]] = set()
        for key, value in node.value:
            if isinstance(key, yaml.ScalarNode):
                ident = (key.tag, key.value)
                if ident in seen:
                    raise _Refused(f"key {_cut(key.value)} given twice", key.start_mark)
                seen.add(ident)
            else:
                raise _Refused("a mapping key that is not a plain value", key.start_mark)
            _check_keys(value)
    elif isinstance(node, yaml.SequenceNode):
        for item in node.value:
            _check_keys(item)


def _cut(value: Any, n: int = 60) -> str:
    return shown(value, n)


def load_yaml(text: str, path: Path | str) -> Any:
    """YAML through the safe loader, without anchors, aliases (an alias bomb
    expands a few hundred bytes into gigabytes) or keys given twice (the last
    would win silently), nested at most MAX_DEPTH levels."""
    try:
        _scan_events(text)
        _check_keys(yaml.compose(text, Loader=_LOADER))
        return yaml.load(text, Loader=_LOADER)
    except (yaml.YAMLError, _Refused) as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        if "maximum nesting depth" in problem:
            # libyaml (PyYAML >= 6.0.3 wheels) has a nesting limit of its own,
            # far above ours, and may reach it while scanning ahead: the file
            # is deeper than ours either way, so one message for both.
            problem = f"nested deeper than {MAX_DEPTH} levels"
        problem = problem if len(problem) <= 120 else problem[:117] + "..."
        raise ConfigError(f"{where}: invalid YAML ({problem})") from None
    except RecursionError:
        raise ConfigError(f"{path}: invalid YAML (nested too deep)") from None
    except (ValueError, OverflowError) as exc:  # a value its constructor cannot make
        raise ConfigError(f"{path}: invalid YAML ({clipped(str(exc), 120)})") from None


def load_json(text: str) -> Any:
    """json.loads with a nesting limit (ValueError beyond it)."""
    depth = 0
    in_string = escaped = False
    for ch in text:  # a cheap scan: brackets outside strings
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            if depth > MAX_DEPTH:
                raise ValueError(f"nested deeper than {MAX_DEPTH} levels")
        elif ch in "]}":
            depth -= 1
    return json.loads(text)

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

from redistro.errors import ConfigError

MAX_BYTES = 1 << 20  # a config, task or positions file is a few kB
MAX_DEPTH = 64


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


def _scan_events(text: str) -> None:
    """Aliases, anchors and deep nesting, from the event stream (iterative:
    nothing recurses before the depth is known)."""
    depth = 0
    for ev in yaml.parse(text, Loader=_LOADER):
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
    text = repr(value)
    return text if len(text) <= n else text[: n - 3] + "..."


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


def _cut_text(text: str, n: int = 60) -> str:
    return text if len(text) <= n else text[: n - 3] + "..."


def _existing_ancestor(p: Path) -> Path:
    p = p.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_out_dir(path: str, option: str) -> None:
    """A folder the command will write into: an existing writable folder, or
    one that can be created (its nearest existing ancestor a writable folder)."""
    p = Path(path)
    shown = _cut_text(path)
    if p.exists() or p.is_symlink():
        if not p.is_dir():
            raise ConfigError(f"{option} {shown}: exists and is not a folder")
        if not os.access(p, os.W_OK | os.X_OK):
            raise ConfigError(f"{option} {shown}: the folder is not writable")
        return
    up = _existing_ancestor(p)
    if not up.is_dir():
        raise ConfigError(f"{option} {shown}: cannot be created ({up} is not a folder)")
    # the first missing folder, made and removed again: what the OS says
    # (os.access answers yes to root everywhere, /proc included)
    first = p.absolute()
    while first.parent != up:
        first = first.parent
    try:
        os.mkdir(first, 0o700)
    except OSError as exc:
        raise ConfigError(f"{option} {shown}: cannot be created ({exc.strerror})") from None
    os.rmdir(first)


def check_out_file(path: str, option: str) -> None:
    """A file the command will write: not a folder, its folder writable or creatable."""
    p = Path(path)
    shown = _cut_text(path)
    if p.is_dir():
        raise ConfigError(f"{option} {shown}: is a folder, expected a file name")
    if p.exists() and not p.is_file():
        raise ConfigError(f"{option} {shown}: exists and is not a regular file")
    if p.exists() and not os.access(p, os.W_OK):
        raise ConfigError(f"{option} {shown}: the file is not writable")
    check_out_dir(str(p.absolute().parent), option)

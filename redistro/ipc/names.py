"""Every IPC name derives here from (session id, node, object).

POSIX shared memory ``/redistro.<session>.<node>.<object>`` appears as
``/dev/shm/redistro.<session>.<node>.<object>``; a named semaphore of the same
name appears as ``/dev/shm/sem.redistro.<session>.<node>.<object>``.
"""

from __future__ import annotations

import os
import re
import secrets
import tempfile
import time
from pathlib import Path

PREFIX = "redistro"
SHM_DIR = Path("/dev/shm")
_SESSION_RE = re.compile(r"^\d{8}T\d{6}-[0-9a-f]{6}$")
_PART_RE = re.compile(r"^[A-Za-z0-9_\-]+(\.[A-Za-z0-9_\-]+)*$")


def new_session_id() -> str:
    """A sortable, unique session id such as ``20261121T193000-a1b2c3``."""
    return time.strftime("%Y%m%dT%H%M%S", time.gmtime()) + "-" + secrets.token_hex(3)


def is_session_id(text: str) -> bool:
    return bool(_SESSION_RE.match(text))


def object_name(session_id: str, node: str, obj: str) -> str:
    """The POSIX name (leading slash) of object ``obj`` of ``node`` in a session."""
    if not is_session_id(session_id):
        raise ValueError(f"not a session id: {session_id!r}")
    for part in (node, obj):
        if not _PART_RE.match(part):
            raise ValueError(f"bad IPC name part {part!r}")
    return f"/{PREFIX}.{session_id}.{node}.{obj}"


def session_of_entry(entry: str) -> str | None:
    """Session id of a /dev/shm entry that belongs to redistro, else None."""
    if entry.startswith("sem."):
        entry = entry[4:]
    parts = entry.split(".", 2)
    if len(parts) < 2 or parts[0] != PREFIX or not is_session_id(parts[1]):
        return None
    return parts[1]


def entry_to_name(entry: str) -> tuple[str, str]:
    """(/dev/shm entry) -> (kind, POSIX name): kind is ``sem`` or ``shm``."""
    if entry.startswith("sem."):
        return "sem", "/" + entry[4:]
    return "shm", "/" + entry


def runtime_dir() -> Path:
    """Where session locks and manifests live (one per machine and user).

    Every redistro process of this user must agree on it, because the reaper
    judges liveness by the locks found here. ``REDISTRO_RUNTIME_DIR`` overrides.
    """
    env = os.environ.get("REDISTRO_RUNTIME_DIR")
    if env:
        return Path(env)
    return Path(tempfile.gettempdir()) / f"{PREFIX}-{os.getuid()}"

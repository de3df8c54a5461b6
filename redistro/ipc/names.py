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
    """Where session locks and manifests live (one per machine and user):
    ``$XDG_RUNTIME_DIR/redistro`` when that names a folder, else
    ``/tmp/redistro-<uid>``; ``REDISTRO_RUNTIME_DIR`` overrides both.

    Every redistro process of this user must agree on it, because the reaper
    judges liveness by the locks found here (children inherit the environment).
    """
    env = os.environ.get("REDISTRO_RUNTIME_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_RUNTIME_DIR")
    if xdg and os.path.isabs(xdg) and os.path.isdir(xdg):
        return Path(xdg) / PREFIX
    return Path(tempfile.gettempdir()) / f"{PREFIX}-{os.getuid()}"


def checked_runtime_dir(create: bool = True) -> Path | None:
    """The runtime directory, created 0700 when missing (``create``), and
    checked: a real folder (not a symlink), owned by this user, with no
    access for group or others. IPCError naming what is wrong otherwise
    (another user could plant locks or manifests there). None when it does
    not exist and ``create`` is false."""
    import stat

    from redistro.errors import IPCError

    root = runtime_dir()
    if create:
        try:
            os.mkdir(root, 0o700)
        except FileExistsError:
            pass
        except OSError as exc:
            raise IPCError(f"runtime directory {root}: cannot create it ({exc.strerror})") from None
    try:
        st = os.lstat(root)
    except FileNotFoundError:
        return None
    if stat.S_ISLNK(st.st_mode) or not stat.S_ISDIR(st.st_mode):
        raise IPCError(f"runtime directory {root}: not a folder (a symlink or a file): refused")
    if st.st_uid != os.getuid():
        raise IPCError(f"runtime directory {root}: owned by uid {st.st_uid}, not {os.getuid()}")
    if st.st_mode & 0o077:
        raise IPCError(
            f"runtime directory {root}: mode {stat.S_IMODE(st.st_mode):04o}, expected 0700 "
            "(chmod 700 it)"
        )
    return root


def entry_path(kind: str, name: str) -> Path:
    """Where a POSIX object (``shm`` or ``sem``) of ``name`` appears."""
    return SHM_DIR / (("sem." if kind == "sem" else "") + name.lstrip("/"))


def holder(kind: str, name: str) -> str:
    """Who owns the POSIX object ``name`` (for a refusal that names them)."""
    import pwd

    try:
        uid = os.lstat(entry_path(kind, name)).st_uid
    except OSError:
        return "gone since"
    try:
        return f"owned by uid {uid} ({pwd.getpwuid(uid).pw_name})"
    except KeyError:
        return f"owned by uid {uid}"

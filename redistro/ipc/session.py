"""Session manifests, liveness locks and the reaper.

A session owns a directory ``<runtime>/<session-id>/`` holding:

- ``lock``: held with ``flock(LOCK_EX)`` by the session owner for its whole life
  and inherited (same open file description) by every process it spawns, so
  the lock is free only when every process of the session is gone;
- ``manifest``: one line per IPC object (``shm /name`` or ``sem /name``),
  appended under a short ``flock`` *before* the object is created, so a crash
  between the two never hides an object from the reaper.

The reaper removes the objects of every session whose lock is free, and any
``/dev/shm`` entry named for a session that has no live lock.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import posix_ipc

from redistro.errors import IPCError
from redistro.ipc import names

log = logging.getLogger(__name__)

LOCK_FD_ENV = "REDISTRO_SESSION_LOCK_FD"


@dataclass
class Manifest:
    """Appends object names to a session's manifest file."""

    session_id: str
    directory: Path

    @property
    def path(self) -> Path:
        return self.directory / "manifest"

    def register(self, kind: str, name: str) -> None:
        line = f"{kind} {name}\n".encode()
        fd = os.open(
            self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600
        )
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            os.write(fd, line)
        finally:
            os.close(fd)

    def entries(self) -> list[tuple[str, str]]:
        try:
            fd = os.open(self.path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
        except FileNotFoundError:
            return []
        except OSError as exc:
            log.warning("manifest %s not read: %s", self.path, exc.strerror)
            return []
        with os.fdopen(fd, encoding="utf-8", errors="replace") as f:
            text = f.read(1 << 20)
        out = []
        for line in text.splitlines():
            kind, _, name = line.partition(" ")
            posix = kind in ("shm", "sem") and name.startswith("/")
            if posix or (kind == "sysv" and name.startswith("0x")):
                out.append((kind, name))
        return out

    @classmethod
    def for_session(cls, session_id: str) -> Manifest:
        return cls(session_id, names.runtime_dir() / session_id)


@dataclass
class Session:
    """The session owner's handle: id, directory, liveness lock and manifest."""

    id: str
    directory: Path
    lock_fd: int
    manifest: Manifest = field(init=False)

    def __post_init__(self) -> None:
        self.manifest = Manifest(self.id, self.directory)

    @classmethod
    def create(cls) -> Session:
        root = names.checked_runtime_dir()
        assert root is not None
        for _ in range(10):
            sid = names.new_session_id()
            directory = root / sid
            try:
                directory.mkdir(mode=0o700)
            except FileExistsError:
                continue
            try:
                fd = os.open(directory / "lock", os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600)
            except FileNotFoundError:  # reaped between mkdir and open
                continue
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                # A reaper took the brand-new directory for a dead one; pick another id.
                os.close(fd)
                continue
            if not directory.exists():  # reaped between mkdir and flock
                os.close(fd)
                continue
            os.set_inheritable(fd, True)
            return cls(sid, directory, fd)
        raise IPCError("could not create a session directory")

    def child_env(self) -> dict[str, str]:
        """Environment entries for a process spawned inside this session."""
        return {LOCK_FD_ENV: str(self.lock_fd)}

    def close(self) -> list[str]:
        """Remove whatever the session's processes left, then the session itself.

        Returns the names of objects that had to be removed here (leaks that
        their creator should have unlinked).
        """
        removed = _remove_objects(self.manifest.entries())
        removed += _remove_entries_of(self.id)
        shutil.rmtree(self.directory, ignore_errors=True)
        with contextlib.suppress(OSError):
            os.close(self.lock_fd)
        return removed

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        leaked = self.close()
        if leaked:
            log.warning("session %s: removed leftover IPC objects: %s", self.id, leaked)


def unlink(kind: str, name: str) -> bool:
    """Unlink a named object this user owns; False if it was already gone,
    is another user's (a squatter's: left alone and reported), or may not
    be removed (reported, not raised). /dev/shm is sticky: an entry this
    user owns when checked cannot be replaced by another user's before the
    unlink."""
    try:
        if kind == "sysv":
            from redistro.ipc import sysv

            return sysv.remove_key(int(name, 16))
        try:
            uid = os.lstat(names.entry_path(kind, name)).st_uid
        except FileNotFoundError:
            return False
        if uid != os.getuid():
            log.warning(
                "%s %s not removed: %s, not by this user", kind, name, names.holder(kind, name)
            )
            return False
        if kind == "sem":
            posix_ipc.unlink_semaphore(name)
        else:
            posix_ipc.unlink_shared_memory(name)
    except posix_ipc.ExistentialError:
        return False
    except (posix_ipc.PermissionsError, PermissionError) as exc:
        log.warning("%s %s not removed: %s", kind, name, exc)
        return False
    return True


def _remove_objects(entries: list[tuple[str, str]]) -> list[str]:
    return [name for kind, name in entries if unlink(kind, name)]


def _remove_entries_of(session_id: str | None, dead: set[str] | None = None) -> list[str]:
    """Unlink /dev/shm entries of ``session_id`` (or of the ``dead`` sessions:
    those whose directory in this runtime directory was found with its lock
    free; objects of sessions unknown here, of another runtime directory or
    another user, are left alone)."""
    removed: list[str] = []
    try:
        entries = sorted(os.listdir(names.SHM_DIR))
    except FileNotFoundError:
        return removed
    for entry in entries:
        sid = names.session_of_entry(entry)
        if sid is None:
            continue
        if session_id is not None and sid != session_id:
            continue
        if session_id is None and (dead is None or sid not in dead):
            continue
        kind, name = names.entry_to_name(entry)
        if unlink(kind, name):
            removed.append(name)
    return removed


def reap() -> list[str]:
    """Remove the objects of every dead session of this runtime directory (its
    lock free, and held by the reaper while it unlinks: the session cannot
    come back meanwhile); return what was removed."""
    root = names.checked_runtime_dir(create=False)
    removed: list[str] = []
    if root is None:
        return removed
    for directory in sorted(root.iterdir()):
        if directory.is_symlink() or not directory.is_dir():
            continue
        if not names.is_session_id(directory.name):
            continue
        lock = directory / "lock"
        try:
            fd = os.open(lock, os.O_RDWR | os.O_NOFOLLOW | os.O_CLOEXEC)
        except FileNotFoundError:
            # No lock file: a dead session, or one being born this instant
            # (its creator then sees its directory gone and picks a new id).
            shutil.rmtree(directory, ignore_errors=True)
            continue
        except OSError as exc:
            log.warning("session %s not reaped: %s", directory.name, exc.strerror)
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                continue  # alive
            manifest = Manifest(directory.name, directory)
            removed += _remove_objects(manifest.entries())
            removed += _remove_entries_of(None, {directory.name})
            shutil.rmtree(directory, ignore_errors=True)
        finally:
            os.close(fd)
    return removed


def live_sessions() -> list[str]:
    """Ids of sessions whose lock is held."""
    root = names.runtime_dir()
    out: list[str] = []
    if not root.is_dir():
        return out
    for directory in sorted(root.iterdir()):
        lock = directory / "lock"
        try:
            fd = os.open(lock, os.O_RDWR)
        except (FileNotFoundError, NotADirectoryError):
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            out.append(directory.name)
        finally:
            os.close(fd)
    return out

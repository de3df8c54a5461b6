"""Writing the files a user gets (run folders, exports, plots, JSON): never
through a link another user planted, never onto a pseudo-filesystem.

- A folder redistro writes into (a run folder, ``--csv``, ``--out``, the
  folder of a ``--json`` or ``--plot`` file) is *safe*: it and every folder
  above it is owned by this user or root, and none is writable by anyone
  else unless it has the sticky bit (``/tmp``), so nobody else can rename,
  replace or plant anything in it; and it is not on a pseudo-filesystem
  (/proc, /sys, ...). :func:`check_folder` says why not, in one line.
- Every file is created with ``O_CREAT | O_EXCL | O_NOFOLLOW`` (:func:`create`):
  a name that exists, a symlink among them, is an error, never followed. A
  file written whole (:func:`replace`) goes to a fresh temporary name made
  the same way, then is renamed over the target (a rename replaces a
  planted symlink itself, never what it points to). Appending
  (:func:`open_append`) refuses a symlink (``O_NOFOLLOW``).
- :func:`check_out_dir` and :func:`check_out_file` are the front door's:
  an output named on the command line is tested by creating a file there,
  before any work (and removed again).
"""

from __future__ import annotations

import contextlib
import os
import secrets
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from redistro.errors import ConfigError, clipped

# filesystems whose files are the kernel's, not data
PSEUDO_FS = frozenset(
    {
        "proc",
        "sysfs",
        "devtmpfs",
        "devpts",
        "cgroup",
        "cgroup2",
        "debugfs",
        "tracefs",
        "securityfs",
        "pstore",
        "bpf",
        "configfs",
        "fusectl",
        "mqueue",
        "hugetlbfs",
        "binfmt_misc",
        "efivarfs",
        "selinuxfs",
        "autofs",
        "nsfs",
    }
)
_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC


def fs_type(path: Path | str) -> str:
    """The type of the filesystem ``path`` (an existing path) is on, from
    /proc/self/mountinfo ('' when unknown)."""
    real = os.path.realpath(path)
    best, kind = -1, ""
    try:
        with open("/proc/self/mountinfo", encoding="utf-8", errors="replace") as f:
            lines = f.read().splitlines()
    except OSError:
        return ""
    for line in lines:
        left, sep, right = line.partition(" - ")
        fields = left.split()
        if not sep or len(fields) < 5:
            continue
        mount = fields[4].replace("\\040", " ")
        inside = real == mount or real.startswith(mount.rstrip("/") + "/")
        if inside and len(mount) > best:
            best, kind = len(mount), right.split()[0] if right.split() else ""
    return kind


def folder_problem(path: Path | str) -> str:
    """Why an existing folder is not safe to write into ('' when it is; the
    reason names the folder it is about: ``path`` or one above it)."""
    p = Path(os.path.abspath(path))
    try:
        st = os.lstat(p)
    except OSError as exc:
        return f"{p} cannot be read ({exc.strerror})"
    if stat.S_ISLNK(st.st_mode):
        return f"{p} is a symbolic link"
    if not stat.S_ISDIR(st.st_mode):
        return f"{p} exists and is not a folder"
    kind = fs_type(p)
    if kind in PSEUDO_FS:
        return f"{p} is on a {kind} pseudo-filesystem"
    uid = os.getuid()
    for q in (p, *p.parents):
        try:
            st = os.stat(q)
        except OSError as exc:
            return f"{q}: cannot be read ({exc.strerror})"
        if st.st_uid not in (uid, 0):
            return f"{q} is owned by uid {st.st_uid}, not by you ({uid}) or root"
        if st.st_mode & 0o022 and not st.st_mode & stat.S_ISVTX:
            mode = stat.S_IMODE(st.st_mode)
            return f"{q} is writable by others (mode {mode:04o})"
    return ""


def check_folder(path: Path | str, what: str, shown: str | None = None) -> None:
    """ConfigError naming ``what`` (and ``shown``, the path as the user gave
    it) when an existing folder is not safe."""
    why = folder_problem(path)
    if why:
        raise ConfigError(f"{what} {shown or clipped(str(path))}: {why}")


def make_folder(path: Path | str, what: str, mode: int = 0o755) -> Path:
    """A safe folder at ``path``, made (with its missing parents) when absent."""
    p = Path(path)
    up = _existing_ancestor(p)
    check_folder(up, what, clipped(str(p)))
    missing = []
    q = p.absolute()
    while q != up:
        missing.append(q)
        q = q.parent
    for q in reversed(missing):
        try:
            os.mkdir(q, mode)
        except FileExistsError:
            pass
        except OSError as exc:
            raise ConfigError(
                f"{what} {clipped(str(p))}: cannot be created ({exc.strerror})"
            ) from None
    check_folder(p, what)
    return p


def create(path: Path | str, mode: int = 0o644) -> int:
    """A new file's descriptor (write only): the name must not exist."""
    return os.open(path, _FLAGS, mode)


def open_new(path: Path | str, text: bool = True, mode: int = 0o644) -> IO[Any]:
    """:func:`create` as a file object (text: UTF-8)."""
    fd = create(path, mode)
    if text:
        return os.fdopen(fd, "w", encoding="utf-8", newline="")
    return os.fdopen(fd, "wb")


def open_append(path: Path | str, mode: int = 0o644) -> IO[str]:
    """A text file to append to (created when absent), never through a symlink."""
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, mode)
    return os.fdopen(fd, "a", encoding="utf-8", buffering=1)


def temp_name(path: Path | str) -> Path:
    """A fresh name beside ``path`` that nobody can guess."""
    p = Path(path)
    return p.with_name(f".{p.name}.{secrets.token_hex(6)}.tmp")


def replace(path: Path | str, data: bytes | str, mode: int = 0o644, sync: bool = False) -> None:
    """Write ``path`` whole: a reader sees the old file or the new one."""
    tmp = temp_name(path)
    fd = create(tmp, mode)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
            if sync:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def writing(path: Path | str, text: bool = True, mode: int = 0o644) -> Iterator[IO[Any]]:
    """A file object on a fresh temporary name beside ``path``, renamed over
    ``path`` when the block ends without an error (removed otherwise)."""
    tmp = temp_name(path)
    f = open_new(tmp, text, mode)
    try:
        with f:
            yield f
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _existing_ancestor(p: Path) -> Path:
    p = p.absolute()
    while not os.path.lexists(p) and p != p.parent:
        p = p.parent
    return p


def check_out_dir(path: str, option: str) -> None:
    """A folder the command will write into: an existing safe folder, or one
    that can be made in a safe folder; tested by making a file there (or
    the first missing folder), removed again."""
    p = Path(path)
    shown = clipped(path)
    if os.path.lexists(p):
        check_folder(p, option, shown)
        _probe(p, option, shown)
        return
    up = _existing_ancestor(p)
    if not up.is_dir() or up.is_symlink():
        raise ConfigError(f"{option} {shown}: cannot be created ({up} is not a folder)")
    check_folder(up, option, shown)
    first = p.absolute()
    while first.parent != up:
        first = first.parent
    try:
        os.mkdir(first, 0o700)
    except OSError as exc:
        raise ConfigError(f"{option} {shown}: cannot be created ({exc.strerror})") from None
    os.rmdir(first)


def check_out_file(path: str, option: str) -> None:
    """A file the command will write (whole, by :func:`replace`): not a
    folder, a symlink or a special file; its folder safe, or one that can
    be made."""
    p = Path(path)
    shown = clipped(path)
    if os.path.lexists(p):
        st = os.lstat(p)
        if stat.S_ISDIR(st.st_mode):
            raise ConfigError(f"{option} {shown}: is a folder, expected a file name")
        if stat.S_ISLNK(st.st_mode):
            raise ConfigError(f"{option} {shown}: is a symbolic link")
        if not stat.S_ISREG(st.st_mode):
            raise ConfigError(f"{option} {shown}: exists and is not a regular file")
    folder = p.absolute().parent
    if os.path.lexists(folder):
        check_folder(folder, option, shown)
        _probe(folder, option, shown)
    else:
        check_out_dir(str(folder), option)


def _probe(folder: Path, option: str, shown: str) -> None:
    """A file made in ``folder`` and removed: what the OS says (os.access
    answers yes to root everywhere)."""
    tmp = temp_name(folder / "probe")
    try:
        os.close(create(tmp, 0o600))
    except OSError as exc:
        raise ConfigError(f"{option} {shown}: cannot be written ({exc.strerror})") from None
    tmp.unlink()

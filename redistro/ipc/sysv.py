"""SysV shared memory: the memory cards of the simulated reflective-memory network.

A card's key is drawn at random from a range of our own (``KEY_BASE`` ..
``KEY_BASE + 0xFFFF``), so leftovers are recognisable and nobody can take
a session's key before it does: nothing world-readable predicts it. Only
the node's own ddm uses its card. The creator registers the key in the
session manifest before creating the segment (exclusively: a key that
exists is somebody else's, and another is drawn) and removes it at the
end; the reaper removes the cards of dead sessions that this user created
(:func:`remove_key` checks the creator at removal).
"""

from __future__ import annotations

import contextlib
import logging
import os
import secrets
from pathlib import Path

import sysv_ipc

from redistro.errors import IPCError

log = logging.getLogger(__name__)

KEY_BASE = 0x52440000
KIND = "sysv"  # manifest kind; the name is the key in hex
TRIES = 64  # random keys tried before a card is refused


def random_key() -> int:
    return KEY_BASE | secrets.randbelow(0x10000)


def key_name(key: int) -> str:
    return f"{key:#010x}"


class Card:
    """An attached SysV segment with byte-level read/write at offsets."""

    def __init__(self, shm: sysv_ipc.SharedMemory, owner: bool) -> None:
        self.shm = shm
        self.key = int(shm.key)
        self.size = int(shm.size)
        self.owner = owner

    @classmethod
    def create(cls, key: int, size: int, manifest: object | None) -> Card:
        """A new card at ``key``; IPCError naming who holds the key when it exists."""
        if manifest is not None:
            manifest.register(KIND, key_name(key))  # type: ignore[attr-defined]
        try:
            shm = sysv_ipc.SharedMemory(key, sysv_ipc.IPC_CREX, mode=0o600, size=size)
        except sysv_ipc.ExistentialError:
            raise IPCError(f"memory card {key_name(key)} already exists ({holder(key)})") from None
        shm.write(b"\0" * size, 0)
        return cls(shm, owner=True)

    @classmethod
    def create_new(cls, size: int, manifest: object | None) -> Card:
        """A new card at a random key of our range (another key is drawn
        while one is taken); IPCError naming the holders after TRIES."""
        taken = []
        for _ in range(TRIES):
            key = random_key()
            try:
                return cls.create(key, size, manifest)
            except IPCError as exc:
                taken.append(str(exc))
        raise IPCError(f"no free memory card key in {TRIES} tries: {taken[-1]}")

    @classmethod
    def attach(cls, key: int) -> Card:
        try:
            shm = sysv_ipc.SharedMemory(key)
        except sysv_ipc.ExistentialError:
            raise IPCError(f"memory card {key_name(key)} does not exist") from None
        return cls(shm, owner=False)

    def write(self, data: bytes, offset: int) -> None:
        self.shm.write(data, offset)

    def read(self, size: int, offset: int) -> bytes:
        out: bytes = self.shm.read(size, offset)
        return out

    def close(self) -> None:
        with contextlib.suppress(sysv_ipc.Error):
            self.shm.detach()

    def remove(self) -> None:
        remove_key(self.key)


def holder(key: int) -> str:
    """Who created the segment of ``key`` (for a refusal that names them)."""
    try:
        shm = sysv_ipc.SharedMemory(key)
    except sysv_ipc.Error:
        return "gone since"
    with contextlib.suppress(sysv_ipc.Error):
        shm.detach()
    return f"created by uid {shm.cuid}{_user(shm.cuid)}"


def _user(uid: int) -> str:
    import pwd

    try:
        return f" ({pwd.getpwuid(uid).pw_name})"
    except KeyError:
        return ""


def remove_key(key: int) -> bool:
    """Remove the segment of ``key``, if this user created it (checked on the
    segment itself, which is then removed by its id: nothing can take the
    key in between); False if there is none, or another user's (logged)."""
    try:
        shm = sysv_ipc.SharedMemory(key)
    except sysv_ipc.ExistentialError:
        return False
    with contextlib.suppress(sysv_ipc.Error):
        shm.detach()
    if shm.cuid != os.getuid():
        log.warning(
            "memory card %s not removed: created by uid %d%s, not by this user",
            key_name(key),
            shm.cuid,
            _user(shm.cuid),
        )
        return False
    try:
        shm.remove()
    except sysv_ipc.ExistentialError:
        return False
    return True


def our_keys(uid: int | None = None) -> set[int]:
    """Keys of every SysV segment in our range (from /proc/sysvipc/shm);
    uid: only those that user created."""
    out: set[int] = set()
    try:
        lines = Path("/proc/sysvipc/shm").read_text().splitlines()
    except OSError:
        return out
    head = lines[0].split() if lines else []
    at = head.index("cuid") if "cuid" in head else -1
    for line in lines[1:]:
        fields = line.split()
        if fields:
            key = int(fields[0]) & 0xFFFFFFFF
            if key & 0xFFFF0000 != KEY_BASE:
                continue
            if uid is None or (at >= 0 and int(fields[at]) == uid):
                out.add(key)
    return out

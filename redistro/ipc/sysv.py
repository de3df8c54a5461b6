"""SysV shared memory: the memory cards of the simulated reflective-memory network.

A card's key derives from (session id, node) into a range of our own
(``KEY_BASE`` .. ``KEY_BASE + 0xFFFF``), so leftovers are recognisable. The
creator registers the key in the session manifest before creating the
segment and removes it at the end; the reaper removes the cards of dead
sessions.
"""

from __future__ import annotations

import contextlib
import zlib
from pathlib import Path

import sysv_ipc

from redistro.errors import IPCError

KEY_BASE = 0x52440000
KIND = "sysv"  # manifest kind; the name is the key in hex


def card_key(session_id: str, node: str) -> int:
    return KEY_BASE | (zlib.crc32(f"{session_id}/{node}".encode()) & 0xFFFF)


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
        if manifest is not None:
            manifest.register(KIND, key_name(key))  # type: ignore[attr-defined]
        try:
            shm = sysv_ipc.SharedMemory(key, sysv_ipc.IPC_CREX, mode=0o600, size=size)
        except sysv_ipc.ExistentialError:
            raise IPCError(f"memory card {key_name(key)} already exists") from None
        shm.write(b"\0" * size, 0)
        return cls(shm, owner=True)

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


def remove_key(key: int) -> bool:
    """Remove the segment of ``key``; False if there is none."""
    try:
        shm = sysv_ipc.SharedMemory(key)
    except sysv_ipc.ExistentialError:
        return False
    with contextlib.suppress(sysv_ipc.Error):
        shm.detach()
    try:
        shm.remove()
    except sysv_ipc.ExistentialError:
        return False
    return True


def our_keys() -> set[int]:
    """Keys of every SysV segment in our range (from /proc/sysvipc/shm)."""
    out: set[int] = set()
    try:
        lines = Path("/proc/sysvipc/shm").read_text().splitlines()[1:]
    except OSError:
        return out
    for line in lines:
        fields = line.split()
        if fields:
            key = int(fields[0]) & 0xFFFFFFFF
            if key & 0xFFFF0000 == KEY_BASE:
                out.add(key)
    return out

"""Named POSIX shared memory, mapped once; the creator unlinks, attachers only close."""

from __future__ import annotations

import contextlib
import mmap
from typing import ClassVar

import posix_ipc

from redistro.errors import IPCError
from redistro.ipc import names
from redistro.ipc.session import Manifest


class SharedMemory:
    """A mapped POSIX shared-memory object.

    Use :meth:`create` (registers the name in the session manifest first) or
    :meth:`attach`. ``buffer`` is the mapping; views onto it must be dropped
    before :meth:`close`.
    """

    def __init__(self, name: str, mapping: mmap.mmap, size: int, owner: bool) -> None:
        self.name = name
        self.buffer = mapping
        self.size = size
        self.owner = owner

    @classmethod
    def create(cls, name: str, size: int, manifest: Manifest | None) -> SharedMemory:
        if manifest is not None:
            manifest.register("shm", name)
        try:
            shm = posix_ipc.SharedMemory(name, posix_ipc.O_CREX, mode=0o600, size=size)
        except posix_ipc.ExistentialError:
            raise IPCError(
                f"shared memory {name} already exists ({names.holder('shm', name)})"
            ) from None
        try:
            mapping = mmap.mmap(shm.fd, size)
        finally:
            shm.close_fd()
        return cls(name, mapping, size, owner=True)

    @classmethod
    def attach(cls, name: str) -> SharedMemory:
        try:
            shm = posix_ipc.SharedMemory(name)
        except posix_ipc.ExistentialError:
            raise IPCError(f"shared memory {name} does not exist") from None
        try:
            size = shm.size
            if size == 0:
                raise IPCError(f"shared memory {name} is not sized yet (being created)")
            mapping = mmap.mmap(shm.fd, size)
        finally:
            shm.close_fd()
        return cls(name, mapping, size, owner=False)

    def close(self) -> None:
        """Unmap. Fails loudly if numpy views onto the buffer are still alive."""
        if not self.buffer.closed:
            try:
                self.buffer.close()
            except BufferError as exc:
                raise IPCError(f"{self.name}: views still exported at close") from exc

    def unlink(self) -> None:
        with contextlib.suppress(posix_ipc.ExistentialError):
            posix_ipc.unlink_shared_memory(self.name)


class MemorySegment:
    """An in-process stand-in for :class:`SharedMemory`, the same contract
    (create refuses a name that exists, attach one that does not; close
    fails while views are exported; the creator unlinks) over anonymous
    memory that only this process sees: Local Data for unit tests that run
    a manager's bookkeeping, a worker or a ddm without processes. The
    contract tests of Local Data run over both."""

    _named: ClassVar[dict[str, mmap.mmap]] = {}

    def __init__(self, name: str, mapping: mmap.mmap, owner: bool) -> None:
        self.name = name
        self._mapping = mapping
        self.buffer = memoryview(mapping)
        self.size = len(mapping)
        self.owner = owner

    @classmethod
    def create(cls, name: str, size: int, manifest: Manifest | None = None) -> MemorySegment:
        if name in cls._named:
            raise IPCError(f"shared memory {name} already exists")
        mapping = mmap.mmap(-1, size)
        cls._named[name] = mapping
        return cls(name, mapping, owner=True)

    @classmethod
    def attach(cls, name: str) -> MemorySegment:
        mapping = cls._named.get(name)
        if mapping is None:
            raise IPCError(f"shared memory {name} does not exist")
        return cls(name, mapping, owner=False)

    def close(self) -> None:
        try:
            self.buffer.release()
        except BufferError as exc:
            raise IPCError(f"{self.name}: views still exported at close") from exc

    def unlink(self) -> None:
        self._named.pop(self.name, None)

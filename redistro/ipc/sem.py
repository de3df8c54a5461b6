"""Named POSIX semaphores whose every wait has a deadline on the monotonic clock.

posix_ipc's own timeout runs on the wall clock and a signal during a wait raises
``SignalError``; :meth:`Semaphore.acquire` loops against a monotonic deadline.
"""

from __future__ import annotations

import contextlib
import time

import posix_ipc

from redistro.errors import IPCError
from redistro.ipc import names
from redistro.ipc.session import Manifest


class Semaphore:
    def __init__(self, name: str, sem: posix_ipc.Semaphore, owner: bool) -> None:
        self.name = name
        self._sem = sem
        self.owner = owner

    @classmethod
    def create(cls, name: str, manifest: Manifest | None, initial: int = 0) -> Semaphore:
        if manifest is not None:
            manifest.register("sem", name)
        try:
            sem = posix_ipc.Semaphore(name, posix_ipc.O_CREX, mode=0o600, initial_value=initial)
        except posix_ipc.ExistentialError:
            raise IPCError(
                f"semaphore {name} already exists ({names.holder('sem', name)})"
            ) from None
        return cls(name, sem, owner=True)

    @classmethod
    def attach(cls, name: str) -> Semaphore:
        try:
            sem = posix_ipc.Semaphore(name)
        except posix_ipc.ExistentialError:
            raise IPCError(f"semaphore {name} does not exist") from None
        return cls(name, sem, owner=False)

    def try_acquire(self) -> bool:
        try:
            self._sem.acquire(0)
        except posix_ipc.BusyError:
            return False
        return True

    def acquire(self, timeout_s: float) -> bool:
        """Take the semaphore; False if ``timeout_s`` passes on the monotonic clock."""
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return self.try_acquire()
            try:
                self._sem.acquire(remaining)
                return True
            except posix_ipc.BusyError:
                continue  # the wall-clock timeout fired; the loop re-checks monotonic time
            except posix_ipc.SignalError:
                continue

    def release(self) -> None:
        self._sem.release()

    @property
    def value(self) -> int:
        return int(self._sem.value)

    def close(self) -> None:
        with contextlib.suppress(posix_ipc.ExistentialError):
            self._sem.close()

    def unlink(self) -> None:
        with contextlib.suppress(posix_ipc.ExistentialError):
            posix_ipc.unlink_semaphore(self.name)

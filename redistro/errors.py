"""The project's exceptions: one root, each subclass also a matching builtin."""

from __future__ import annotations


class RedistroError(Exception):
    """Root of every error raised by redistro."""


class ConfigError(RedistroError, ValueError):
    """A config file, task file, override or command line is invalid.

    The message is one line naming where (file, field) and what is wrong.
    """


class IPCError(RedistroError, OSError):
    """An OS primitive (shared memory, semaphore, signal) failed."""


class LayoutError(RedistroError, ValueError):
    """A Local Data segment does not match the declared layout, or a block is
    written by a process that is not its declared writer."""


class CycleTimeout(RedistroError, TimeoutError):
    """A wait ran past its deadline on the monotonic clock."""


class TornReadTimeout(CycleTimeout):
    """No consistent snapshot of a block could be taken within the time budget."""


class NodeFault(RedistroError, RuntimeError):
    """A node ended on a fault; `reason` is one of unsafe, starving, estop, abnormal."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


class IOFault(RedistroError, OSError):
    """A board did not answer or update within its timeout, a frame was bad,
    or the plant behind the backplane is gone: the robot must be frozen."""


class WireError(RedistroError, ValueError):
    """A DDM wire record that cannot be trusted (size, magic, version, kind, checksum)."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


class TransportError(RedistroError, ConnectionError):
    """A DDM link is lost (peer closed, reset or unreachable)."""

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


def shown(value: object, n: int = 60) -> str:
    """A value as an error message shows it: its repr, cut to ``n``
    characters, without walking more of a large or deep value than that
    needs (a message never expands a whole document)."""
    import reprlib

    r = reprlib.Repr()
    r.maxlevel, r.maxstring, r.maxother, r.maxlong = 3, n, n, n
    r.maxlist = r.maxtuple = r.maxdict = r.maxset = 8
    try:
        text = r.repr(value)
    except (ValueError, RecursionError):  # an int too long to print, a cycle
        text = f"<{type(value).__name__}>"
    return text if len(text) <= n else text[: n - 3] + "..."


def clipped(text: str, n: int = 60) -> str:
    """A piece of text as an error message quotes it: cut to ``n`` characters
    (control characters are escaped where the message is printed)."""
    return text if len(text) <= n else text[: n - 3] + "..."

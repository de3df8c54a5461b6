"""Real-time signals for cycle synchronization, waited for with sigtimedwait.

No Python signal handlers are used: every process blocks these signals in all
threads (before any thread exists) and takes them synchronously.
"""

from __future__ import annotations

import ctypes
import functools
import os
import select
import signal
import time

SIG_SYNC = signal.SIGRTMIN + 1
"""Manager -> worker: a new cycle has started. Queued, so a backlog is countable."""
SIG_END = signal.SIGRTMIN + 2
"""Manager -> worker: the session ends; go to Cleanup."""
SIG_ORPHAN = signal.SIGRTMIN + 3
"""Kernel -> child: the parent died (set with PR_SET_PDEATHSIG)."""

SIG_WAKE = signal.SIGRTMIN + 4
"""Worker -> manager: look at the workers' rows now (an e-stop request), not at the next tick."""

SIG_ESTOP = signal.SIGRTMIN + 5
"""Session owner -> manager: a node of the group faulted and cannot carry its
e-stop through its DDM (it has none, or its DDM is what failed): e-stop now.
(Manager -> owner: a SIGCHLD sent with kill asks for that relay.)"""

STOP_SIGNALS = frozenset({signal.SIGINT, signal.SIGTERM, signal.SIGHUP})
RUNTIME_SIGNALS = frozenset(
    {SIG_SYNC, SIG_END, SIG_ORPHAN, SIG_WAKE, SIG_ESTOP, signal.SIGALRM, signal.SIGCHLD}
    | STOP_SIGNALS
)

_PR_SET_PDEATHSIG = 1
_PR_SET_CHILD_SUBREAPER = 36


def block_runtime_signals() -> None:
    """Block the runtime signals in the calling thread (and threads it starts)."""
    signal.pthread_sigmask(signal.SIG_BLOCK, RUNTIME_SIGNALS)


def wait(signals: frozenset[int] | set[int], timeout_s: float) -> signal.struct_siginfo | None:
    """Take one of ``signals`` within ``timeout_s`` (monotonic), else None.

    sigtimedwait restarts on EINTR with a recomputed monotonic timeout (PEP 475).
    A process stopped (SIGSTOP) inside it and continued may see it return no
    signal at all (signal number 0, the rest of the record unfilled): that is
    no signal, and the wait goes on to its deadline.
    """
    deadline = time.monotonic() + max(0.0, timeout_s)
    while True:
        info = signal.sigtimedwait(signals, max(0.0, deadline - time.monotonic()))
        if info is None or info.si_signo != 0:
            return info


def drain(sig: int) -> int:
    """Take every pending instance of ``sig`` without waiting; return how many."""
    count = 0
    while signal.sigtimedwait({sig}, 0) is not None:
        count += 1
    return count


def send(pidfd: int, sig: int) -> bool:
    """Send ``sig`` through a pidfd (safe against pid reuse); False if the process is gone."""
    try:
        signal.pidfd_send_signal(pidfd, sig)
    except ProcessLookupError:
        return False
    return True


_SFD_NONBLOCK = os.O_NONBLOCK
_SFD_CLOEXEC = os.O_CLOEXEC
SIGINFO_BYTES = 128  # struct signalfd_siginfo


@functools.cache
def c_library() -> ctypes.CDLL:
    """The C library, as the process already has it (``dlopen(NULL)``):
    ``ctypes.util.find_library`` would run ``ldconfig -p`` in a child of every
    process that asks."""
    return ctypes.CDLL(None, use_errno=True)


def signalfd(sigs: frozenset[int] | set[int]) -> int:
    """A file descriptor that becomes readable when one of ``sigs`` (blocked,
    as every runtime signal is) is pending: a process that waits on sockets
    with poll can take its signals in the same wait. Read them with
    :func:`read_signalfd`."""
    libc = c_library()
    mask = bytearray(128)  # sigset_t: 1024 bits
    for sig in sigs:
        n = int(sig) - 1
        mask[n // 8] |= 1 << (n % 8)
    buf = (ctypes.c_ubyte * 128).from_buffer(mask)
    fd = int(libc.signalfd(-1, ctypes.byref(buf), _SFD_NONBLOCK | _SFD_CLOEXEC))
    if fd < 0:
        err = ctypes.get_errno()
        raise OSError(err, os.strerror(err))
    return fd


def read_signalfd(fd: int) -> list[int]:
    """The signals taken from a :func:`signalfd` (each consumed), oldest first."""
    out: list[int] = []
    while True:
        try:
            data = os.read(fd, SIGINFO_BYTES)
        except BlockingIOError:
            return out
        if len(data) < SIGINFO_BYTES:
            return out
        out.append(int.from_bytes(data[:4], "little"))


def _prctl(option: int, value: int) -> None:
    libc = c_library()
    if libc.prctl(option, value, 0, 0, 0) != 0:
        err = ctypes.get_errno()
        raise OSError(err, os.strerror(err))


def set_parent_death_signal(sig: int) -> None:
    """Ask the kernel to send ``sig`` to this process when its parent dies."""
    _prctl(_PR_SET_PDEATHSIG, sig)


def become_subreaper() -> None:
    """Orphaned descendants re-parent to this process, which can then reap them."""
    _prctl(_PR_SET_CHILD_SUBREAPER, 1)


def children_of(pid: int) -> list[int]:
    """Pids whose parent is ``pid`` (read from /proc)."""
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as f:
                stat = f.read()
        except OSError:
            continue
        # the command name may hold spaces or parentheses: parse after the last ')'
        fields = stat[stat.rfind(b")") + 2 :].split()
        if int(fields[1]) == pid:
            out.append(int(entry))
    return out


def process_alive(pidfd: int) -> bool:
    """Whether the process behind a pidfd is still running (not exited)."""
    poller = select.poll()
    poller.register(pidfd, select.POLLIN)
    return not poller.poll(0)

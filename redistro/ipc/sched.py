"""Scheduling: SCHED_RR with the paper's relative priorities when permitted,
nice values otherwise; CPU affinity; memory locking; the CPUs' wake-up
latency (PM QoS). Reports what was granted."""

from __future__ import annotations

import contextlib
import ctypes
import os
import threading
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from typing import Any

from redistro.ipc import signals

_MCL_CURRENT = 1
_MCL_FUTURE = 2

POLICY_CODES = {"default": 0, "SCHED_RR": 1, "nice": 2, "SCHED_BATCH": 3}


@dataclass
class Granted:
    """What the OS gave a process.

    policy: ``SCHED_RR``, ``nice``, ``SCHED_BATCH`` or ``default``; priority: the RR priority
    (0 when not RR); nice: the nice value; cpus: allowed CPUs; memory_locked:
    whether mlockall succeeded; refused: what was asked for and denied.
    """

    policy: str = "default"
    priority: int = 0
    nice: int = 0
    cpus: list[int] = field(default_factory=list)
    memory_locked: bool = False
    cpu_latency_us: int | None = None  # the PM QoS request held (None: none)
    refused: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def nice_for(priority: int) -> int:
    """Map a paper priority (15..19, higher first) to a nice value (-5..-9)."""
    return max(-20, min(0, 10 - priority))


def apply(
    priority: int, cpus: list[int] | None = None, policy: str = "auto", lock_memory: bool = False
) -> Granted:
    """Ask for ``priority`` under ``policy`` (auto | rr | nice | none | batch)
    and ``cpus`` (batch: SCHED_BATCH, whatever ``priority``)."""
    granted = Granted()
    if cpus:
        try:
            os.sched_setaffinity(0, cpus)
        except OSError as exc:
            granted.refused.append(f"affinity {cpus}: {exc.strerror}")
    granted.cpus = sorted(os.sched_getaffinity(0))

    if policy in ("auto", "rr"):
        try:
            # reset on fork: a process this one spawns starts at the default
            # policy (its start-up must not run at this priority)
            os.sched_setscheduler(0, os.SCHED_RR | os.SCHED_RESET_ON_FORK, os.sched_param(priority))
            granted.policy, granted.priority = "SCHED_RR", priority
        except (PermissionError, OSError) as exc:
            granted.refused.append(f"SCHED_RR {priority}: {exc.strerror}")
    if policy == "batch":
        granted.policy = batch(granted.refused)
    if granted.policy == "default" and policy in ("auto", "nice"):
        want = nice_for(priority)
        try:
            os.setpriority(os.PRIO_PROCESS, 0, want)
            granted.policy = "nice"
        except (PermissionError, OSError) as exc:
            granted.refused.append(f"nice {want}: {exc.strerror}")
    granted.nice = os.getpriority(os.PRIO_PROCESS, 0)

    if lock_memory:
        granted.memory_locked = _mlockall(granted)
    return granted


def batch(refused: list[str] | None = None) -> str:
    """The calling process at SCHED_BATCH (its children inherit it): when it
    wakes up it does not preempt the process running, it waits for that
    one's slice, so a chain of processes handing work on (a lockstep tick)
    runs with fewer switches. Returns the policy now held."""
    try:
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
        return "SCHED_BATCH"
    except OSError as exc:  # (any process may ask for it: an odd kernel)
        if refused is not None:
            refused.append(f"SCHED_BATCH: {exc.strerror}")
        return "default"


def leave_real_time() -> None:
    """Back to the normal policy (a process whose cycles are over: its clean-up
    must not hold the simulated plant off the CPUs; the robot is frozen by
    then)."""
    try:
        # the policy carries SCHED_RESET_ON_FORK when apply() set it
        if os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK in (os.SCHED_RR, os.SCHED_FIFO):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except OSError:
        pass  # not permitted: it stays where it is


def share_with_threads() -> int:
    """Give every other thread of this process the calling thread's
    real-time policy and priority: threads a library starts (zenoh's I/O
    threads) are clones, and SCHED_RESET_ON_FORK sends every clone back to
    the normal policy, where the real-time processes hold it off. Returns how
    many threads were raised (0: not real time, or not permitted)."""
    try:
        policy = os.sched_getscheduler(0)
        if policy & ~os.SCHED_RESET_ON_FORK not in (os.SCHED_RR, os.SCHED_FIFO):
            return 0
        param = os.sched_getparam(0)
        me = threading.get_native_id()
        raised = 0
        for entry in os.listdir("/proc/self/task"):
            tid = int(entry)
            if tid == me:
                continue
            try:
                os.sched_setscheduler(tid, policy, param)
                raised += 1
            except OSError:
                pass  # gone, or not permitted
        return raised
    except OSError:
        return 0


def runnable(pid: int) -> bool:
    """One of the process's threads is running or waiting for a CPU (state
    R): starved by a loaded host, not stopped nor blocked (a lockstep wait
    goes on for it). Every thread: a transport's own (zenoh's) may be the
    one that carries the record waited for."""
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return False
    for tid in tids:
        try:
            with open(f"/proc/{pid}/task/{tid}/stat", "rb") as f:
                if f.read().rsplit(b")", 1)[1].split()[0] == b"R":
                    return True
        except (OSError, IndexError):
            continue
    return False


def is_real_time() -> bool:
    """Whether the calling thread runs under SCHED_RR or SCHED_FIFO."""
    try:
        return os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK in (os.SCHED_RR, os.SCHED_FIFO)
    except OSError:
        return False


@contextlib.contextmanager
def normal_policy() -> Iterator[None]:
    """Run a block at the normal policy, then return to the real-time one (a
    real-time process's occasional chores: a progress display, a spawn)."""
    try:
        policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    except OSError:
        policy, param = os.SCHED_OTHER, None
    real_time = policy & ~os.SCHED_RESET_ON_FORK in (os.SCHED_RR, os.SCHED_FIFO)
    if real_time:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, os.SCHED_OTHER | os.SCHED_RESET_ON_FORK, os.sched_param(0))
    try:
        yield
    finally:
        if real_time and param is not None:
            with contextlib.suppress(OSError):
                os.sched_setscheduler(0, policy, param)


CPU_LATENCY_PATH = "/dev/cpu_dma_latency"


def hold_cpu_latency(us: int, granted: Granted, path: str = CPU_LATENCY_PATH) -> int | None:
    """Ask the kernel's power management to keep every CPU's wake-up latency
    within ``us`` (a PM QoS request: 0 keeps idle CPUs polling instead of
    halting). The request lasts while the returned descriptor is open: the
    caller keeps it for its lifetime, and the kernel drops it when the
    process ends, however it ends. None (and the refusal noted in
    ``granted``) where the device is missing or not permitted."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CLOEXEC)
    except OSError as exc:
        granted.refused.append(f"cpu latency {us} us: {exc.strerror}")
        return None
    try:
        os.write(fd, int(us).to_bytes(4, "little", signed=True))
    except OSError as exc:
        os.close(fd)
        granted.refused.append(f"cpu latency {us} us: {exc.strerror}")
        return None
    granted.cpu_latency_us = int(us)
    return fd


def _mlockall(granted: Granted) -> bool:
    libc = signals.c_library()
    # MCL_FUTURE under a small RLIMIT_MEMLOCK would make later allocations fail,
    # so only root (CAP_IPC_LOCK, no limit) asks for it.
    flags = _MCL_CURRENT | (_MCL_FUTURE if os.geteuid() == 0 else 0)
    if libc.mlockall(flags) == 0:
        return True
    granted.refused.append(f"mlockall: {os.strerror(ctypes.get_errno())}")
    return False


def cpu_mask(cpus: list[int]) -> int:
    mask = 0
    for cpu in cpus:
        mask |= 1 << cpu
    return mask


def cpus_of_mask(mask: int) -> list[int]:
    return [i for i in range(64) if mask >> i & 1]

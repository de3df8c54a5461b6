"""A node's worker processes, as its manager keeps them: spawned with
fork+exec, synced each cycle through their pidfds, reaped as they exit,
ended (or killed) at Cleanup."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable

from redistro.ipc import signals
from redistro.process.spawn import spawn
from redistro.process.spec import NodeSpec


def describe_status(status: int) -> str:
    if os.WIFSIGNALED(status):
        return f"killed by {signal.Signals(os.WTERMSIG(status)).name}"
    if os.WIFEXITED(status):
        return f"exited with code {os.WEXITSTATUS(status)}"
    return f"status {status:#x}"


class Child:
    """One worker process."""

    def __init__(self, name: str, pid: int, pidfd: int) -> None:
        self.name = name
        self.pid = pid
        self.pidfd = pidfd
        self.status: int | None = None

    @property
    def alive(self) -> bool:
        return self.status is None

    def sync(self) -> None:
        """The tick's sync signal: run a cycle."""
        signals.send(self.pidfd, signals.SIG_SYNC)

    def reap(self, wait: bool = False) -> bool:
        """Collect the exit status if the process has exited (or wait for it)."""
        if self.alive:
            pid, status = os.waitpid(self.pid, 0 if wait else os.WNOHANG)
            if pid:
                self.status = status
        return not self.alive

    @property
    def exit(self) -> str:
        return describe_status(self.status) if self.status is not None else "unknown"


def spawn_workers(
    spec: NodeSpec, spec_path: str, wake_fd: int, pass_fds: tuple[int, ...]
) -> list[Child]:
    """Every worker of ``spec``, started (each reaped later by its Child)."""
    children = []
    for j, w in enumerate(spec.workers):
        args = ["worker", "--spec", spec_path, "--index", str(j)]
        args += ["--manager-pid", str(os.getpid()), "--wake-fd", str(wake_fd)]
        proc = spawn(args, pass_fds=pass_fds)
        children.append(Child(w.name, proc.pid, os.pidfd_open(proc.pid)))
        proc.returncode = 0  # reaped by Child.reap, not by Popen
    return children


def end_workers(children: list[Child], hung: set[int]) -> None:
    """Ask every worker to end (a hung one is killed: it would not take the
    chance to clean up)."""
    for j, child in enumerate(children):
        if child.alive:
            signals.send(child.pidfd, signal.SIGKILL if j in hung else signals.SIG_END)


def reap_workers(children: list[Child], timeout_s: float, warn: Callable[[str], None]) -> None:
    """Wait up to ``timeout_s`` for the workers to end; kill the rest."""
    deadline = time.monotonic() + timeout_s
    while any(c.alive for c in children):
        for child in children:
            child.reap()
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            break
        signals.wait(frozenset({signal.SIGCHLD}), min(remaining, 0.05))
    for child in children:
        if child.alive:
            warn(f"worker {child.name} did not end in time; killed")
            signals.send(child.pidfd, signal.SIGKILL)
            child.reap(wait=True)

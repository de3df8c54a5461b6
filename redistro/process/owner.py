"""The session owner: starts a node's manager, waits, and leaves nothing behind.

The owner holds the session lock, becomes a child subreaper (orphaned workers
re-parent to it), forwards Ctrl-C/SIGTERM to the manager as an orderly end,
and after the manager exits reaps every descendant and removes any IPC object
the session still has.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import time
from pathlib import Path
from typing import Any

from redistro.ipc import signals
from redistro.ipc.session import Session
from redistro.process.manager import describe_status
from redistro.process.spawn import spawn
from redistro.process.spec import NodeSpec

log = logging.getLogger(__name__)

OWNER_WAIT = frozenset({signal.SIGCHLD}) | signals.STOP_SIGNALS


def run_node(spec: NodeSpec, session: Session) -> dict[str, Any]:
    """Run one node to its end; return the manager's result (always a dict)."""
    signals.become_subreaper()
    spec.owner_pid = os.getpid()
    spec_path = session.directory / f"{spec.node}.spec.json"
    result_path = session.directory / f"{spec.node}.result.json"
    spec.result_path = str(result_path)
    spec.save(spec_path)
    proc = spawn(
        ["manager", "--spec", str(spec_path)], pass_fds=(session.lock_fd,), env=session.child_env()
    )
    pidfd = os.pidfd_open(proc.pid)
    budget = spec.startup_timeout_s + spec.shutdown_timeout_s + 5.0
    deadline = time.monotonic() + budget + spec.cycles / spec.rate_hz if spec.cycles else None
    interrupted: str | None = None
    kill_at: float | None = None
    status = 0
    stragglers: list[int] = []
    try:
        while True:
            info = signals.wait(OWNER_WAIT, 0.2)
            pid, status = os.waitpid(proc.pid, os.WNOHANG)
            if pid:
                break
            now = time.monotonic()
            if info is not None and info.si_signo in signals.STOP_SIGNALS and interrupted is None:
                interrupted = signal.Signals(info.si_signo).name
                signals.send(pidfd, signal.SIGTERM)
                kill_at = now + spec.shutdown_timeout_s + 2.0
            if deadline is not None and now > deadline and kill_at is None:
                log.error("node %s ran past its time budget; stopping it", spec.node)
                signals.send(pidfd, signal.SIGTERM)
                kill_at = now + spec.shutdown_timeout_s + 2.0
            if kill_at is not None and now > kill_at:
                signals.send(pidfd, signal.SIGKILL)
    finally:
        proc.returncode = status
        os.close(pidfd)
        stragglers = reap_descendants(spec.shutdown_timeout_s)
    try:
        result: dict[str, Any] = json.loads(result_path.read_text())
    except (OSError, ValueError):
        result = {
            "node": spec.node,
            "result": "abnormal",
            "reason": f"manager of {spec.node} died: {describe_status(status)}",
        }
    result["stragglers_killed"] = stragglers
    if stragglers:
        log.warning("killed processes of %s that did not end: %s", spec.node, stragglers)
    if interrupted and result.get("result") == "ok":
        result.update(result="abnormal", reason=f"interrupted by {interrupted}")
    return result


def reap_descendants(timeout_s: float) -> list[int]:
    """Wait for orphaned descendants (we are their subreaper); SIGKILL stragglers."""
    me = os.getpid()
    deadline = time.monotonic() + timeout_s
    killed: list[int] = []
    while True:
        with contextlib.suppress(ChildProcessError):
            while os.waitpid(-1, os.WNOHANG)[0]:
                pass
        left = signals.children_of(me)
        if not left:
            return killed
        if time.monotonic() > deadline:
            for pid in left:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
                killed.append(pid)
            deadline = time.monotonic() + 5.0
        signals.wait(frozenset({signal.SIGCHLD}), 0.05)


def write_json(path: Path, data: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    os.replace(tmp, path)

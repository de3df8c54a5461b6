"""The session owner: starts a node's manager, waits, and leaves nothing behind.

The owner holds the session lock, becomes a child subreaper (orphaned workers
re-parent to it), forwards Ctrl-C/SIGTERM to the manager as an orderly end,
and after the manager exits reaps every descendant and removes any IPC object
the session still has.

Past the house's ~400 lines: starting, watching, relaying an e-stop and
ending a node are one life cycle of the same child, kept together.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from redistro.errors import RedistroError
from redistro.ipc import signals
from redistro.ipc.session import Session
from redistro.localdata.view import NodeView
from redistro.process.children import describe_status
from redistro.process.result import NodeResult
from redistro.process.spawn import spawn
from redistro.process.spec import NodeSpec

log = logging.getLogger(__name__)

OWNER_WAIT = frozenset({signal.SIGCHLD}) | signals.STOP_SIGNALS
SI_USER = 0  # siginfo.si_code of a signal sent by kill()
_T = TypeVar("_T")
# children of this process that are no part of any node (a benchmark's
# cyclictest running beside a session): reaping leaves them alone
SPARED: set[int] = set()


def run_node(spec: NodeSpec, session: Session) -> NodeResult:
    """Run one node to its end; return the manager's result."""
    return run_nodes([spec], session)[0]


def run_nodes(
    specs: list[NodeSpec],
    session: Session,
    *,
    budget_s: float | None = None,
    on_wait: Callable[[], None] | None = None,
    keep: frozenset[int] = frozenset(),
    clock: Callable[[], float | None] | None = None,
    beside: Callable[[], bool] | None = None,
) -> list[NodeResult]:
    """Run nodes side by side to their ends; return each manager's result.

    The first node that ends with a fault stops the others (one robot's
    fault stops the group): at once, or, when every node has a DDM (which
    carries the group's e-stop itself), after GROUP_STOP_GRACE_S.
    Ctrl-C/SIGTERM is passed on as an orderly end.
    budget_s: how long the nodes' routine may last before they are stopped
    (start-up and shutdown time come on top); None: until they end (or their
    ``cycles`` run out). on_wait: called about five times a second while
    waiting. keep: pids of other children (the plant) not to reap here.
    clock: the task's own clock [s] (the simulated plant's time; None when it
    cannot be read): budget_s then counts on it, so a slow plant is not a
    fault, with a wall-clock backstop at MIN_CLOCK_RATE of real time.
    beside: whether a process started beside the nodes is up yet (the plant,
    whose start-up overlaps theirs; they wait for it themselves): polled
    until true. When it raises RedistroError every node is stopped, and the
    error is raised once they have ended.
    """
    signals.become_subreaper()
    nodes: list[_Node] = []
    side = _Beside(beside)

    def start(spec: NodeSpec) -> None:
        spec.owner_pid = os.getpid()
        spec_path = session.directory / f"{spec.node}.spec.json"
        spec.result_path = str(session.directory / f"{spec.node}.result.json")
        spec.save(spec_path)
        proc = spawn(
            ["manager", "--spec", str(spec_path)],
            pass_fds=(session.lock_fd,),
            env=session.child_env(),
        )
        proc.returncode = 0  # reaped below, not by Popen
        nodes.append(_Node(spec, proc.pid, os.pidfd_open(proc.pid)))

    try:
        for spec in specs:
            start(spec)
        _wait_nodes(nodes, budget_s, on_wait, clock, side)
    finally:
        for n in nodes:
            os.close(n.pidfd)
        stragglers = reap_descendants(
            max((s.shutdown_timeout_s for s in specs), default=3.0), keep=keep
        )
    results = []
    for n in nodes:
        result = n.result()
        result.stragglers_killed = list(stragglers)
        if stragglers:
            log.warning("killed processes that did not end: %s", stragglers)
        if n.interrupted and (result.ok or result.reason.startswith("interrupted by SIGTERM")):
            # the manager saw our SIGTERM; the reason is why we sent it
            result.result, result.reason = "abnormal", f"interrupted by {n.interrupted}"
        results.append(result)
    if side.error is not None:
        raise side.error
    return results


class _Beside:
    """A process started beside the nodes, polled until it is up."""

    def __init__(self, up: Callable[[], bool] | None) -> None:
        self.up = up
        self.done = up is None
        self.error: RedistroError | None = None

    def poll(self, nodes: list[_Node], now: float) -> None:
        if self.done or self.up is None:
            return
        try:
            self.done = self.up()
        except RedistroError as exc:
            self.done, self.error = True, exc
            log.error("%s", exc)
            for n in nodes:
                n.stop(str(exc), now)


class _Node:
    def __init__(self, spec: NodeSpec, pid: int, pidfd: int) -> None:
        self.spec = spec
        self.pid = pid
        self.pidfd = pidfd
        self.status: int | None = None
        self.interrupted: str | None = None
        self.kill_at: float | None = None

    def stop(self, why: str, now: float) -> None:
        if self.status is None and self.kill_at is None:
            self.interrupted = why
            signals.send(self.pidfd, signal.SIGTERM)
            # a stopped (SIGSTOP) manager takes it too, and ends in order
            signals.send(self.pidfd, signal.SIGCONT)
            self.kill_at = now + self.spec.shutdown_timeout_s + 2.0

    def result(self) -> NodeResult:
        try:
            return NodeResult.from_dict(json.loads(Path(self.spec.result_path).read_text()))
        except (OSError, ValueError, TypeError, AttributeError):
            return NodeResult.died(
                self.spec.node,
                f"manager of {self.spec.node} died: {describe_status(self.status or 0)}",
            )


# How long the other nodes get to end on the group's e-stop (their DDMs carry
# it in a few milliseconds, their managers act within a cycle) before the
# owner stops them itself. Nodes without DDMs get the e-stop from the owner's
# relay only: they are stopped after a short grace, so that the relayed
# e-stop (a real-time signal) is taken before the SIGTERM (a standard
# signal, which a manager's sigwaitinfo would return first when both wait).
GROUP_STOP_GRACE_S = 0.25
RELAYED_STOP_GRACE_S = 0.05

# The slowest a task's own clock (the simulated plant) may run before the
# wall-clock backstop of its budget stops the nodes [share of real time]: a
# stalled plant, not a slow one (a loaded two-vCPU host ran it at 0.1-0.9).
MIN_CLOCK_RATE = 0.05


class _Budget:
    """The nodes' time budget, on the task's clock when there is one."""

    def __init__(
        self,
        budget_s: float | None,
        margin_s: float,
        start: float,
        clock: Callable[[], float | None] | None,
        paused: Callable[[], float] | None = None,
    ) -> None:
        """paused: the task time an operator held the task paused [s] (the
        budget grows by it)."""
        self.budget_s, self.margin_s, self.clock = budget_s, margin_s, clock
        self.paused = paused
        # the clock counts from its first reading (a plant still starting
        # beside the nodes has none yet)
        self.clock_start = clock() if clock is not None and budget_s is not None else None
        self.wall_deadline: float | None = None
        if budget_s is not None:
            rate = 1.0 if clock is None else MIN_CLOCK_RATE
            self.wall_deadline = start + margin_s + budget_s / rate

    def exceeded(self, now: float) -> str | None:
        """Why the budget is spent (a line for the log), or None."""
        if self.budget_s is None or self.wall_deadline is None:
            return None
        if now > self.wall_deadline:
            if self.clock is None:
                return f"nodes ran past their time budget ({self.budget_s:.1f} s); stopping them"
            return (
                f"the task's clock ran below {MIN_CLOCK_RATE:g} of real time past its "
                f"budget ({self.budget_s:.1f} s); stopping the nodes"
            )
        if self.clock is not None:
            t = self.clock()
            if t is not None and self.clock_start is None:
                self.clock_start = t
            ran = None if t is None or self.clock_start is None else t - self.clock_start
            if ran is not None and ran > self.margin_s + self.budget_s and self.paused:
                ran -= self.paused()  # (read only when the budget looks spent)
            if ran is not None and ran > self.margin_s + self.budget_s:
                return (
                    f"nodes ran past their time budget ({self.budget_s:.1f} s of the "
                    f"plant's time, {ran:.1f} s since they started); stopping them"
                )
        return None


class _Paused:
    """The SSC's paused time so far [s] (its plan's ``paused_s``), read-only."""

    def __init__(self, session_id: str) -> None:
        self.session_id = session_id
        self.view: NodeView | None = None

    def __call__(self) -> float:
        try:
            if self.view is None:
                self.view = NodeView.open(self.session_id, "ssc")
                if self.view is None:
                    return 0.0
            return float(self.view.read("plan", 0)["paused_s"])
        except Exception:
            return 0.0

    def close(self) -> None:
        if self.view is not None:
            self.view.close()
            self.view = None


def _has_ddm(spec: NodeSpec) -> bool:
    return any(w.role == "ddm" for w in spec.workers)


# How long the group's own e-stop (a faulted node's DDM -> the others') has
# before the session owner relays it to the nodes it has not reached [s]:
# a part of a 200 Hz cycle; the DDMs carry it in 1-3 ms. A node whose DDM is
# down (none, or the one that failed) is relayed at once.
RELAY_GRACE_S = 0.0015
# SCHED_RR while the owner waits on its nodes, above every controller process
# (the e-stop relay must not queue behind a fault's clean-up); its chores (the
# progress display, starting a node) run at the normal policy
OWNER_PRIORITY = 30


class _Relay:
    """The session owner's relay of a node's e-stop to the rest of the group."""

    def __init__(self, nodes: list[_Node], session_id: str) -> None:
        self.nodes = nodes
        self.session_id = session_id
        self.due: list[tuple[float, _Node, str]] = []
        self.done: set[int] = set()
        self._views: dict[str, NodeView] = {}

    def request(self, pid: int, now: float) -> None:
        """A manager faulted (its SIGCHLD by kill): relay its e-stop."""
        source = next((n for n in self.nodes if n.pid == pid), None)
        if source is None or source.pid in self.done:
            return
        self.done.add(source.pid)
        from redistro.process.manager import RELAY_FILE

        # the manager wrote it before it signalled (the receiving managers
        # name their source from it)
        door = ""
        with contextlib.suppress(OSError):
            folder = Path(source.spec.result_path).parent
            door = (folder / f"{RELAY_FILE}.{source.spec.node}").read_text().strip()
        # no door: at once, to every other node (one already stopped ignores it);
        # a door: after the grace, to the nodes its DDM has not reached
        self.due.append((now + (0.0 if door == "no door" else RELAY_GRACE_S), source, door))

    @property
    def next_s(self) -> float | None:
        return min((d[0] for d in self.due), default=None)

    def poll(self, now: float) -> None:
        due = [d for d in self.due if d[0] <= now]
        if not due:
            return
        self.due = [d for d in self.due if d[0] > now]
        checked = all(door != "no door" for _, _, door in due)
        for n in self.nodes:
            if n.status is not None or any(n is s for _, s, _ in due):
                continue
            if not checked or not self._stopped(n):
                signals.send(n.pidfd, signals.SIG_ESTOP)

    def prepare(self) -> None:
        """Attach the running nodes' Local Data ahead of any fault (an attach
        costs milliseconds; the relay has a part of a cycle)."""
        for n in self.nodes:
            if n.status is None and n.pid and n.spec.node not in self._views:
                view = NodeView.open(self.session_id, n.spec.node)
                if view is not None:
                    with contextlib.suppress(Exception):
                        view.block("manager")  # mapped now, read at the fault
                    self._views[n.spec.node] = view

    def _stopped(self, n: _Node) -> bool:
        """Whether node ``n`` has its e-stop already (its manager block says so)."""
        view = self._views.get(n.spec.node)
        if view is None:
            return False  # not attached: relay (a second e-stop is harmless)
        try:
            return view.estop()
        except Exception:
            return False

    def close(self) -> None:
        for view in self._views.values():
            view.close()
        self._views.clear()


def _wait_nodes(
    nodes: list[_Node],
    budget_s: float | None,
    on_wait: Callable[[], None] | None,
    clock: Callable[[], float | None] | None = None,
    side: _Beside | None = None,
) -> None:
    start = time.monotonic()
    specs = [n.spec for n in nodes]
    margin = max(s.startup_timeout_s + s.shutdown_timeout_s for s in specs) + 5.0
    if budget_s is None and all(s.cycles for s in specs):
        budget_s, clock = max(s.cycles / s.rate_hz for s in specs), None
    paused = _Paused(specs[0].session_id) if any(s.kind == "ssc" for s in specs) else None
    budget = _Budget(budget_s, margin, start, clock, paused)
    relay = _Relay(nodes, specs[0].session_id)
    from redistro.ipc import sched

    raised = specs[0].sched_policy in ("auto", "rr") and os.sched_getscheduler(0) in (
        os.SCHED_OTHER,
        os.SCHED_BATCH,
    )
    if raised:
        raised = sched.apply(OWNER_PRIORITY, None, "rr").policy == "SCHED_RR"
    try:
        _wait_loop(nodes, budget, on_wait, relay, side or _Beside(None))
    finally:
        relay.close()
        if paused is not None:
            paused.close()
        if raised:
            sched.leave_real_time()


def _wait_loop(
    nodes: list[_Node],
    budget: _Budget,
    on_wait: Callable[[], None] | None,
    relay: _Relay,
    side: _Beside,
) -> None:
    spent = False
    group_stop: tuple[float, str] | None = None  # (when, why): the fallback stop
    while any(n.status is None for n in nodes):
        busy = group_stop is not None or not side.done
        timeout = 0.02 if busy else 0.2
        if relay.next_s is not None:
            timeout = max(0.0, min(timeout, relay.next_s - time.monotonic()))
        info = signals.wait(OWNER_WAIT, timeout)
        now = time.monotonic()
        if info is not None and info.si_signo == signal.SIGCHLD and info.si_code == SI_USER:
            relay.request(info.si_pid, now)  # a manager faulted: relay its e-stop
        relay.poll(now)
        _chore(side.poll, nodes, now)
        for n in nodes:
            if n.status is None:
                pid, status = os.waitpid(n.pid, os.WNOHANG)
                if pid:
                    n.status = status
                    if not n.result().ok and group_stop is None:
                        # the group's own e-stop (through the DDMs) ends the
                        # other nodes within a few cycles; stopping them is
                        # the fallback, after a grace
                        with_ddms = all(_has_ddm(o.spec) for o in nodes)
                        grace = GROUP_STOP_GRACE_S if with_ddms else RELAYED_STOP_GRACE_S
                        group_stop = (now + grace, f"a fault in {n.spec.node}")
        if not relay.due and len(relay._views) < len(nodes):
            _chore(relay.prepare)
        if group_stop is not None and now >= group_stop[0]:
            for n in nodes:
                n.stop(group_stop[1], now)
        if info is not None and info.si_signo in signals.STOP_SIGNALS:
            for n in nodes:
                n.stop(signal.Signals(info.si_signo).name, now)
        why = None if spent else budget.exceeded(now)
        if why is not None:
            spent = True
            log.error("%s", why)
            for n in nodes:
                n.stop("the session's time budget", now)
        for n in nodes:
            if n.status is None and n.kill_at is not None and now > n.kill_at:
                signals.send(n.pidfd, signal.SIGKILL)
        if on_wait is not None:
            _chore(on_wait)


def _chore(fn: Callable[..., _T], *args: Any) -> _T:
    """Run an owner's chore at the normal policy."""
    from redistro.ipc import sched

    with sched.normal_policy():
        return fn(*args)


def reap_descendants(timeout_s: float, keep: frozenset[int] = frozenset()) -> list[int]:
    """Wait for orphaned descendants (we are their subreaper); SIGKILL stragglers.

    keep: children to leave alone (and not wait for), with those in SPARED."""
    keep = keep | frozenset(SPARED)
    me = os.getpid()
    deadline = time.monotonic() + timeout_s
    killed: list[int] = []
    while True:
        for pid in signals.children_of(me):
            if pid not in keep:
                with contextlib.suppress(ChildProcessError):
                    os.waitpid(pid, os.WNOHANG)
        left = [p for p in signals.children_of(me) if p not in keep]
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
    """``path`` written whole (a fresh temporary name, then renamed over it),
    in its folder (a run folder, made safe by the session)."""
    from redistro import files

    if not path.parent.is_dir():
        files.make_folder(path.parent, "folder")
    files.replace(path, json.dumps(data, indent=1) + "\n")

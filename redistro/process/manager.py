"""The Manager: interval timer, sync signals, heartbeat check, fault termination.

One manager per node. Initialization creates the node's Local Data and
semaphores, runs :meth:`Manager.initialize` (the ESC freezes its robot there,
before any worker exists), spawns the workers and waits until each is ready.
Routine takes one timer tick per cycle: checks heartbeats, prints message
boxes, publishes the cycle and sends the sync signal to every worker. Worker
exits are seen at once (SIGCHLD, reaped through waitpid and watched through
pidfds). Cleanup ends the workers, reaps them, writes the result and removes
every IPC object the node created.

Past the house's ~400 lines: the four states and the fault reaction are
one sequence, read top to bottom; the bookkeeping is in ``books.py``.
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

from redistro import files
from redistro.errors import NodeFault, TornReadTimeout
from redistro.ipc import names, sched, signals
from redistro.ipc.sem import Semaphore
from redistro.ipc.session import LOCK_FD_ENV, Manifest
from redistro.ipc.timer import IntervalTimer
from redistro.localdata import Block, LocalData, ProcState
from redistro.localdata.block import Record
from redistro.localdata.layout import MANAGER, MSG_TEXT
from redistro.process import hooks
from redistro.process.books import NodeBooks, node_local_data
from redistro.process.result import NodeResult
from redistro.process.spawn import spawn
from redistro.process.spec import EXIT_FAILED, NodeSpec
from redistro.process.stats import Samples
from redistro.process.worker import IDLE_GUARD_NS

log = logging.getLogger(__name__)

ROUTINE_WAIT = (
    frozenset(
        {signal.SIGALRM, signal.SIGCHLD, signals.SIG_ORPHAN, signals.SIG_WAKE, signals.SIG_ESTOP}
    )
    | signals.STOP_SIGNALS
)
RELAY_FILE = "estop"  # in the session folder, estop.<node>: a faulted node asks for a relay
START_WAIT = frozenset({signals.SIG_ORPHAN, signals.SIG_ESTOP}) | signals.STOP_SIGNALS


def describe_status(status: int) -> str:
    if os.WIFSIGNALED(status):
        return f"killed by {signal.Signals(os.WTERMSIG(status)).name}"
    if os.WIFEXITED(status):
        return f"exited with code {os.WEXITSTATUS(status)}"
    return f"status {status:#x}"


def iso_time(t: float) -> str:
    """UNIX time as ISO 8601 UTC with milliseconds."""
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t)) + f".{int(t % 1 * 1000):03d}Z"


class _Child:
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


class Manager:
    """Base manager; node kinds (ESC, SSC) subclass it and override the hooks."""

    def __init__(self, spec: NodeSpec, spec_path: str) -> None:
        self.spec = spec
        self.spec_path = spec_path
        self.timer = IntervalTimer(spec.rate_hz)
        self.cycle = 0
        self.result = NodeResult(node=spec.node, kind=spec.kind, session_id=spec.session_id)
        self.children: list[_Child] = []
        self.on_cycle: list[_Child] = []  # the children the sync signal goes to
        self.lateness = Samples()
        self.tick_work = Samples()
        self.missed_ticks = 0
        self.overruns = 0
        self.torn_ticks = 0  # ticks whose on_tick could not read a block consistently
        self.ld: LocalData | None = None
        self.books = NodeBooks(spec)
        self.sems: list[Semaphore] = []
        self._routine_start = 0.0
        self._routine_end = 0.0
        self._cpu_start = 0.0
        self._cpu_end = 0.0
        self.granted: sched.Granted | None = None
        self.block: Block | None = None
        self.mine = Record(MANAGER)  # the manager's own block, published whole each tick
        self._due_ns = 0
        self._tick_ns = 0
        self._estop = False
        self.wake_fd = -1
        self.idle_slices = 0  # slices of Idle work between ticks (message boxes first)
        self.cpu_latency_fd: int | None = None  # the PM QoS request, held while the node runs
        self.ring: Any = None  # the session log's ring, when the node logs
        self.capture: Any = None

    @property
    def last_error(self) -> dict[str, str]:
        """Worker name -> its last ERROR message."""
        return self.books.last_error

    # -- hooks --

    def initialize(self) -> None:
        """Runs after Local Data exists and before any worker is spawned."""

    def on_tick(self, cycle: int) -> bool:
        """Runs at every tick after the heartbeat check, before the cycle is
        dispatched. Raise NodeFault to end the session with that reason;
        return True to end it orderly (the node's work is done)."""
        return False

    def on_wake(self) -> None:
        """A worker woke the manager between ticks (SIG_WAKE): raise NodeFault
        for what it found (the ESC: its guard tripped)."""

    def on_fault(self, reason: str, message: str) -> None:
        """Runs first on any fault (the ESC freezes its robot here)."""

    def before_end(self) -> None:
        """Runs first in Cleanup, on every exit path, before the workers are
        ended (the ESC freezes its robot here)."""

    def cleanup(self) -> None:
        """Runs after every worker has been reaped."""

    # -- the four states --

    def run(self) -> int:
        started = time.time()
        signals.set_parent_death_signal(signals.SIG_ORPHAN)
        if self.spec.owner_pid and os.getppid() != self.spec.owner_pid:
            return 3
        if self.spec.messages_path:
            self.books.msg_file = files.open_append(self.spec.messages_path)
        try:
            self._initialization()
            # a developer's profile of the manager (tools/profile.py NODE/manager)
            profiled = hooks.profile(f"{self.spec.node}/manager")
            with profiled if profiled is not None else contextlib.nullcontext():
                self._routine()
        except NodeFault as fault:
            self._fault(fault.reason, str(fault))
        except Exception as exc:
            log.exception("manager of %s failed", self.spec.node)
            self._fault("abnormal", f"manager error: {exc!r}")
        finally:
            self._cleanup(started)
        return 0 if self.result.ok else 1

    def open_local_data(self, manifest: Manifest | None, memory: bool = False) -> LocalData:
        """The node's Local Data (``memory``: the in-process stand-in, for
        unit tests), the manager's block and the bookkeeping over it."""
        self.ld = ld = node_local_data(self.spec, self.timer.period_ns, manifest, memory)
        self.block = ld.writer("manager", role="manager")
        self.books.attach(ld)
        with self.block.write() as d:
            d["state"] = ProcState.INITIALIZATION
            d["pid"] = os.getpid()
        self.block.read_into(self.mine.bytes)
        return ld

    def _initialization(self) -> None:
        spec = self.spec
        manifest = Manifest.for_session(spec.session_id)
        ld = self.open_local_data(manifest)
        self.ready = Semaphore.create(
            names.object_name(spec.session_id, spec.node, "ready"), manifest
        )
        self.sems.append(self.ready)
        for j in range(len(spec.workers)):
            self.sems.append(
                Semaphore.create(names.object_name(spec.session_id, spec.node, f"go{j}"), manifest)
            )

        from redistro.log.recorder import log_topics

        topics = log_topics(spec)
        if topics:  # every cycle's logged blocks into the ring, for the logging worker
            from redistro.log.ring import Capture, LogRing, RingLayout

            layout = RingLayout.of(topics, len(spec.workers))
            self.ring = LogRing.create(spec.session_id, spec.node, layout, manifest=manifest)
            self.capture = Capture(self.ring, ld)

        self.initialize()
        # real-time priority for the routine only: the set-up above (imports,
        # opening drivers) must not hold off the plant or other nodes; the
        # workers spawned below start at the default policy (reset on fork)
        self.granted = sched.apply(
            spec.manager_priority, spec.cpus, spec.sched_policy, spec.lock_memory
        )
        if spec.cpu_latency_us is not None:
            # held until this process ends (the kernel drops it then)
            self.cpu_latency_fd = sched.hold_cpu_latency(spec.cpu_latency_us, self.granted)

        lock_fd = os.environ.get(LOCK_FD_ENV)
        # the node's wake event: what its event-driven worker (the ddm) waits on
        # beside its sockets; a producer (or this manager, on a fault) writes it
        self.wake_fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        pass_fds = ((int(lock_fd),) if lock_fd else ()) + (self.wake_fd,)
        for j, w in enumerate(spec.workers):
            proc = spawn(
                [
                    "worker",
                    "--spec",
                    self.spec_path,
                    "--index",
                    str(j),
                    "--manager-pid",
                    str(os.getpid()),
                    "--wake-fd",
                    str(self.wake_fd),
                ],
                pass_fds=pass_fds,
            )
            self.children.append(_Child(w.name, proc.pid, os.pidfd_open(proc.pid)))
            self.books.pids[j] = proc.pid
            proc.returncode = 0  # reaped by _Child.reap, not by Popen
        self.on_cycle = [c for c, w in zip(self.children, spec.workers, strict=True) if w.on_cycle]
        self._wait_ready()

    def _wait_ready(self) -> None:
        deadline = time.monotonic() + self.spec.startup_timeout_s
        n_ready = 0
        while n_ready < len(self.children):
            if self.ready.acquire(0.02):
                n_ready += 1
                continue
            self._check_children()
            info = signals.wait(START_WAIT, 0)
            if info is not None and info.si_signo == signals.SIG_ESTOP:
                # another node faulted while this one started: its robot
                # stays frozen, and the node ends on the group's e-stop
                raise NodeFault("estop", self._relayed_estop() + " during start-up")
            if info is not None:
                raise NodeFault("abnormal", self._stop_text(info.si_signo) + " during start-up")
            self.books.drain_messages()
            if time.monotonic() > deadline:
                late = [
                    c.name
                    for c, r in zip(self.children, self.books.rows, strict=True)
                    if int(r.read()["state"]) != ProcState.ROUTINE
                ]
                raise NodeFault(
                    "abnormal",
                    f"workers not ready within {self.spec.startup_timeout_s} s: {', '.join(late)}",
                )

    def _routine(self) -> None:
        block = self.block
        assert block is not None  # created in Initialization
        tick_timeout = max(0.5, 100 * self.timer.period_s)
        with block.write() as d:
            d["state"] = ProcState.ROUTINE
        # Hot path on local records: the manager's own block is kept locally
        # and published whole each tick; worker rows are snapshot into records.
        block.read_into(self.mine.bytes)
        import gc

        gc.collect()
        gc.freeze()
        gc.disable()
        self._routine_start = time.monotonic()
        self._cpu_start = time.process_time()
        self.timer.start()
        try:
            while True:
                info = signals.wait(ROUTINE_WAIT, tick_timeout)
                if info is None:
                    raise NodeFault("abnormal", f"no timer tick for {tick_timeout} s")
                sig = info.si_signo
                if sig == signal.SIGCHLD:
                    self._check_children()
                    continue
                if sig == signals.SIG_ESTOP:  # the session owner relays a node's e-stop
                    raise NodeFault("estop", self._relayed_estop())
                if sig == signals.SIG_WAKE:
                    # a worker's e-stop or trip: act now, not at the next tick
                    self.books.check_failed()
                    self.books.check_estop_requests()
                    with contextlib.suppress(TornReadTimeout):  # the tick looks again
                        self.on_wake()
                    continue
                if sig != signal.SIGALRM:
                    raise NodeFault("abnormal", self._stop_text(sig))
                if self.tick(time.monotonic_ns()):
                    return
                # Idle: what need not hold the cycle back, after the syncs
                self._idle(self._due_ns + self.timer.period_ns - IDLE_GUARD_NS)
        finally:
            self.timer.stop()
            self._routine_end = time.monotonic()
            self._cpu_end = time.process_time()
            gc.enable()

    def tick(self, now: int) -> bool:
        """One timer tick taken at ``now`` (CLOCK_MONOTONIC ns): the cycle
        that ended is captured for the log and its heartbeats checked, the
        node's own check runs, the next cycle is published and every worker
        on the cycle gets its sync. True: the routine is over (the node's
        work is done, or its cycle count reached). A fault raises
        :class:`NodeFault`."""
        due, late, missed = self.timer.due(now)
        self.lateness.add(late)
        if missed:
            self.overruns += 1
            self.missed_ticks += missed
        if self.cycle:
            if self.capture is not None:  # the cycle that ended, for the session log
                self.capture(self.cycle, self._due_ns, self._tick_ns, self._estop)
            self.books.check_heartbeats(self.cycle, self._due_ns, self.timer.period_ns)
        if self.spec.cycles and self.cycle >= self.spec.cycles:
            return True
        try:
            if self.on_tick(self.cycle):
                return True
        except TornReadTimeout:
            # a worker held off inside its write (a host stall): no
            # consistent view this tick; the next tick looks again (a
            # writer that stays stuck misses its heartbeats)
            self.torn_ticks += 1
        self.cycle += 1
        mine = self.mine
        mine["cycle"] = self.cycle
        mine["tick_due_ns"] = due
        mine["tick_ns"] = now
        mine["overruns"] = self.overruns
        mine["missed_ticks"] = self.missed_ticks
        assert self.block is not None
        self.block.publish(mine.bytes)
        for child in self.on_cycle:
            child.sync()
        self._due_ns = due
        self._tick_ns = now
        self.tick_work.add(time.monotonic_ns() - now)
        return False

    def idle(self, deadline_ns: int) -> bool:
        """A node's own Idle work (see :meth:`Worker.idle`): one short slice
        per call, True while there is more. Default: nothing."""
        return False

    def _idle(self, deadline_ns: int) -> None:
        """The manager's Idle state, after the tick's syncs went out: the
        workers' message boxes to the log and messages.log, then the node's
        own idle work in slices, until the deadline or the next tick (pending,
        it is taken by the wait that follows)."""
        self.books.drain_messages()
        self.idle_slices += 1
        clock = time.monotonic_ns
        while clock() < deadline_ns and signal.SIGALRM not in signal.sigpending():
            more = self.idle(deadline_ns)
            self.idle_slices += 1
            if not more:
                return

    def _relayed_estop(self) -> str:
        source = "another node"
        if self.spec.result_path:
            # the faulted nodes' relay files name them
            mine = f"{RELAY_FILE}.{self.spec.node}"
            with contextlib.suppress(OSError):
                folder = Path(self.spec.result_path).parent
                found = sorted(
                    p.name.removeprefix(f"{RELAY_FILE}.")
                    for p in folder.glob(f"{RELAY_FILE}.*")
                    if p.name != mine
                )
                source = ", ".join(found) or source
        return f"e-stop from {source} (relayed by the session owner)"

    def _stop_text(self, sig: int) -> str:
        if sig == signals.SIG_ORPHAN:
            return "session owner died"
        return f"interrupted by {signal.Signals(sig).name}"

    # -- checks --

    def _check_children(self) -> None:
        """Reap any worker that exited; a worker exit during the session is a fault."""
        books = self.books
        for j, child in enumerate(self.children):
            if child.alive and child.reap():
                books.door_down(j)
                status = child.status or 0
                if os.WIFEXITED(status) and os.WEXITSTATUS(status) == EXIT_FAILED:
                    # it said why in its box: that is the cause
                    books.drain_messages()
                    why = books.failed.get(j, describe_status(status))
                    raise NodeFault("abnormal", f"{books.who(j)} {why}")
                raise NodeFault(
                    "abnormal",
                    f"{books.who(j)} died: {describe_status(status)} at cycle {self.cycle}",
                )

    def _drain_messages(self) -> None:
        self.books.drain_messages()

    def _message(self, process: str, level: int, text: str, stamp_ns: int | None = None) -> None:
        self.books.message(process, level, text, stamp_ns)

    def _fault(self, reason: str, message: str) -> None:
        r = self.result
        if not r.ok:
            return  # the first fault is the cause; later ones are consequences
        r.result, r.reason = reason, message
        r.fault_monotonic_ns, r.fault_cycle = time.monotonic_ns(), self.cycle
        # act first (e-stop for the workers, the ESC freezes its robot), then tell
        self._estop = True
        if self.block is not None:
            with self.block.write() as d:
                d["estop"] = 1
                d["fault_reason"] = reason.encode()[:16]
                d["fault_text"] = message.encode("utf-8", "replace")[:MSG_TEXT]
        if self.wake_fd >= 0:  # the ddm carries the e-stop to the group now
            with contextlib.suppress(OSError):
                os.eventfd_write(self.wake_fd, 1)
        try:
            self.on_fault(reason, message)  # the ESC's robot: frozen now
        except Exception:
            log.exception("on_fault hook failed")
        if reason != "estop" and self.spec.owner_pid:
            # ... and the session owner relays it to the nodes it has not
            # reached within a part of a cycle (at once when this node has no
            # DDM to carry it): a SIGCHLD sent by kill (SI_USER) asks for that
            # (an owner that does not expect it ignores it); the relay file
            # says whether this node's door is down
            with contextlib.suppress(OSError):
                if self.spec.result_path:
                    relay = Path(self.spec.result_path).parent / f"{RELAY_FILE}.{self.spec.node}"
                    relay.write_text("no door\n" if self.books.no_door else "door\n")
                os.kill(self.spec.owner_pid, signal.SIGCHLD)
        # the reaction is out; what is left (the workers' end, the results)
        # must not hold the simulated plant off the CPUs while it applies
        # the group's freezes
        sched.leave_real_time()
        self._message("manager", logging.ERROR, f"{reason}: {message}")

    # -- cleanup --

    def _cleanup(self, started: float) -> None:
        try:
            self.timer.stop()
            try:
                self.before_end()
            except Exception as exc:
                log.exception("before_end hook failed")
                self._fault("abnormal", f"cleanup error: {exc!r}")
            if self.block is not None:
                with self.block.write() as d:
                    d["state"] = ProcState.CLEANUP
            # the robot is frozen (before_end); what is left is bookkeeping
            sched.leave_real_time()
            self._end_workers()
            try:
                self.cleanup()
            except Exception as exc:
                log.exception("cleanup hook failed")
                self._fault("abnormal", f"cleanup error: {exc!r}")
            self._collect(started)
        finally:
            for child in self.children:
                os.close(child.pidfd)
            if self.wake_fd >= 0:
                os.close(self.wake_fd)
                self.wake_fd = -1
            if self.cpu_latency_fd is not None:
                os.close(self.cpu_latency_fd)  # the request ends with it
                self.cpu_latency_fd = None
            for sem in self.sems:
                sem.close()
                sem.unlink()
            if self.ring is not None:
                self.capture = None  # its kernel plans hold views of the mappings
                self.ring.close()
                self.ring.unlink()
            if self.ld is not None:
                self.ld.close()
                self.ld.unlink()
            self._write_result()
            if self.books.msg_file is not None:
                self.books.msg_file.close()

    def _end_workers(self) -> None:
        for j, child in enumerate(self.children):
            if child.alive:
                # A hung worker gets no chance to clean up: it would not take it.
                signals.send(
                    child.pidfd, signal.SIGKILL if j in self.books.hung else signals.SIG_END
                )
        for sem in self.sems[1:]:  # wake workers waiting at a collecting point
            sem.release()
        deadline = time.monotonic() + self.spec.shutdown_timeout_s
        while any(c.alive for c in self.children):
            for child in self.children:
                child.reap()
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            signals.wait(frozenset({signal.SIGCHLD}), min(remaining, 0.05))
        for child in self.children:
            if child.alive:
                self._message(
                    "manager", logging.WARNING, f"worker {child.name} did not end in time; killed"
                )
                signals.send(child.pidfd, signal.SIGKILL)
                child.reap(wait=True)

    def _collect(self, started: float) -> None:
        books = self.books
        books.drain_messages()
        routine_s = max(0.0, self._routine_end - self._routine_start)
        manager_cpu_s = max(0.0, self._cpu_end - self._cpu_start)
        exits = [
            describe_status(c.status) if c.status is not None else "unknown" for c in self.children
        ]
        exits += ["unknown"] * (len(self.spec.workers) - len(exits))
        workers = books.worker_results(routine_s, exits) if books.rows else []
        cpu_s = manager_cpu_s + sum(w.cpu_s for w in workers)
        r = self.result
        r.started, r.ended = iso_time(started), iso_time(time.time())
        r.rate_hz = self.spec.rate_hz
        r.period_us = self.timer.period_ns / 1e3
        r.cycles = self.cycle
        r.routine_s = round(routine_s, 3)
        r.manager_overruns = self.overruns
        r.missed_ticks = self.missed_ticks
        r.worker_overruns = sum(w.overruns for w in workers)
        r.worker_skipped = sum(w.skipped for w in workers)
        r.late_heartbeats = books.late_heartbeats
        r.missed_heartbeats = books.missed_heartbeats
        r.deadline_misses = books.deadline_misses
        r.incomplete_cycles = books.incomplete_cycles
        r.torn_ticks = self.torn_ticks
        r.idle_slices = self.idle_slices
        # timer periods without a completed cycle: finished late, unfinished
        # at the next tick, or a tick never taken
        r.overruns = books.deadline_misses + books.incomplete_cycles + self.missed_ticks
        r.lateness_us = self.lateness.summary_us()
        r.makespan_us = books.makespan.summary_us()
        r.manager_work_us = self.tick_work.summary_us()
        r.cpu_s = round(cpu_s, 3)
        r.cpu_percent = round(100 * cpu_s / routine_s, 1) if routine_s else 0.0
        r.manager = {
            "pid": os.getpid(),
            "scheduling": self.granted.as_dict() if self.granted else {},
            "cpu_s": round(manager_cpu_s, 3),
            "cpu_percent": round(100 * manager_cpu_s / routine_s, 2) if routine_s else 0.0,
            "tick_work_us": self.tick_work.summary_us(),
        }
        r.workers = workers
        r.messages = books.messages
        r.messages_lost = books.messages_lost

    def _write_result(self) -> None:
        if not self.spec.result_path:
            return
        files.replace(self.spec.result_path, json.dumps(self.result.as_dict(), indent=1))


def run_manager(spec_path: str) -> int:
    from redistro.process.registry import manager_class

    spec = NodeSpec.load(spec_path)
    return manager_class(spec.kind)(spec, spec_path).run()

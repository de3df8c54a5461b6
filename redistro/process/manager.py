"""The Manager: interval timer, sync signals, heartbeat check, fault termination.

One manager per node. Initialization creates the node's Local Data and
semaphores, runs :meth:`Manager.initialize` (the ESC freezes its robot there,
before any worker exists), spawns the workers and waits until each is ready.
Routine takes one timer tick per cycle: checks heartbeats, prints message
boxes, publishes the cycle and sends the sync signal to every worker. Worker
exits are seen at once (SIGCHLD, reaped through waitpid and watched through
pidfds). Cleanup ends the workers, reaps them, writes the result and removes
every IPC object the node created.

The states and their moves are :class:`~redistro.process.states.Lifecycle`'s
table; the worker processes are :mod:`redistro.process.children`'s; the
bookkeeping over Local Data is ``watch.py``'s.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from redistro import files
from redistro.errors import NodeFault, TornReadTimeout
from redistro.ipc import names, sched, signals
from redistro.ipc.sem import Semaphore
from redistro.ipc.session import LOCK_FD_ENV, Manifest
from redistro.ipc.timer import tick_source
from redistro.localdata import Block, LocalData, ProcState
from redistro.localdata.block import Record
from redistro.localdata.layout import MANAGER, MSG_TEXT
from redistro.process import hooks
from redistro.process.children import (
    Child,
    describe_status,
    end_workers,
    reap_workers,
    spawn_workers,
)
from redistro.process.result import NodeResult
from redistro.process.spec import EXIT_FAILED, NodeSpec
from redistro.process.states import CODE, Event, Lifecycle, State
from redistro.process.stats import Samples
from redistro.process.watch import WorkerWatch, node_local_data
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


def iso_time(t: float) -> str:
    """UNIX time as ISO 8601 UTC with milliseconds."""
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t)) + f".{int(t % 1 * 1000):03d}Z"


@dataclass
class Timing:
    """What the manager measures of its own cycles (into the result)."""

    lateness: Samples = field(default_factory=Samples)
    tick_work: Samples = field(default_factory=Samples)
    missed_ticks: int = 0
    overruns: int = 0
    torn_ticks: int = 0  # ticks whose on_tick could not read a block consistently
    idle_slices: int = 0  # slices of Idle work between ticks (message boxes first)
    routine: tuple[float, float] = (0.0, 0.0)  # its start and end, monotonic [s]
    cpu: tuple[float, float] = (0.0, 0.0)  # the process's CPU time then [s]

    @property
    def routine_s(self) -> float:
        return max(0.0, self.routine[1] - self.routine[0])

    @property
    def cpu_s(self) -> float:
        return max(0.0, self.cpu[1] - self.cpu[0])


class Manager:
    """Base manager; node kinds (ESC, SSC) subclass it and override the hooks."""

    def __init__(self, spec: NodeSpec, spec_path: str) -> None:
        self.spec = spec
        self.spec_path = spec_path
        self.timer = tick_source(spec.rate_hz, spec.clock)
        self.cycle = 0
        from redistro import kernels

        self.result = NodeResult(
            node=spec.node, kind=spec.kind, session_id=spec.session_id, kernels=kernels.AVAILABLE
        )
        self.life = Lifecycle(self._state_changed)
        self.children: list[Child] = []
        self.on_cycle: list[Child] = []  # the children the sync signal goes to
        self.timing = Timing()
        self.ld: LocalData | None = None
        self.watch = WorkerWatch(spec)
        self.sems: list[Semaphore] = []
        self.granted: sched.Granted | None = None
        self.block: Block | None = None
        self.mine = Record(MANAGER)  # the manager's own block, published whole each tick
        self._state_word = self.mine.word("state")
        self._due_ns = 0
        self._tick_ns = 0
        self._estop = False
        self.wake_fd = -1
        self.cpu_latency_fd: int | None = None  # the PM QoS request, held while the node runs
        self.ring: Any = None  # the session log's ring, when the node logs
        self.capture: Any = None

    @property
    def last_error(self) -> dict[str, str]:
        """Worker name -> its last ERROR message."""
        return self.watch.last_error

    def _state_changed(self, old: State, new: State) -> None:
        """The state into the manager's block: at once when the node starts
        or ends its routine; the cycle's Routine and Idle ride in the block
        each tick publishes."""
        self._state_word[0] = CODE[new]
        ends = new is State.CLEANUP  # (from any state: the plant's lockstep waits on it)
        if self.block is not None and (ends or (new is State.ROUTINE and old is not State.IDLE)):
            with self.block.write() as d:
                d["state"] = new.value
            self.block.read_into(self.mine.bytes)

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
            self.watch.msg_file = files.open_append(self.spec.messages_path)
        try:
            self._initialization()
            self.life.process(Event.READY)
            # a developer's profile of the manager (tools/profile.py NODE/manager)
            profiled = hooks.profile(f"{self.spec.node}/manager")
            with profiled if profiled is not None else contextlib.nullcontext():
                self._routine()
            self.life.process(Event.DONE)
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
        self.watch.attach(ld)
        with self.block.write() as d:
            d["state"] = ProcState.INITIALIZATION
            d["pid"] = os.getpid()
        self.block.read_into(self.mine.bytes)
        return ld

    def _initialization(self) -> None:
        spec = self.spec
        manifest = Manifest.for_session(spec.session_id)
        ld = self.open_local_data(manifest)
        node_semaphores(spec, manifest, self.sems)  # ready, then each worker's go
        self.ready = self.sems[0]
        self.ring = log_ring(spec, manifest)
        if self.ring is not None:  # every cycle's logged blocks, for the logging worker
            from redistro.log.ring import Capture

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
        self.children = spawn_workers(spec, self.spec_path, self.wake_fd, pass_fds)
        for j, child in enumerate(self.children):
            self.watch.pids[j] = child.pid
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
            start_signal(self.spec, signals.wait(START_WAIT, 0))
            self.watch.drain_messages()
            if time.monotonic() > deadline:
                late = [
                    c.name
                    for c, r in zip(self.children, self.watch.rows, strict=True)
                    if int(r.read()["state"]) != ProcState.ROUTINE
                ]
                raise NodeFault(
                    "abnormal",
                    f"workers not ready within {self.spec.startup_timeout_s} s: {', '.join(late)}",
                )

    def _routine(self) -> None:
        """Routine and Idle, cycle after cycle, until the node's work is
        done (returns) or a fault (raises NodeFault)."""
        tick_timeout = max(0.5, 100 * self.timer.period_s)
        if self.spec.clock == "lockstep":  # (the plant's first tick waits for every link)
            tick_timeout = max(tick_timeout, self.spec.startup_timeout_s)
        import gc

        gc.collect()
        gc.freeze()
        gc.disable()
        t = self.timing
        t.routine, t.cpu = (time.monotonic(), 0.0), (time.process_time(), 0.0)
        self.timer.start()
        life = self.life
        try:
            while True:
                info = signals.wait(ROUTINE_WAIT, tick_timeout)
                if info is None:
                    raise NodeFault("abnormal", f"no timer tick for {tick_timeout} s")
                if info.si_signo != signal.SIGALRM:
                    self._between_ticks(info.si_signo)
                    continue
                if life.state is State.IDLE:
                    life.process(Event.TICK)
                if self.tick(time.monotonic_ns()):
                    return
                life.process(Event.SYNCED)
                # Idle: what need not hold the cycle back, after the syncs
                self._idle(self._due_ns + self.timer.period_ns - IDLE_GUARD_NS)
        finally:
            self.timer.stop()
            t.routine, t.cpu = (t.routine[0], time.monotonic()), (t.cpu[0], time.process_time())
            gc.enable()

    def _between_ticks(self, sig: int) -> None:
        """A signal other than the timer's: a worker exited, the session
        owner relays an e-stop, a worker woke the manager (its e-stop or a
        trip: acted on now, not at the next tick), or a stop."""
        if sig == signal.SIGCHLD:
            self._check_children()
        elif sig == signals.SIG_ESTOP:
            raise NodeFault("estop", relayed_estop(self.spec))
        elif sig == signals.SIG_WAKE:
            self.watch.check_failed()
            self.watch.check_estop_requests()
            with contextlib.suppress(TornReadTimeout):  # the tick looks again
                self.on_wake()
        else:
            raise NodeFault("abnormal", stop_text(sig))

    def tick(self, now: int) -> bool:
        """One timer tick taken at ``now`` (CLOCK_MONOTONIC ns): the cycle
        that ended is captured for the log and its heartbeats checked, the
        node's own check runs, the next cycle is published and every worker
        on the cycle gets its sync. True: the routine is over (the node's
        work is done, or its cycle count reached). A fault raises
        :class:`NodeFault`."""
        due, late, missed = self.timer.due(now)
        t = self.timing
        t.lateness.add(late)
        if missed:
            t.overruns += 1
            t.missed_ticks += missed
        if self.cycle:
            if self.capture is not None:  # the cycle that ended, for the session log
                self.capture(self.cycle, self._due_ns, self._tick_ns, self._estop)
            self.watch.check_heartbeats(self.cycle, self._due_ns, self.timer.period_ns)
        if self.spec.cycles and self.cycle >= self.spec.cycles:
            return True
        try:
            if self.on_tick(self.cycle):
                return True
        except TornReadTimeout:
            # a worker held off inside its write (a host stall): no
            # consistent view this tick; the next tick looks again (a
            # writer that stays stuck misses its heartbeats)
            t.torn_ticks += 1
        self.cycle += 1
        mine = self.mine
        mine["cycle"] = self.cycle
        mine["tick_due_ns"] = due
        mine["tick_ns"] = now
        mine["overruns"] = t.overruns
        mine["missed_ticks"] = t.missed_ticks
        assert self.block is not None
        self.block.publish(mine.bytes)
        for child in self.on_cycle:
            child.sync()
        self._due_ns = due
        self._tick_ns = now
        t.tick_work.add(time.monotonic_ns() - now)
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
        self.watch.drain_messages()
        self.timing.idle_slices += 1
        clock = time.monotonic_ns
        while clock() < deadline_ns and signal.SIGALRM not in signal.sigpending():
            more = self.idle(deadline_ns)
            self.timing.idle_slices += 1
            if not more:
                return

    # -- checks --

    def _check_children(self) -> None:
        """Reap any worker that exited; a worker exit during the session is a fault."""
        watch = self.watch
        for j, child in enumerate(self.children):
            if child.alive and child.reap():
                watch.door_down(j)
                status = child.status or 0
                if os.WIFEXITED(status) and os.WEXITSTATUS(status) == EXIT_FAILED:
                    # it said why in its box: that is the cause
                    watch.drain_messages()
                    why = watch.failed.get(j, describe_status(status))
                    raise NodeFault("abnormal", f"{watch.who(j)} {why}")
                raise NodeFault(
                    "abnormal",
                    f"{watch.who(j)} died: {describe_status(status)} at cycle {self.cycle}",
                )

    def _drain_messages(self) -> None:
        self.watch.drain_messages()

    def _message(self, process: str, level: int, text: str, stamp_ns: int | None = None) -> None:
        self.watch.message(process, level, text, stamp_ns)

    def _fault(self, reason: str, message: str) -> None:
        r = self.result
        if not r.ok:
            return  # the first fault is the cause; later ones are consequences
        r.result, r.reason = reason, message
        r.fault_monotonic_ns, r.fault_cycle = time.monotonic_ns(), self.cycle
        self.life.process(Event.FAULT)
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
        if reason != "estop":
            ask_for_relay(self.spec, self.watch.no_door)
        # the reaction is out; what is left (the workers' end, the results)
        # must not hold the simulated plant off the CPUs while it applies
        # the group's freezes
        sched.leave_real_time()
        self._message("manager", logging.ERROR, f"{reason}: {message}")

    # -- cleanup --

    def _cleanup(self, started: float) -> None:
        if self.life.state is not State.CLEANUP:  # (an interrupt: no fault said so)
            self.life.process(Event.FAULT)
        try:
            self.timer.stop()
            try:
                self.before_end()
            except Exception as exc:
                log.exception("before_end hook failed")
                self._fault("abnormal", f"cleanup error: {exc!r}")
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
            if self.watch.msg_file is not None:
                self.watch.msg_file.close()
            self.life.process(Event.CLEANED)

    def _end_workers(self) -> None:
        end_workers(self.children, self.watch.hung)
        for sem in self.sems[1:]:  # wake workers waiting at a collecting point
            sem.release()

        def warn(text: str) -> None:
            self._message("manager", logging.WARNING, text)

        reap_workers(self.children, self.spec.shutdown_timeout_s, warn)

    def _collect(self, started: float) -> None:
        self.watch.drain_messages()
        collect(self.result, self, started)

    def _write_result(self) -> None:
        if not self.spec.result_path:
            return
        files.replace(self.spec.result_path, json.dumps(self.result.as_dict(), indent=1))


def collect(r: NodeResult, m: Manager, started: float) -> None:
    """The node's figures into its result, at the end of Cleanup."""
    watch, t = m.watch, m.timing
    routine_s, manager_cpu_s = t.routine_s, t.cpu_s
    exits = [c.exit for c in m.children]
    exits += ["unknown"] * (len(m.spec.workers) - len(exits))
    workers = watch.worker_results(routine_s, exits) if watch.rows else []
    cpu_s = manager_cpu_s + sum(w.cpu_s for w in workers)
    r.started, r.ended = iso_time(started), iso_time(time.time())
    r.rate_hz, r.period_us = m.spec.rate_hz, m.timer.period_ns / 1e3
    r.cycles, r.routine_s = m.cycle, round(routine_s, 3)
    r.manager_overruns, r.missed_ticks = t.overruns, t.missed_ticks
    r.worker_overruns = sum(w.overruns for w in workers)
    r.worker_skipped = sum(w.skipped for w in workers)
    r.late_heartbeats, r.missed_heartbeats = watch.late_heartbeats, watch.missed_heartbeats
    r.deadline_misses, r.incomplete_cycles = watch.deadline_misses, watch.incomplete_cycles
    r.torn_ticks, r.idle_slices = t.torn_ticks, t.idle_slices
    # timer periods without a completed cycle: finished late, unfinished
    # at the next tick, or a tick never taken
    r.overruns = watch.deadline_misses + watch.incomplete_cycles + t.missed_ticks
    r.lateness_us = t.lateness.summary_us()
    r.makespan_us = watch.makespan.summary_us()
    r.manager_work_us = t.tick_work.summary_us()
    r.cpu_s = round(cpu_s, 3)
    r.cpu_percent = round(100 * cpu_s / routine_s, 1) if routine_s else 0.0
    r.manager = {
        "pid": os.getpid(),
        "scheduling": m.granted.as_dict() if m.granted else {},
        "cpu_s": round(manager_cpu_s, 3),
        "cpu_percent": round(100 * manager_cpu_s / routine_s, 2) if routine_s else 0.0,
        "tick_work_us": t.tick_work.summary_us(),
    }
    r.workers = workers
    r.messages, r.messages_lost = watch.messages, watch.messages_lost


def node_semaphores(spec: NodeSpec, manifest: Manifest, into: list[Semaphore]) -> None:
    """The node's semaphores, into ``into`` as each is made (Cleanup removes
    what was made): its workers' ready, then each worker's go."""
    for n in ["ready"] + [f"go{j}" for j in range(len(spec.workers))]:
        into.append(Semaphore.create(names.object_name(spec.session_id, spec.node, n), manifest))


def log_ring(spec: NodeSpec, manifest: Manifest) -> Any:
    """The ring the manager captures each cycle's logged blocks into (None:
    the node logs nothing)."""
    from redistro.log.recorder import log_topics

    topics = log_topics(spec)
    if not topics:
        return None
    from redistro.log.ring import LogRing, RingLayout

    layout = RingLayout.of(topics, len(spec.workers))
    return LogRing.create(spec.session_id, spec.node, layout, manifest=manifest)


def stop_text(sig: int) -> str:
    if sig == signals.SIG_ORPHAN:
        return "session owner died"
    return f"interrupted by {signal.Signals(sig).name}"


def start_signal(spec: NodeSpec, info: signal.struct_siginfo | None) -> None:
    """A signal taken during a node's start-up ends the node."""
    if info is not None and info.si_signo == signals.SIG_ESTOP:
        # another node faulted while this one started: its robot stays
        # frozen, and the node ends on the group's e-stop
        raise NodeFault("estop", relayed_estop(spec) + " during start-up")
    if info is not None:
        raise NodeFault("abnormal", stop_text(info.si_signo) + " during start-up")


def wait_in_start(spec: NodeSpec, ready: Callable[[], bool], what: str, timeout_s: float) -> None:
    """In a manager's Initialization, wait for ``ready()`` (polled every 5 ms)
    while still taking the start-up signals (an e-stop or a stop ends the
    node). what: what did not happen, for the fault's reason."""
    deadline = time.monotonic() + timeout_s
    while not ready():
        start_signal(spec, signals.wait(START_WAIT, 0.005))
        if time.monotonic() > deadline:
            raise NodeFault("abnormal", f"{what} within {timeout_s:g} s")


def relayed_estop(spec: NodeSpec) -> str:
    """What a relayed e-stop says: the nodes that faulted (their relay
    files in the session folder name them)."""
    source = "another node"
    if spec.result_path:
        mine = f"{RELAY_FILE}.{spec.node}"
        with contextlib.suppress(OSError):
            folder = Path(spec.result_path).parent
            found = sorted(
                p.name.removeprefix(f"{RELAY_FILE}.")
                for p in folder.glob(f"{RELAY_FILE}.*")
                if p.name != mine
            )
            source = ", ".join(found) or source
    return f"e-stop from {source} (relayed by the session owner)"


def ask_for_relay(spec: NodeSpec, no_door: bool) -> None:
    """A faulted node asks the session owner to relay its e-stop to the
    nodes its DDM has not reached within a part of a cycle (at once when it
    has no DDM): a SIGCHLD sent by kill (SI_USER) asks for that (an owner
    that does not expect it ignores it); the relay file says whether this
    node's door is down."""
    if not spec.owner_pid:
        return
    with contextlib.suppress(OSError):
        if spec.result_path:
            relay = Path(spec.result_path).parent / f"{RELAY_FILE}.{spec.node}"
            relay.write_text("no door\n" if no_door else "door\n")
        os.kill(spec.owner_pid, signal.SIGCHLD)


def run_manager(spec_path: str) -> int:
    from redistro.process.registry import manager_class

    spec = NodeSpec.load(spec_path)
    return manager_class(spec.kind)(spec, spec_path).run()

"""The Worker base: wait for the sync signal, run one cycle, sign the heartbeat.

Subclasses override :meth:`Worker.initialize`, :meth:`Worker.step` and
:meth:`Worker.cleanup`; the loop, stage ordering, heartbeat, overrun counting
and manager watch live here.

Past the house's ~400 lines: the four states of a worker, on the cycle and
off it (event-driven), are one runner.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import signal
import time
from typing import Any

from redistro.errors import TornReadTimeout
from redistro.ipc import names, sched, signals
from redistro.ipc.bell import Ringer
from redistro.ipc.sem import Semaphore
from redistro.localdata import LocalData, MessageBox, ProcState
from redistro.localdata.block import Record
from redistro.localdata.layout import MANAGER, PROC_STATUS
from redistro.process import hooks
from redistro.process.spec import EXIT_FAILED, NodeSpec, WorkerSpec
from redistro.process.stats import Samples

log = logging.getLogger(__name__)


class WorkerFailed(Exception):
    """A worker's own failure, already posted to its message box."""


WAIT_SET = frozenset({signals.SIG_SYNC, signals.SIG_END, signals.SIG_ORPHAN}) | signals.STOP_SIGNALS
# Idle work ends this long before the next tick is due: the slice that runs
# when the deadline passes still ends before the sync comes
IDLE_GUARD_NS = 200_000
LOCKSTEP_STAGE_NS = 400_000_000  # a collecting point's wait in lockstep (below the plant's)
# ... and again while a previous stage's process is runnable (starved of
# CPU by a loaded host, not hung), up to this (below the plant's 60 s)
LOCKSTEP_STAGE_MAX_NS = 30_000_000_000


class Worker:
    """Base class of every worker process of a node."""

    def __init__(self, spec: NodeSpec, index: int, ld: LocalData) -> None:
        self.spec = spec
        self.index = index
        self.me: WorkerSpec = spec.workers[index]
        self.params: dict[str, Any] = self.me.params
        self.ld = ld
        self.msgbox: MessageBox = ld.msgbox(index)
        self.due_ns = 0  # when the running cycle's tick was due (CLOCK_MONOTONIC)
        self.period_ns = int(ld.static["period_ns"])
        # set to ask the manager for an e-stop (published with the next heartbeat)
        self.estop_request = False
        # set when the manager must look now (a guard trip): it gets SIG_WAKE
        # after this cycle's heartbeat, once
        self.wake_manager = False
        self.wake_fd = -1  # the node's wake event (the runner sets it)
        # an event-driven worker: the fds its last wake found readable (None:
        # unknown, look at every one)
        self.ready_fds: list[int] | None = None

    def idle(self, deadline_ns: int) -> bool:
        """The Idle state: work that need not be in the cycle (statistics,
        reports, flushing), run after this cycle's step and heartbeat, before
        the next sync, in slices: do one short slice (tens of µs) and return
        whether there is more. The runner calls again while the clock is
        before ``deadline_ns`` (CLOCK_MONOTONIC) and the next sync has not
        come, so the cycle never waits on it. Default: nothing (a worker that
        does not override this pays nothing)."""
        return False

    def wants_idle(self) -> bool:
        """Whether this worker has Idle work at all (asked once, after
        Initialization): by default, whether it overrides :meth:`idle`."""
        return type(self).idle is not Worker.idle

    def wake_ddm(self) -> None:
        """Tell the node's ddm there is data to move (a fresh command or
        feedback): it waits on this event beside its sockets."""
        if self.wake_fd >= 0:
            os.eventfd_write(self.wake_fd, 1)

    # -- event-driven workers (off the cycle, rate 0) --

    def fds(self) -> list[int]:
        """File descriptors whose data this worker waits for (besides the
        node's wake event); asked again after every step."""
        return []

    def wait_s(self) -> float:
        """The longest an event-driven worker waits for data before it steps
        anyway (its heartbeat and its peers' silence are seen that often)."""
        return self.period_ns / 1e9

    # -- hooks for subclasses --

    def initialize(self) -> None:
        """Initialization: open what the worker needs (runs before the first cycle)."""

    def step(self, cycle: int) -> None:
        """Routine: one cycle's work."""

    def cleanup(self) -> None:
        """Cleanup: release what initialize() opened."""

    def post(self, text: str, level: int = logging.INFO) -> None:
        """Put a message in this process's message box (the manager prints and logs it)."""
        self.msgbox.post(text, level)


def start_worker(spec: NodeSpec, i: int, ld: LocalData, row: Any, wake_fd: int) -> Worker:
    """Worker i made and initialized (at the default priority: imports and
    opening drivers must not hold off the plant or other nodes), the
    collector's one full pass, then its real-time priority: ready for its
    Routine (the caller releases ``ready``)."""
    me = spec.workers[i]
    with row.write() as d:
        d["pid"] = os.getpid()
        d["state"] = ProcState.INITIALIZATION
    from redistro.process.registry import worker_class

    worker: Worker = worker_class(me.role)(spec, i, ld)
    worker.wake_fd = wake_fd
    try:
        worker.initialize()
    except Exception as exc:
        worker.post(f"initialization failed: {exc}", logging.CRITICAL)
        raise WorkerFailed(str(exc)) from exc
    # the collector's one full pass, then no more: before ``ready``, at the
    # default priority (in the SSC worker it takes 10-25 ms, which at 1 kHz
    # were its first cycles' heartbeats)
    gc.collect()
    gc.freeze()
    gc.disable()  # no collector pauses inside cycles; Routine allocates little
    granted = sched.apply(me.priority, me.cpus or spec.cpus, spec.sched_policy, spec.lock_memory)
    with row.write() as d:
        d["sched_policy"] = sched.POLICY_CODES[granted.policy]
        d["sched_priority"] = granted.priority
        d["nice"] = granted.nice
        d["cpu_mask"] = sched.cpu_mask(granted.cpus)
        d["state"] = ProcState.ROUTINE
    for refusal in granted.refused:
        ld.msgbox(i).post(f"scheduling: {refusal}", logging.DEBUG)
    return worker


class _Runner:
    """Drives a Worker through its four states."""

    def __init__(self, spec: NodeSpec, index: int, manager_pid: int, wake_fd: int = -1) -> None:
        self.spec = spec
        self.index = index
        self.manager_pid = manager_pid
        self.wake_fd = wake_fd
        self.period_ns = 0  # the manager's timer period, read from Local Data
        self.overruns = 0
        self.skipped = 0
        self.stage_timeouts = 0
        self.cycles = 0
        self.lateness = Samples()
        self.compute = Samples()
        self.step_cpu = Samples()
        self.cpu_start_s = 0.0
        self.estop_woken = False
        self.manager_fd = -1
        self.idle_slices = 0
        self.idle_late = 0

    def run(self) -> int:
        spec, i = self.spec, self.index
        me = spec.workers[i]
        # Die with the manager: the kernel queues SIG_ORPHAN, taken below like any signal.
        signals.set_parent_death_signal(signals.SIG_ORPHAN)
        if os.getppid() != self.manager_pid:
            return 3  # the manager died before we could watch it
        manager_fd = self.manager_fd = os.pidfd_open(self.manager_pid)
        ld = LocalData.attach(spec.session_id, spec.node)
        self.period_ns = int(ld.static["period_ns"])
        sems: list[Semaphore] = []
        worker: Worker | None = None
        try:
            row = ld.writer("proc", i, role=me.role, proc_index=i)
            manager_block = ld.block("manager")
            rows = [ld.block("proc", j) for j in range(len(spec.workers))]
            stages = spec.stages()
            preds: list[int] = []
            succs: list[int] = []
            if me.on_cycle:
                my_stage = next(k for k, s in enumerate(stages) if i in s)
                preds = stages[my_stage - 1] if my_stage > 0 else []
                succs = stages[my_stage + 1] if my_stage + 1 < len(stages) else []
            go = [
                Semaphore.attach(names.object_name(spec.session_id, spec.node, f"go{j}"))
                for j in range(len(spec.workers))
            ]
            ready = Semaphore.attach(names.object_name(spec.session_id, spec.node, "ready"))
            sems = [*go, ready]

            worker = start_worker(spec, i, ld, row, self.wake_fd)
            ready.release()

            # a developer's profile of this process (tools/profile.py; none normally)
            profiled = hooks.profile(f"{spec.node}/{me.name}")
            with profiled if profiled is not None else contextlib.nullcontext():
                if me.on_cycle:
                    reason = self._routine(
                        worker, row, manager_block, rows, preds, succs, go, manager_fd
                    )
                elif me.rate_hz > 0:
                    reason = self._routine_timed(worker, row, manager_block, me.rate_hz, manager_fd)
                else:
                    reason = self._routine_events(worker, row, manager_block, manager_fd)
            if reason:
                worker.post(reason, logging.WARNING)
            with row.write() as d:
                d["state"] = ProcState.CLEANUP
            sched.leave_real_time()
            worker.cleanup()
            return 0
        finally:
            self._finish(ld, i)
            for s in sems:
                s.close()
            ld.close()
            os.close(manager_fd)

    def _routine(
        self,
        worker: Worker,
        row: Any,
        manager_block: Any,
        rows: list[Any],
        preds: list[int],
        succs: list[int],
        go: list[Semaphore],
        manager_fd: int,
    ) -> str:
        """The cycle loop. Returns why it ended ('' for an orderly end)."""
        self.cpu_start_s = time.process_time()
        my_go = go[self.index]
        watch_s = max(0.05, 4 * self.period_ns / 1e9)
        # a collecting point gives up at the end of the period; in lockstep
        # the plant waits for the cycle, and so does a later stage
        lockstep = self.spec.clock == "lockstep"
        stage_ns = LOCKSTEP_STAGE_NS if lockstep else self.period_ns
        # Hot path on local records: snapshot into them, publish from them.
        mine = Record(PROC_STATUS)
        row.read_into(mine.bytes)  # this process is the row's one writer
        tick = Record(MANAGER)
        pred_recs = [(rows[p], Record(PROC_STATUS)) for p in preds]
        idles = worker.wants_idle()  # the Idle state, if it has work
        # in lockstep the cycle's last stage rings the plant's bell once signed
        ring = Ringer(self.spec.session_id).ring if lockstep and not succs else None
        while True:
            # Every worker wakes at the tick; a later stage then waits at its
            # collecting point. (Waiting at the collecting point first and taking
            # the sync on the token was measured slower: the wake-up work then
            # lands on the critical path of the stage chain.)
            got = self._wait_for(signals.SIG_SYNC, WAIT_SET, watch_s, manager_fd)
            if got is None:
                continue
            if isinstance(got, str):
                return got
            extra = signals.drain(signals.SIG_SYNC)
            wake_ns = time.monotonic_ns()
            if extra:
                self.overruns += 1
                self.skipped += extra
            try:
                manager_block.read_into(tick.bytes)
            except TornReadTimeout:
                # the manager held off inside its write (a host stall): no
                # cycle to sign; the next sync will have one
                self.stage_timeouts += 1
                continue
            cycle = tick["cycle"]
            due_ns = tick["tick_due_ns"]
            self.lateness.add(wake_ns - due_ns)
            if pred_recs and not self._wait_stage(
                cycle, pred_recs, my_go, due_ns + stage_ns, lockstep
            ):
                self.stage_timeouts += 1
            else:
                self._step(worker, cycle, due_ns)
            self._sign(mine, row, cycle, wake_ns, worker.estop_request)
            self._wake_for_estop(worker, manager_fd)
            for j in succs:
                go[j].release()
            if ring is not None:
                ring()
            if idles:
                self._idle(worker, due_ns + self.period_ns - IDLE_GUARD_NS)

    def _idle(self, worker: Worker, deadline_ns: int) -> None:
        """Idle work in slices until the deadline or the next sync (pending,
        it is taken by the wait that follows)."""
        clock = time.monotonic_ns
        while clock() < deadline_ns and signals.SIG_SYNC not in signal.sigpending():
            more = worker.idle(deadline_ns)
            self.idle_slices += 1
            if clock() > deadline_ns:
                self.idle_late += 1
            if not more:
                return

    @staticmethod
    def _wait_for(
        wanted: int, waits: frozenset[int], watch_s: float, manager_fd: int
    ) -> int | str | None:
        """Wait for the signal that starts a step: ``wanted`` when it came, the
        reason to stop ('' for an orderly end), or None (nothing yet, manager alive)."""
        info = signals.wait(waits, watch_s)
        if info is None:
            return None if signals.process_alive(manager_fd) else "manager vanished; stopping"
        sig = info.si_signo
        if sig == signals.SIG_END:
            return ""
        if sig == signals.SIG_ORPHAN:
            return "manager died; stopping"
        if sig != wanted:
            return f"stopped by {signal.Signals(sig).name}"
        return sig

    def _step(self, worker: Worker, cycle: int, due_ns: int) -> None:
        """One step of the worker, timed and counted."""
        t0 = time.monotonic_ns()
        c0 = time.thread_time_ns()
        worker.due_ns = due_ns
        try:
            worker.step(cycle)
        except TornReadTimeout:
            # a writer was held off inside its write (a host stall): no
            # consistent input this cycle; skip it, keep signing (a writer
            # that stays stuck misses its own heartbeats)
            self.stage_timeouts += 1
            return
        except Exception as exc:
            # CRITICAL: this worker cannot go on; the manager, woken now, ends
            # the node with this text as the cause (before our exit is seen)
            worker.post(f"failed at cycle {cycle}: {exc}", logging.CRITICAL)
            with contextlib.suppress(OSError):
                signals.send(self.manager_fd, signals.SIG_WAKE)
            raise WorkerFailed(str(exc)) from exc
        self.step_cpu.add(time.thread_time_ns() - c0)
        self.compute.add(time.monotonic_ns() - t0)
        self.cycles += 1

    def _wake_for_estop(self, worker: Worker, manager_fd: int) -> None:
        """A new e-stop request goes to the manager at once (it would see it at
        its next tick anyway): the e-stop crosses a node in well under a cycle."""
        if (worker.estop_request or worker.wake_manager) and not self.estop_woken:
            self.estop_woken = True
            with contextlib.suppress(OSError):
                signals.send(manager_fd, signals.SIG_WAKE)

    def _sign(self, mine: Record, row: Any, cycle: int, wake_ns: int, estop: bool) -> None:
        """Sign the heartbeat (the cycle done) and publish this process's counters."""
        mine["heartbeat_cycle"] = cycle
        mine["estop_request"] = 1 if estop else 0
        mine["wake_ns"] = wake_ns
        mine["done_ns"] = time.monotonic_ns()
        mine["cycles"] = self.cycles
        mine["overruns"] = self.overruns
        mine["skipped"] = self.skipped
        mine["stage_timeouts"] = self.stage_timeouts
        row.publish(mine.bytes)

    def _routine_timed(
        self, worker: Worker, row: Any, manager_block: Any, rate_hz: float, manager_fd: int
    ) -> str:
        """The loop of an off-cycle worker: its own timer at ``rate_hz``.

        Each tick it runs one step and signs its heartbeat with the newest
        manager cycle, so the manager watches it like any worker.
        """
        from redistro.ipc.timer import IntervalTimer

        self.cpu_start_s = time.process_time()
        timer = IntervalTimer(rate_hz)
        worker.period_ns = timer.period_ns
        watch_s = max(0.05, 4 * timer.period_s)
        mine = Record(PROC_STATUS)
        row.read_into(mine.bytes)
        tick = Record(MANAGER)
        waits = frozenset({signal.SIGALRM}) | WAIT_SET - {signals.SIG_SYNC}
        timer.start()
        try:
            while True:
                got = self._wait_for(signal.SIGALRM, waits, watch_s, manager_fd)
                if got is None:
                    continue
                if isinstance(got, str):
                    return got
                wake_ns = time.monotonic_ns()
                due_ns, late_ns, missed = timer.due(wake_ns)
                self.lateness.add(late_ns)
                if missed:
                    self.overruns += 1
                    self.skipped += missed
                try:
                    manager_block.read_into(tick.bytes)
                except TornReadTimeout:
                    self.stage_timeouts += 1  # no cycle to sign: the next tick will
                    continue
                cycle = tick["cycle"]
                self._step(worker, cycle, due_ns)
                self._sign(mine, row, cycle, wake_ns, worker.estop_request)
                self._wake_for_estop(worker, manager_fd)
        finally:
            timer.stop()

    def _routine_events(self, worker: Worker, row: Any, manager_block: Any, manager_fd: int) -> str:
        """The loop of an event-driven worker: it sleeps in one poll on its own
        file descriptors (``worker.fds()``), the node's wake event, its
        signals (a signalfd) and its manager's pidfd, at most
        ``worker.wait_s()``; it steps when woken by data or by that deadline,
        and signs its heartbeat with the newest manager cycle each time."""
        import select

        self.cpu_start_s = time.process_time()
        sigfd = signals.signalfd(WAIT_SET)
        poller = select.epoll()
        poller.register(sigfd, select.EPOLLIN)
        poller.register(manager_fd, select.EPOLLIN)
        if self.wake_fd >= 0:
            poller.register(self.wake_fd, select.EPOLLIN)
        watched: list[int] = []
        mine = Record(PROC_STATUS)
        row.read_into(mine.bytes)
        tick = Record(MANAGER)
        wake_fd = self.wake_fd
        last_ns = time.monotonic_ns()
        cycle = 0
        with contextlib.suppress(TornReadTimeout):
            manager_block.read_into(tick.bytes)
            cycle = tick["cycle"]
        try:
            while True:
                fds = worker.fds()
                if fds != watched:
                    for fd in watched:
                        with contextlib.suppress(OSError):
                            poller.unregister(fd)
                    for fd in fds:
                        poller.register(fd, select.EPOLLIN)
                    watched = list(fds)
                wait_s = worker.wait_s()  # (asked each time: a ddm's changes)
                wait_ns = int(wait_s * 1e9)
                events = poller.poll(wait_s)
                wake_ns = time.monotonic_ns()
                ready = [fd for fd, _ev in events]
                worker.ready_fds = ready
                if sigfd in ready:
                    for sig in signals.read_signalfd(sigfd):
                        if sig == signals.SIG_END:
                            return ""
                        if sig == signals.SIG_ORPHAN:
                            return "manager died; stopping"
                        if sig in signals.STOP_SIGNALS:
                            return f"stopped by {signal.Signals(sig).name}"
                if manager_fd in ready:
                    return "manager vanished; stopping"
                if wake_fd in ready:  # (before the step: a wake during it stays)
                    with contextlib.suppress(BlockingIOError):
                        os.eventfd_read(wake_fd)
                # the data first: the step (a command on its way) runs before
                # the bookkeeping of the wake, which it never needs; it gets
                # the manager cycle read at the previous wake
                self._step(worker, cycle, wake_ns)
                if not events:  # woken by the deadline: how late past it
                    self.lateness.add(max(0, wake_ns - last_ns - wait_ns))
                last_ns = wake_ns
                try:
                    manager_block.read_into(tick.bytes)
                except TornReadTimeout:
                    self.stage_timeouts += 1  # no cycle to sign: the next wake will
                    continue
                cycle = tick["cycle"]
                self._sign(mine, row, cycle, wake_ns, worker.estop_request)
                self._wake_for_estop(worker, manager_fd)
        finally:
            poller.close()
            os.close(sigfd)

    @staticmethod
    def _wait_stage(
        cycle: int,
        preds: list[tuple[Any, Record]],
        my_go: Semaphore,
        deadline_ns: int,
        lockstep: bool = False,
    ) -> bool:
        """Collecting point: wait until every worker of the previous stage finished ``cycle``.

        The heartbeat cycles in Local Data are the truth; the semaphore only
        wakes us. Stale posts from earlier cycles are dropped first. In
        lockstep, past the deadline the wait goes on while a previous
        stage's process is runnable (up to ``LOCKSTEP_STAGE_MAX_NS``): a
        stage starved of CPU is not a missed one, and the run stays the same.
        """
        while my_go.try_acquire():
            pass
        last_ns = deadline_ns + LOCKSTEP_STAGE_MAX_NS
        while True:
            try:
                for block, rec in preds:
                    block.read_into(rec.bytes)
                if all(rec["heartbeat_cycle"] >= cycle for _, rec in preds):
                    return True
            except TornReadTimeout:
                pass  # a predecessor stuck inside its write: keep waiting to the deadline
            now = time.monotonic_ns()
            remaining = (deadline_ns - now) / 1e9
            if remaining <= 0:
                if not lockstep or now > last_ns or not _starved(preds):
                    return False
                deadline_ns, remaining = now + LOCKSTEP_STAGE_NS, LOCKSTEP_STAGE_NS / 1e9
            my_go.acquire(remaining)

    def _finish(self, ld: LocalData, i: int) -> None:
        """Publish run statistics and go Idle (best effort: the segment may be gone)."""
        try:
            row = ld.writer("proc", i, role=self.spec.workers[i].role, proc_index=i)
            lat, comp = self.lateness.summary_us(), self.compute.summary_us()
            torn = ld.torn_reads()
            with row.write() as d:
                d["lateness_us"] = [lat["p50"], lat["p99"], lat["max"]]
                d["compute_us"] = [comp["p50"], comp["p99"], comp["max"]]
                c = self.step_cpu.summary_us()
                d["step_cpu_us"] = [c["p50"], c["p99"], c["max"]]
                d["torn_reads"] = torn
                d["cpu_s"] = time.process_time() - self.cpu_start_s if self.cpu_start_s else 0.0
                d["cycles"] = self.cycles
                d["overruns"] = self.overruns
                d["skipped"] = self.skipped
                d["stage_timeouts"] = self.stage_timeouts
                d["idle_slices"] = self.idle_slices
                d["idle_late"] = self.idle_late
                d["state"] = ProcState.IDLE
        except Exception:  # finishing must never mask the real exit path
            log.debug("could not publish final status", exc_info=True)


def run_worker(spec_path: str, index: int, manager_pid: int, wake_fd: int = -1) -> int:
    spec = NodeSpec.load(spec_path)
    try:
        return _Runner(spec, index, manager_pid, wake_fd).run()
    except WorkerFailed:
        return EXIT_FAILED  # the reason is in the message box; the manager reports it


def _starved(preds: list[tuple[Any, Record]]) -> bool:
    """A previous stage's process is runnable (starved of CPU, not hung)."""
    return any(sched.runnable(int(rec["pid"])) for _, rec in preds if int(rec["pid"]) > 0)

"""The manager's bookkeeping: what its node's Local Data says of the workers.

The manager (``process/manager.py``) owns the loop: the timer, the signals,
the worker processes and the fault reaction. This is what it reads and
keeps beside: each worker's heartbeat and e-stop request in its ``proc``
row, the message boxes (printed, logged, the last error and a failed
worker's reason kept), the cycle's makespan, and at the end every worker's
figures as a :class:`~redistro.process.result.WorkerResult`. None of it
touches a process or a signal, so unit tests run it over the in-process
Local Data (``LocalData.create(..., memory=True)``).
"""

from __future__ import annotations

import contextlib
import logging
import time
from typing import IO, Any

from redistro.errors import NodeFault, TornReadTimeout
from redistro.ipc import sched
from redistro.ipc.session import Manifest
from redistro.localdata import LocalData
from redistro.localdata.block import Record
from redistro.localdata.layout import PROC_STATUS
from redistro.process.result import WorkerResult
from redistro.process.spec import NodeSpec
from redistro.process.stats import Samples

log = logging.getLogger(__name__)

KEPT_MESSAGES = 200  # messages kept for the node's result (all go to the log)


def node_local_data(
    spec: NodeSpec, period_ns: int, manifest: Manifest | None, memory: bool = False
) -> LocalData:
    """The node's Local Data, created (by its manager) from its spec: one
    row and message box per worker, its stage (-1: off the cycle)."""
    stage_of = {j: -1 for j in range(len(spec.workers))}
    for k, group in enumerate(spec.stages()):
        for j in group:
            stage_of[j] = k
    return LocalData.create(
        spec.session_id,
        spec.node,
        node_kind=spec.kind,
        proc_names=[w.name for w in spec.workers],
        proc_roles=[w.role for w in spec.workers],
        proc_stages=[stage_of[j] for j in range(len(spec.workers))],
        robot_names=spec.robots,
        rate_hz=spec.rate_hz,
        period_ns=period_ns,
        heartbeat_limit_cycles=spec.heartbeat_limit_cycles,
        manifest=manifest,
        memory=memory,
    )


def triple(values: Any) -> dict[str, float]:
    return {k: round(float(v), 1) for k, v in zip(("p50", "p99", "max"), values, strict=True)}


class WorkerWatch:
    """A node's bookkeeping; :meth:`attach` it to the node's Local Data."""

    def __init__(self, spec: NodeSpec, msg_file: IO[str] | None = None) -> None:
        self.spec = spec
        self.msg_file = msg_file
        n = len(spec.workers)
        self.pids = [0] * n  # set as the workers are spawned
        node_limit = spec.heartbeat_limit_cycles
        # each worker's heartbeat limit (the recorders' is longer than the node's)
        self.limits = [w.heartbeat_limit_cycles or node_limit for w in spec.workers]
        self.last_hb = [0] * n
        self.last_stage = spec.stages()[-1]
        # late and missed heartbeats are counted for the workers on the cycle
        # (an off-cycle one signs when it runs: a recorder 50 times a second)
        self.per_cycle = [w.on_cycle for w in spec.workers]
        # in lockstep an off-cycle worker still runs on the wall clock (its own
        # timer, its events): it is hung when it has not signed for its limit
        # in periods of wall time, however many ticks the plant ran meanwhile
        lockstep = spec.clock == "lockstep"
        self.wall_paced = [lockstep and not w.on_cycle for w in spec.workers]
        self.signed_ns = [time.monotonic_ns()] * n  # when each heartbeat last moved
        self.late_heartbeats = 0
        self.missed_heartbeats = 0
        self.deadline_misses = 0  # cycles completed, but after their period ended
        self.incomplete_cycles = 0  # cycles whose last stage had not signed at the next tick
        self.makespan = Samples()
        self.hung: set[int] = set()
        self.messages: list[dict[str, Any]] = []
        self.last_error: dict[str, str] = {}  # worker name -> its last ERROR message
        self.failed: dict[int, str] = {}  # worker index -> why it failed (CRITICAL message)
        # the node cannot carry its e-stop to the group itself: it has no DDM
        # (an ESC-only session), or its DDM is what failed
        self.no_door = not any(w.role == "ddm" for w in spec.workers)
        self.ld: LocalData | None = None
        self.rows: list[Any] = []
        self.recs: list[Record] = []
        self.boxes: list[Any] = []

    def attach(self, ld: LocalData) -> None:
        self.ld = ld
        n = len(self.spec.workers)
        self.rows = [ld.block("proc", j) for j in range(n)]
        self.recs = [Record(PROC_STATUS) for _ in range(n)]
        self.boxes = [ld.msgbox(j) for j in range(n)]

    def who(self, j: int) -> str:
        return f"worker {self.spec.workers[j].name} (pid {self.pids[j]})"

    def door_down(self, j: int) -> None:
        """Worker ``j`` failed: if it is the node's DDM, the node's e-stop
        cannot reach the group through it."""
        if self.spec.workers[j].role == "ddm":
            self.no_door = True

    # -- every tick --

    def check_heartbeats(self, cycle: int, due_ns: int, period_ns: int) -> None:
        """Each worker must have signed the cycle that just ended (``cycle``,
        due at ``due_ns``); ``limit`` misses is a hang, an e-stop request
        ends the node: both raise :class:`NodeFault`."""
        snaps: list[Record | None] = []
        now = time.monotonic_ns()
        for j, (row, rec) in enumerate(zip(self.rows, self.recs, strict=True)):
            try:
                row.read_into(rec.bytes)
                if rec["heartbeat_cycle"] != self.last_hb[j]:
                    self.signed_ns[j] = now
                self.last_hb[j] = rec["heartbeat_cycle"]
                snaps.append(rec)
            except TornReadTimeout:
                # The worker was stopped inside its write (a VM stall, a hang):
                # no sign-up seen this cycle; its last known one stands.
                snaps.append(None)
        for j, last_hb in enumerate(self.last_hb):
            age = cycle - last_hb
            if not self.per_cycle[j]:
                pass
            elif age == 1:
                self.late_heartbeats += 1  # signed late; may still come
            elif age > 1:
                self.missed_heartbeats += 1  # a whole cycle without a sign-up
            limit = self.limits[j]
            if age >= limit and self.wall_paced[j] and now - self.signed_ns[j] < limit * period_ns:
                continue  # (lockstep: ticks ran fast, the wall clock did not)
            if age >= limit:
                self.hung.add(j)
                self.door_down(j)
                raise NodeFault(
                    "abnormal",
                    f"{self.who(j)} missed {age} heartbeats (limit {limit}) at cycle {cycle}",
                )
        self.raise_estop(snaps)
        last = [snaps[j] for j in self.last_stage]
        if all(s is not None and s["heartbeat_cycle"] == cycle for s in last):
            span = max(s["done_ns"] for s in last if s is not None) - due_ns
            self.makespan.add(span)
            if span > period_ns:
                self.deadline_misses += 1
        else:
            self.incomplete_cycles += 1

    def raise_estop(self, snaps: list[Record | None]) -> None:
        for j, snap in enumerate(snaps):
            if snap is not None and snap["estop_request"]:
                raise NodeFault("estop", self.estop_text(self.spec.workers[j].name))

    def check_estop_requests(self) -> None:
        """Between ticks: a worker asked for an e-stop and said so (SIG_WAKE)."""
        snaps: list[Record | None] = []
        for row, rec in zip(self.rows, self.recs, strict=True):
            try:
                row.read_into(rec.bytes)
                snaps.append(rec)
            except TornReadTimeout:
                snaps.append(None)
        self.raise_estop(snaps)

    def estop_text(self, name: str) -> str:
        """Why a worker asked for an e-stop: the node it came from, when a
        ddm says; else what the worker said last as an error (its message
        box drained first: it posts why before it asks)."""
        assert self.ld is not None
        for r in range(len(self.spec.robots)):
            with contextlib.suppress(Exception):
                ex = self.ld.block("exchange", r).read()
                if ex["estop_in"]:
                    src = bytes(ex["estop_source"]).decode(errors="replace")
                    return f"e-stop from {src} (through {name})"
        self.drain_messages()
        said = self.last_error.get(name)
        return f"e-stop requested by {name}: {said}" if said else f"e-stop requested by {name}"

    # -- message boxes --

    def drain_messages(self) -> None:
        for j, (w, box) in enumerate(zip(self.spec.workers, self.boxes, strict=True)):
            for stamp_ns, level, text in box.drain():
                self.message(w.name, level, text, stamp_ns)
                if level >= logging.ERROR:
                    self.last_error[w.name] = text
                if level >= logging.CRITICAL:  # the worker failed: this is why
                    self.failed.setdefault(j, text)

    def check_failed(self) -> None:
        """A worker said it failed (a CRITICAL message): end the node now."""
        self.drain_messages()
        for j, text in self.failed.items():
            self.door_down(j)
            raise NodeFault("abnormal", f"{self.who(j)} {text}")

    def message(self, process: str, level: int, text: str, stamp_ns: int | None = None) -> None:
        line = f"[{self.spec.node}/{process}] {text}"
        log.log(level, "%s", line)
        if self.msg_file is not None:
            stamp = (stamp_ns or time.monotonic_ns()) / 1e9
            self.msg_file.write(f"{stamp:.6f} {logging.getLevelName(level)} {line}\n")
        if len(self.messages) < KEPT_MESSAGES:
            self.messages.append(
                {"process": process, "level": logging.getLevelName(level), "text": text}
            )

    @property
    def messages_lost(self) -> int:
        return sum(b.lost for b in self.boxes)

    # -- the end --

    def worker_results(self, routine_s: float, exits: list[str]) -> list[WorkerResult]:
        """Every worker's figures from its row (``exits``: how each ended)."""
        policies = {v: k for k, v in sched.POLICY_CODES.items()}
        out: list[WorkerResult] = []
        for j, w in enumerate(self.spec.workers):
            row = self.rows[j].read()
            cpu_s = float(row["cpu_s"])
            out.append(
                WorkerResult(
                    name=w.name,
                    role=w.role,
                    pid=self.pids[j],
                    stage=w.stage,
                    cycles=int(row["cycles"]),
                    overruns=int(row["overruns"]),
                    skipped=int(row["skipped"]),
                    stage_timeouts=int(row["stage_timeouts"]),
                    torn_reads=int(row["torn_reads"]),
                    idle_slices=int(row["idle_slices"]),
                    idle_late=int(row["idle_late"]),
                    lateness_us=triple(row["lateness_us"]),
                    compute_us=triple(row["compute_us"]),
                    step_cpu_us=triple(row["step_cpu_us"]),
                    cpu_s=round(cpu_s, 3),
                    cpu_percent=round(100 * cpu_s / routine_s, 2) if routine_s else 0.0,
                    scheduling={
                        "policy": policies[int(row["sched_policy"])],
                        "priority": int(row["sched_priority"]),
                        "nice": int(row["nice"]),
                        "cpus": sched.cpus_of_mask(int(row["cpu_mask"])),
                    },
                    exit=exits[j],
                )
            )
        return out

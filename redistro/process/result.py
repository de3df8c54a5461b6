"""A node's result, typed: what its manager fills, writes once at its end
(``<node>.result.json`` beside its spec) and the session owner reads back.

One name per figure, from the manager to ``summary.json``: ``overruns`` is
the number of timer periods without a completed cycle (finished late,
unfinished at the next tick, or a tick never taken) everywhere. The kinds'
own figures ride in :class:`EscResult` and :class:`SscResult`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

Percentiles = dict[str, float]  # p50, p99, max [µs]


@dataclass
class WorkerResult:
    """One worker process of a node: its counters and timings."""

    name: str
    role: str = ""
    pid: int = 0
    stage: int = 0
    cycles: int = 0
    overruns: int = 0
    skipped: int = 0
    stage_timeouts: int = 0
    torn_reads: int = 0
    idle_slices: int = 0
    idle_late: int = 0
    lateness_us: Percentiles = field(default_factory=dict)
    compute_us: Percentiles = field(default_factory=dict)
    step_cpu_us: Percentiles = field(default_factory=dict)
    cpu_s: float = 0.0
    cpu_percent: float = 0.0
    scheduling: dict[str, Any] = field(default_factory=dict)
    exit: str = "unknown"


@dataclass
class EscResult:
    """An ESC's own figures: its robot, the guard's trip, the freezes, its
    calibration, its positions at the end and its ddm's exchange."""

    robot: str
    violation: dict[str, Any] | None = None
    freeze_monotonic_ns: list[int] = field(default_factory=list)
    calibration: dict[str, Any] | None = None
    positions: dict[str, Any] | None = None
    ddm: dict[str, Any] | None = None


@dataclass
class SscResult:
    """An SSC's own figures: its robots' exchanges and the task's segments."""

    robots: list[str] = field(default_factory=list)
    ddm: dict[str, dict[str, Any]] = field(default_factory=dict)
    starving_cycles_max: int = 0
    segments: list[dict[str, Any]] = field(default_factory=list)
    insertion_depth_m: float = 0.0
    insertion_depth_t_s: float | None = None
    hole_depth_m: float = 0.0
    search: dict[str, Any] = field(default_factory=dict)
    clearance: dict[str, Any] = field(default_factory=dict)  # the watch's nearest
    operator: dict[str, int] = field(default_factory=dict)  # commands accepted, refused


@dataclass
class NodeResult:
    """One node's end: how it ended and what its cycles cost."""

    node: str
    kind: str = ""
    result: str = "ok"
    reason: str = ""
    kernels: bool = False  # the compiled kernels ran (not turned off, REDISTRO_KERNELS=0)
    session_id: str = ""
    started: str = ""
    ended: str = ""
    rate_hz: float = 0.0
    period_us: float = 0.0
    cycles: int = 0
    routine_s: float = 0.0
    overruns: int = 0  # timer periods without a completed cycle
    manager_overruns: int = 0
    missed_ticks: int = 0
    worker_overruns: int = 0
    worker_skipped: int = 0
    late_heartbeats: int = 0
    missed_heartbeats: int = 0
    deadline_misses: int = 0
    incomplete_cycles: int = 0
    torn_ticks: int = 0
    idle_slices: int = 0
    lateness_us: Percentiles = field(default_factory=dict)
    makespan_us: Percentiles = field(default_factory=dict)
    manager_work_us: Percentiles = field(default_factory=dict)
    cpu_s: float = 0.0
    cpu_percent: float = 0.0
    manager: dict[str, Any] = field(default_factory=dict)
    workers: list[WorkerResult] = field(default_factory=list)
    messages: list[dict[str, Any]] = field(default_factory=list)
    messages_lost: int = 0
    fault_monotonic_ns: int | None = None
    fault_cycle: int | None = None
    stragglers_killed: list[int] = field(default_factory=list)
    esc: EscResult | None = None
    ssc: SscResult | None = None

    @property
    def ok(self) -> bool:
        return self.result == "ok"

    @property
    def robot(self) -> str | None:
        """The ESC's robot (None for other nodes)."""
        return self.esc.robot if self.esc is not None else None

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> NodeResult:
        """Read back what :meth:`as_dict` wrote (the manager's file)."""
        d = dict(d)
        workers = [_make(WorkerResult, w) for w in d.pop("workers", None) or []]
        esc = d.pop("esc", None)
        ssc = d.pop("ssc", None)
        out: NodeResult = _make(cls, d)
        out.workers = workers
        out.esc = _make(EscResult, esc) if esc else None
        out.ssc = _make(SscResult, ssc) if ssc else None
        return out

    @classmethod
    def died(cls, node: str, reason: str) -> NodeResult:
        """A node whose manager left no result."""
        return cls(node=node, result="abnormal", reason=reason)


def _make(kind: Any, d: dict[str, Any]) -> Any:
    names = {f.name for f in dataclasses.fields(kind)}
    return kind(**{k: v for k, v in d.items() if k in names})

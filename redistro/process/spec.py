"""What a manager needs to run a node: written by the session owner as JSON."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

# a worker that failed (an exception in its initialize or step) exits with
# this code, its reason in its message box, no traceback
EXIT_FAILED = 4


@dataclass
class WorkerSpec:
    """One worker process.

    role: registry key of the worker class (redistro.process.registry).
    stage: position in the cycle; workers of one stage run in parallel and a
        collecting point waits for all of them before the next stage starts.
        A negative stage takes the worker off the cycle: it runs when its
        data comes (``rate_hz`` 0: it waits on its file descriptors and the
        node's wake event, at most a node period at a time: a DDM), or on a
        timer of its own at ``rate_hz``; it still signs its heartbeat (with
        the newest manager cycle) and is watched like any.
    rate_hz: the own timer's rate of an off-cycle worker (0: event-driven).
    cpus: CPUs to pin this worker to (empty: the node's CPUs).
    priority: paper priority (higher runs first).
    heartbeat_limit_cycles: missed heartbeats that make this worker hung
        (0: the node's limit).
    """

    name: str
    role: str
    stage: int = 0
    cpus: list[int] = field(default_factory=list)
    priority: int = 16
    params: dict[str, Any] = field(default_factory=dict)
    rate_hz: float = 0.0
    heartbeat_limit_cycles: int = 0

    @property
    def on_cycle(self) -> bool:
        return self.stage >= 0


@dataclass
class NodeSpec:
    session_id: str
    node: str
    kind: str
    rate_hz: float
    heartbeat_limit_cycles: int
    workers: list[WorkerSpec]
    robots: list[str] = field(default_factory=list)
    cycles: int = 0  # run this many cycles, then end ok; 0 = until told to stop
    startup_timeout_s: float = 10.0
    shutdown_timeout_s: float = 3.0
    sched_policy: str = "auto"
    lock_memory: bool = False
    cpu_latency_us: int | None = None  # held by the manager (PM QoS); None: not asked
    manager_priority: int = 15
    cpus: list[int] = field(default_factory=list)
    owner_pid: int = 0
    result_path: str = ""
    messages_path: str = ""

    def stages(self) -> list[list[int]]:
        """Indices of the workers on the cycle, grouped by stage, in stage order."""
        order = sorted({w.stage for w in self.workers if w.on_cycle})
        return [[i for i, w in enumerate(self.workers) if w.stage == s] for s in order]

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=1)

    def save(self, path: Path) -> None:
        path.write_text(self.to_json())

    @classmethod
    def load(cls, path: Path | str) -> NodeSpec:
        data = json.loads(Path(path).read_text())
        data["workers"] = [WorkerSpec(**w) for w in data["workers"]]
        return cls(**data)

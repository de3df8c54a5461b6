"""What a manager needs to run a node: written by the session owner as JSON."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from redistro.config.hardware import RobotHardware
    from redistro.config.model import Config
    from redistro.config.task import Task

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
class NodeParams:
    """A node's place in its session, the same for every process of the node.

    robot: an ESC's robot; plant_session: the session whose plant an ESC
    drives ("": its own); link: what the node's DDM meets the other nodes on
    ("": the session id); run_dir: the session's run folder; positions_file:
    where an ESC keeps its robot's joint positions; calibrates: an ESC in a
    self-calibration; from_ssc: an ESC commanded by the SSC (a strategy
    session); segments: an ESC's own segments (calibration moves); settle_s:
    settling time before the end; task_name: the task's name.
    """

    robot: str = ""
    plant_session: str = ""
    link: str = ""
    run_dir: str = ""
    positions_file: str = ""
    calibrates: bool = False
    from_ssc: bool = False
    segments: list[dict[str, Any]] = field(default_factory=list)
    settle_s: float = 0.5
    task_name: str = ""


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
    clock: str = "realtime"  # session.clock: the ticks' source (process/ticks.py)
    shutdown_timeout_s: float = 3.0
    sched_policy: str = "auto"
    lock_memory: bool = False
    cpu_latency_us: int | None = None  # held by the manager (PM QoS); None: not asked
    manager_priority: int = 15
    cpus: list[int] = field(default_factory=list)
    owner_pid: int = 0
    result_path: str = ""
    messages_path: str = ""
    # the session's config and task, loaded and checked once by the session
    # owner (config.loader.resolved); every process of the node rebuilds them
    # from here and never reads the YAML (``cfg()``, ``task()``)
    config: dict[str, Any] = field(default_factory=dict)
    task_data: dict[str, Any] = field(default_factory=dict)
    # an ESC's robot's hardware (I/O wiring, sensors), read and checked once
    # by the session owner with the config, handed down the same way
    hardware_data: dict[str, Any] = field(default_factory=dict)
    node_params: NodeParams = field(default_factory=NodeParams)

    def cfg(self) -> Config:
        """The session's config."""
        from redistro.config.loader import from_resolved
        from redistro.config.model import Config

        return from_resolved(Config, self.config)

    def task(self) -> Task:
        """The session's task."""
        from redistro.config.loader import from_resolved
        from redistro.config.task import Task

        return from_resolved(Task, self.task_data)

    def hardware(self) -> RobotHardware:
        """The node's robot's hardware (an ESC's)."""
        from redistro.config.hardware import RobotHardware
        from redistro.config.loader import from_resolved

        if not self.hardware_data:
            raise ValueError(f"node {self.node}: its spec holds no hardware")
        return from_resolved(RobotHardware, self.hardware_data)

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
        data["node_params"] = NodeParams(**data.get("node_params", {}))
        return cls(**data)

    @property
    def plant_session(self) -> str:
        """The session whose plant the node drives: its own, or the one named
        for a node started alone beside a plant of another session."""
        return self.node_params.plant_session or self.session_id

    @property
    def link(self) -> str:
        """What the node's DDM meets the other nodes of its group on: the
        session id in a session; the ``link`` of nodes started alone."""
        return self.node_params.link or self.session_id

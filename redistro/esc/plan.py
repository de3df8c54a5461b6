"""The ESC node a task needs, as a NodeSpec: workers, stages, priorities, params."""

from __future__ import annotations

import math
from typing import Any

from redistro.config.hardware import RobotHardware
from redistro.config.model import Config
from redistro.config.task import Task
from redistro.process.spec import NodeSpec, WorkerSpec

# Within a cycle: acquisition publishes feedback, the calibration its joint
# reference, the pid its torques, then the sender checks and sends.
ESC_WORKERS = (("acquisition", 0), ("calibration", 1), ("pid", 2), ("sender", 3))
# ... and, given a run folder, the recorder logs the cycle last.
ESC_RECORDER = ("recorder", 4)
# the session log's recorders (lowest priority: a starved one drops cycles)
RECORDERS = ("recorder", "logger")
# In a strategy session the SSC computes the torques: the acquisition
# publishes feedback, the sender checks and sends the SSC's command, and the
# ddm (off the cycle, on its own timer) carries both between the nodes.
ESC_STRATEGY_WORKERS = (("acquisition", 0), ("sender", 1), ("ddm", -1))


def esc_segments(task: Task, robot: str, hw: RobotHardware) -> list[dict[str, Any]]:
    """The ESC-local segments of ``task`` for ``robot`` (calibration worker params)."""
    if task.kind == "strategy":
        return []
    if task.kind == "self_calibration":
        c = task.calibration
        r = math.radians(c.range_deg)
        final = c.final_q_rad.get(robot, list(hw.sensors.home_angle_rad))
        t1, t2, t3 = c.segment_s
        return [
            {"name": "clockwise", "kind": "sweep", "duration_s": t1, "delta_rad": -r},
            {"name": "counter_clockwise", "kind": "sweep", "duration_s": t2, "delta_rad": r},
            {"name": "final_positioning", "kind": "position", "duration_s": t3, "goal_rad": final},
        ]
    return [
        {"name": s.name, "kind": "position", "duration_s": s.duration_s, "goal_rad": s.q_rad[robot]}
        for s in task.segments
    ]


def recorder_heartbeat_limit(cfg: Config, rate_hz: float) -> int:
    """A recorder's heartbeat limit in its node's cycles: ``log.heartbeat_limit_cycles``,
    and never less than ``log.heartbeat_limit_s`` of them (at 1 kHz, 200 cycles
    would be 200 ms, a fifth of what the log ring holds)."""
    return max(cfg.log.heartbeat_limit_cycles, math.ceil(cfg.log.heartbeat_limit_s * rate_hz))


def worker_specs(
    cfg: Config,
    roles: tuple[tuple[str, int], ...],
    params: dict[str, Any],
    rate_hz: float = 0.0,
) -> list[WorkerSpec]:
    """One WorkerSpec per (role, stage), at the role's configured priority; an
    off-cycle worker (negative stage: the ddm) runs on data (ddm.rate_hz 0) or on its
    own timer at ddm.rate_hz;
    the recorders get the log's heartbeat limit."""
    prio = cfg.scheduling.priorities
    return [
        WorkerSpec(
            name=role,
            role=role,
            stage=stage,
            priority=prio.get(role, 16),
            params=params,
            rate_hz=cfg.ddm.rate_hz if stage < 0 else 0.0,
            heartbeat_limit_cycles=(
                recorder_heartbeat_limit(cfg, rate_hz) if role in RECORDERS else 0
            ),
        )
        for role, stage in roles
    ]


def task_seconds(task: Task) -> float:
    """How long the task's motion lasts [s] (for time budgets and progress)."""
    if task.kind == "self_calibration":
        return sum(task.calibration.segment_s) + task.calibration.settle_s
    return sum(s.duration_s for s in task.segments) + task.settle_s


def esc_spec(
    cfg: Config,
    task: Task,
    robot: str,
    hw: RobotHardware,
    session_id: str,
    *,
    config_path: str | None,
    overrides: list[str],
    positions_file: str,
    messages_path: str = "",
    link: str = "",
    plant_session: str = "",
    run_dir: str = "",
) -> NodeSpec:
    """link, plant_session: for a node started alone (``redistro node``): the
    id its DDM meets the other nodes on, and the session whose plant it drives
    (default: its own session for both)."""
    settle = task.calibration.settle_s if task.kind == "self_calibration" else task.settle_s
    params: dict[str, Any] = {
        "robot": robot,
        "config": config_path,
        "overrides": list(overrides),
        "positions_file": positions_file,
        "calibrates": task.kind == "self_calibration",
        "segments": esc_segments(task, robot, hw),
        "settle_s": settle,
        "link": link,
        "plant_session": plant_session,
        "run_dir": run_dir,
        "task_name": task.task,
    }
    strategy = task.kind == "strategy"
    if strategy:
        params["commands"] = "ssc"
    prio = cfg.scheduling.priorities
    roles = ESC_STRATEGY_WORKERS if strategy else ESC_WORKERS
    if run_dir and not strategy:
        roles = (*roles, ESC_RECORDER)  # a strategy session is logged by the SSC
    workers = worker_specs(cfg, roles, params, cfg.esc.rate_hz)
    return NodeSpec(
        session_id=session_id,
        node=f"esc.{robot}",
        kind="esc",
        rate_hz=cfg.esc.rate_hz,
        heartbeat_limit_cycles=cfg.esc.heartbeat_limit_cycles,
        workers=workers,
        robots=[robot],
        startup_timeout_s=cfg.session.startup_timeout_s,
        shutdown_timeout_s=cfg.session.shutdown_timeout_s,
        sched_policy=cfg.scheduling.policy,
        lock_memory=cfg.scheduling.lock_memory,
        cpu_latency_us=cfg.scheduling.cpu_latency_us,
        manager_priority=prio.get("manager", 20),
        cpus=list(cfg.esc.cpus),
        messages_path=messages_path,
    )

"""The ESC node a task needs, as a NodeSpec: workers, stages, priorities, params."""

from __future__ import annotations

import math
from typing import Any

from redistro.config.hardware import RobotHardware
from redistro.config.loader import resolved
from redistro.config.model import Config, controller_view
from redistro.config.task import Task
from redistro.process.plan import worker_specs
from redistro.process.spec import NodeParams, NodeSpec

# Within a cycle: acquisition publishes feedback, the calibration its joint
# reference, the pid its torques, then the sender checks and sends.
ESC_WORKERS = (("acquisition", 0), ("calibration", 1), ("pid", 2), ("sender", 3))
# ... and, given a run folder, the recorder logs the cycles, off the cycle
# (it drains the log ring on its own timer, log.drain_hz).
ESC_RECORDER = ("recorder", -1)
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
    strategy = task.kind == "strategy"
    node_params = NodeParams(
        robot=robot,
        plant_session=plant_session,
        link=link,
        run_dir=run_dir,
        positions_file=positions_file,
        calibrates=task.kind == "self_calibration",
        from_ssc=strategy,
        segments=esc_segments(task, robot, hw),
        settle_s=settle,
        task_name=task.task,
    )
    prio = cfg.scheduling.priorities
    roles = ESC_STRATEGY_WORKERS if strategy else ESC_WORKERS
    if run_dir and not strategy:
        roles = (*roles, ESC_RECORDER)  # a strategy session is logged by the SSC
    workers = worker_specs(cfg, roles, {}, cfg.esc.rate_hz)
    return NodeSpec(
        session_id=session_id,
        node=f"esc.{robot}",
        kind="esc",
        rate_hz=cfg.esc.rate_hz,
        heartbeat_limit_cycles=cfg.esc.heartbeat_limit_cycles,
        workers=workers,
        robots=[robot],
        startup_timeout_s=cfg.session.startup_timeout_s,
        clock=cfg.session.clock,
        shutdown_timeout_s=cfg.session.shutdown_timeout_s,
        sched_policy=cfg.scheduling.policy,
        lock_memory=cfg.scheduling.lock_memory,
        cpu_latency_us=cfg.scheduling.cpu_latency_us,
        manager_priority=prio.get("manager", 20),
        cpus=list(cfg.esc.cpus),
        messages_path=messages_path,
        config=resolved(controller_view(cfg)),
        task_data=resolved(task),
        hardware_data=resolved(hw),
        node_params=node_params,
    )

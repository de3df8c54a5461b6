"""Can each robot reach the task's Cartesian goals? Checked before anything starts.

A goal is reachable when a damped least-squares inverse kinematics on the
arm's own model (Pinocchio; tool and base as in the plant), inside the joint
limits less the guard's margin (redistro/config/limits.py), brings the TCP
within 2 mm and 0.02 rad of it from one of a few starting postures. A goal
none of them reaches is refused with the segment named.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from redistro.config.model import Config
from redistro.config.task import Task

POS_TOL_M = 0.002
ROT_TOL_RAD = 0.02
ITERATIONS = 300


def arm_tool(cfg: Config, robot: str) -> Any:
    """The robot's tool as the URDF draws it: the work-cell's peg, or None."""
    from redistro.robotmodel import Peg

    peg = cfg.workcell.peg
    return Peg(peg.side_m, peg.length_m, peg.mass_kg) if cfg.robots[robot].peg else None


def arm_model(cfg: Config, robot: str, models: dict[str, Any]) -> Any:
    """The robot's ArmModel (its tool, at its base), made once into ``models``."""
    from redistro.control.dynamics import ArmModel

    model = models.get(robot)
    if model is None:
        model = models[robot] = ArmModel(arm_tool(cfg, robot), cfg.robots[robot].base_xyz_m)
    return model


def _ik_error(
    model: Any, q: np.ndarray, p_goal: np.ndarray, R_goal: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    from redistro.control.cartesian import matrix_to_rotvec

    k = model.kinematics(q)
    e_rot = k.R @ matrix_to_rotvec(k.R.T @ R_goal)
    return np.concatenate([p_goal - k.p, e_rot]), k.J


def reachable(
    model: Any,
    pose: np.ndarray,
    starts: list[np.ndarray],
    lo: np.ndarray | None = None,
    hi: np.ndarray | None = None,
) -> tuple[bool, float]:
    """(reached, the best position error [m]) for a TCP pose (position + rotation
    vector), every joint kept in [lo, hi] (default: the model's limits)."""
    ok, err, _ = solve(model, pose, starts, lo, hi)
    return ok, err


def solve(
    model: Any,
    pose: np.ndarray,
    starts: list[np.ndarray],
    lo: np.ndarray | None = None,
    hi: np.ndarray | None = None,
) -> tuple[bool, float, np.ndarray | None]:
    """:func:`reachable`, and the posture that reaches the pose (None: none)."""
    from redistro.control.cartesian import rotvec_to_matrix

    p_goal = np.asarray(pose[:3], dtype=np.float64)
    R_goal = rotvec_to_matrix(np.asarray(pose[3:], dtype=np.float64))
    if lo is None:
        lo = np.asarray(model.model.lowerPositionLimit, dtype=np.float64)
    if hi is None:
        hi = np.asarray(model.model.upperPositionLimit, dtype=np.float64)
    best = np.inf
    for q0 in starts:
        q = np.clip(np.asarray(q0, dtype=np.float64), lo, hi)
        for _ in range(ITERATIONS):
            e, J = _ik_error(model, q, p_goal, R_goal)
            pos, rot = float(np.linalg.norm(e[:3])), float(np.linalg.norm(e[3:]))
            best = min(best, pos)
            if pos < POS_TOL_M and rot < ROT_TOL_RAD:
                return True, pos, q
            step = J.T @ np.linalg.solve(J @ J.T + 1e-2 * np.eye(6), e)
            n = float(np.linalg.norm(step))
            if n > 0.3:
                step *= 0.3 / n
            q = np.clip(q + step, lo, hi)
    return False, best, None


def unreachable_goals(cfg: Config, task: Task) -> list[str]:
    """One line per Cartesian goal no robot posture reaches (empty: all fine)."""
    if task.kind != "strategy":
        return []
    from redistro.config.limits import joint_limits
    from redistro.ssc.plan import segment_plans

    limits = joint_limits(cfg)
    models: dict[str, Any] = {}
    out: list[str] = []
    for plan in segment_plans(task, cfg):
        for mv in plan.moves:
            if mv.scheme not in ("position", "force"):
                continue
            rc = cfg.robots[mv.robot]
            model = arm_model(cfg, mv.robot, models)
            starts = [
                np.asarray(rc.initial_q_rad, dtype=np.float64),
                np.array([0.0, 0.6, 0.0, -1.4, 0.0, 1.0, 0.0]),
                np.array([0.0, 0.3, 0.0, -1.9, 0.0, 0.9, 0.0]),
            ]
            ok, err = reachable(model, mv.pose, starts, limits.inner_lower, limits.inner_upper)
            if not ok:
                xyz = ", ".join(f"{v:.3f}" for v in mv.pose[:3])
                out.append(
                    f"{task.source}: {mv.where}.goal: {mv.robot} cannot reach the pose "
                    f"({xyz}) m inside its joint limits: {err * 1e3:.0f} mm short at best"
                )
    return out


def goal_postures(
    cfg: Config, task: Task, start_q: dict[str, list[float]] | None = None
) -> dict[tuple[int, str], np.ndarray]:
    """Per Cartesian move (by segment index and robot), the posture its goal
    puts the arm in: the inverse kinematics from the robot's posture before
    it (its last joint goal or Cartesian posture, else its recorded
    position), for the speed check of the joint move after it."""
    if task.kind != "strategy":
        return {}
    from redistro.config.limits import joint_limits
    from redistro.ssc.plan import segment_plans

    limits = joint_limits(cfg)
    models: dict[str, Any] = {}
    before: dict[str, np.ndarray] = {
        r: np.asarray(q, dtype=np.float64) for r, q in (start_q or {}).items()
    }
    out: dict[tuple[int, str], np.ndarray] = {}
    for i, plan in enumerate(segment_plans(task, cfg)):
        for mv in plan.moves:
            r = mv.robot
            if mv.scheme == "joint":
                before[r] = mv.q_goal.copy()
                continue
            model = arm_model(cfg, r, models)
            first = before.get(r, np.asarray(cfg.robots[r].initial_q_rad, dtype=np.float64))
            ok, _, q = solve(model, mv.pose, [first], limits.inner_lower, limits.inner_upper)
            if ok and q is not None:
                out[i, r] = before[r] = q
    return out

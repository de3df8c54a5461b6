"""Do the arms keep apart? Checked before anything starts.

Every segment's planned motion is sampled: a joint move along its straight
line in joint space, a Cartesian move (position, force) along the TCP's
straight line and rotation, each sample solved by inverse kinematics from
the one before (:mod:`redistro.ssc.reach`), while every other robot holds
where it is. At each sample the arms' collision geometry (each link's mesh
from the URDF, through Pinocchio's geometry model, as its convex hull:
coal's GJK) must keep every link of one arm at least ``MIN_CLEARANCE_M``
from every link of another. The first sample closer than that is refused
with the segment, the time and the two links named.

Samples: one per ``STEP_RAD`` of the largest joint's travel (a Cartesian
move: per ``STEP_M`` of the TCP's path), at least one per move and its end;
a sample's time is where the move's quintic profile reaches it.
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from redistro.config.model import Config
from redistro.config.task import Task

MIN_CLEARANCE_M = 0.03
STEP_RAD = 0.0125  # joint-space sampling (a point 0.8 m out moves 1 cm)
STEP_M = 0.01  # Cartesian sampling (the TCP's path)


@dataclass
class Closest:
    """The closest two links of two arms at one configuration."""

    distance_m: float
    links: tuple[str, str]  # "r1 lbr_iiwa_link_5", "r2 lbr_iiwa_link_6"


class GroupGeometry:
    """The robots' collision geometry in one Pinocchio model (each arm at
    its base), with every pair of links of two different arms to measure."""

    def __init__(self, cfg: Config, robots: list[str]) -> None:
        import coal
        import pinocchio as pin

        from redistro.robotmodel import write_arm_urdf
        from redistro.ssc.reach import arm_tool

        self._pin = pin
        model, geom = pin.Model(), pin.GeometryModel()
        meshes = coal.CachedMeshLoader()  # (every arm's links: the same meshes, loaded once)
        self.offsets: dict[str, int] = {}  # each robot's first index in q
        with tempfile.TemporaryDirectory(prefix="redistro-clearance-") as tmp:
            for r in robots:
                rc = cfg.robots[r]
                path = str(write_arm_urdf(Path(tmp), r, arm_tool(cfg, r)))
                m = pin.buildModelFromUrdf(path)
                g = pin.buildGeomFromUrdf(m, path, pin.GeometryType.COLLISION, mesh_loader=meshes)
                for i in range(1, m.njoints):  # one model holds every arm: names apart
                    m.names[i] = f"{r} {m.names[i]}"
                for i in range(m.nframes):
                    f = m.frames[i]
                    f.name = f"{r} {f.name}"
                    m.frames[i] = f
                for go in g.geometryObjects:
                    go.name = f"{r} {go.name.rsplit('_', 1)[0]}"
                base = pin.SE3(np.eye(3), np.asarray(rc.base_xyz_m, dtype=np.float64))
                self.offsets[r] = model.nq
                model, geom = pin.appendModel(model, m, geom, g, 0, base)
        for go in geom.geometryObjects:  # GJK on the meshes' hulls, not their trees
            if hasattr(go.geometry, "buildConvexRepresentation"):
                go.geometry.buildConvexRepresentation(False)
                go.geometry = go.geometry.convex
        owner = [go.name.split(" ", 1)[0] for go in geom.geometryObjects]
        for i in range(len(owner)):
            for j in range(i + 1, len(owner)):
                if owner[i] != owner[j]:
                    geom.addCollisionPair(pin.CollisionPair(i, j))
        self.model, self.geom = model, geom
        self.data = model.createData()
        self.gdata = pin.GeometryData(geom)
        self.q = pin.neutral(model)

    def closest(self, qs: dict[str, np.ndarray]) -> Closest:
        """The two closest links of different arms at the robots' postures."""
        pin = self._pin
        for r, q in qs.items():
            k = self.offsets[r]
            self.q[k : k + 7] = q
        pin.computeDistances(self.model, self.data, self.geom, self.gdata, self.q)
        best, at = math.inf, 0
        for k, res in enumerate(self.gdata.distanceResults):
            if res.min_distance < best:
                best, at = res.min_distance, k
        pair = self.geom.collisionPairs[at]
        objs = self.geom.geometryObjects
        return Closest(float(best), (objs[pair.first].name, objs[pair.second].name))


def _path(model: Any, q0: np.ndarray, pose: np.ndarray, lo: Any, hi: Any) -> list[np.ndarray]:
    """Postures along the TCP's straight line from its pose at ``q0`` to
    ``pose`` (position + rotation vector), each solved from the one before
    (a sample no posture reaches ends the path: the reach check names it)."""
    from redistro.control.cartesian import matrix_to_rotvec, rotvec_to_matrix
    from redistro.ssc.reach import solve

    k = model.kinematics(q0)
    p0, R0 = k.p, k.R
    p1, R1 = np.asarray(pose[:3], dtype=np.float64), rotvec_to_matrix(np.asarray(pose[3:]))
    w = matrix_to_rotvec(R0.T @ R1)  # the rotation to make, in the tool's frame
    n = max(1, math.ceil(float(np.linalg.norm(p1 - p0)) / STEP_M))
    out, q = [], q0
    for i in range(1, n + 1):
        f = i / n
        rot = matrix_to_rotvec(R0 @ rotvec_to_matrix(f * w))
        target = np.concatenate([p0 + f * (p1 - p0), rot])
        ok, _, qf = solve(model, target, [q], lo, hi)
        if not ok or qf is None:
            break
        out.append(qf)
        q = qf
    return out


def _time_at(fraction: float, move_s: float) -> float:
    """When the move's quintic profile (control/trajectory.py) reaches ``fraction``."""
    from redistro.control.trajectory import quintic

    zero, one = np.zeros(1), np.ones(1)
    lo, hi = 0.0, 1.0
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        if quintic(zero, one, 1.0, mid)[0][0] < fraction:
            lo = mid
        else:
            hi = mid
    return hi * move_s


def _joint_path(q0: np.ndarray, q1: np.ndarray) -> list[np.ndarray]:
    n = max(1, math.ceil(float(np.max(np.abs(q1 - q0))) / STEP_RAD))
    return [q0 + (i / n) * (q1 - q0) for i in range(1, n + 1)]


def clearance_problems(cfg: Config, task: Task, start_q: dict[str, list[float]]) -> list[str]:
    """One line for the first sample of the task's motion where two arms
    come closer than MIN_CLEARANCE_M (empty: they keep apart)."""
    if task.kind != "strategy" or len(task.robots) < 2:
        return []
    from redistro.config.limits import joint_limits
    from redistro.ssc.plan import segment_plans
    from redistro.ssc.reach import arm_model

    limits = joint_limits(cfg)
    group = GroupGeometry(cfg, list(task.robots))
    q: dict[str, np.ndarray] = {
        r: np.asarray(start_q.get(r, cfg.robots[r].initial_q_rad), dtype=np.float64)
        for r in task.robots
    }
    models: dict[str, Any] = {}
    for i, (seg, plan) in enumerate(zip(task.segments, segment_plans(task, cfg), strict=True)):
        r = plan.robot
        if plan.scheme == "joint":
            path = _joint_path(q[r], np.asarray(plan.q_goal, dtype=np.float64))
        else:
            model = arm_model(cfg, r, models)
            path = _path(model, q[r], plan.pose, limits.inner_lower, limits.inner_upper)
        move_s = plan.move_s
        for k, qk in enumerate(path):
            c = group.closest({**q, r: qk})
            if c.distance_m < MIN_CLEARANCE_M:
                t = _time_at((k + 1) / len(path), move_s)
                gap = (
                    f"come {c.distance_m * 100:.1f} cm apart"
                    if c.distance_m >= 0
                    else f"overlap by {-c.distance_m * 100:.1f} cm"
                )
                return [
                    f"{task.source}: segments[{i}] ({seg.name}) at t={t:.2f} s: {c.links[0]} "
                    f"and {c.links[1]} {gap} (at least {MIN_CLEARANCE_M * 100:.0f} cm apart)"
                ]
        if path:
            q[r] = path[-1]
    return []

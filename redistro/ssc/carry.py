"""Two hands carrying one object (a closed chain), in the SSC.

The symmetric formulation, on the arms' own impedance laws: the object's
motion (the segment's :class:`~redistro.config.task.Carry`) gives each hand's
reference, from where the hands were, measured, as the first carry began
(the grasps' real offsets included; later carries go on from its goals);
both hands squeeze the object along the
line from one to the other, equal and opposite (an internal force: the null
space of the grasp matrix, it moves nothing), and each carries half its
weight (the load shared equally: the hands hold it symmetrically).

Per cycle and hand, before its law: the reference moved onto the object's
arc (the law's own reference goes straight, a chord), in along the line by
the squeeze's spring compression, up by the weight's share; after it: the
squeeze measured at the wrist (the law's applied wrench, on the line)
corrects the compression (an integral, ``KI_SQUEEZE``), and the hand's
height error the weight's share (``KI_UP``). About 5 us per hand and cycle.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from redistro.control.cartesian import matrix_to_rotvec
from redistro.ssc.plan import MovePlan, SegmentPlan, carried

GRAVITY = 9.81
KI_SQUEEZE = 0.015  # [m/(N s)]: with the laws' 300 N/m, the squeeze settles in about 0.2 s
KI_UP = 2.0  # [1/s]: the weight's share trimmed by the hand's height error (about 0.5 s)
MAX_IN_M = 0.1  # the most a hand's reference goes in along the line


class CarryRun:
    """One carry segment's two hands: their references, their squeeze."""

    def __init__(
        self,
        plan: SegmentPlan,
        kins: list[Any],
        k_line: float,
        k_up: float,
        before: CarryRun | None = None,
    ) -> None:
        """``kins``: the hands' kinematics now; ``before``: the carry the
        segment before ran with the same hands (it goes on from that one's
        goals, not from the measured hands: a hand's sag under the load would
        add up from segment to segment)."""
        carry = plan.carry
        assert carry is not None and len(plan.moves) == 2 and len(kins) == 2
        self.robots = [mv.robot for mv in plan.moves]
        self.carry = carry
        self.move_s = max(plan.move_s, 1e-6)
        if before is not None and before.robots == self.robots:
            self.p0 = [p.copy() for p in before.goal_p]
            R0 = [R.copy() for R in before.goal_R]
        else:
            self.p0 = [np.asarray(k.p, dtype=np.float64).copy() for k in kins]
            R0 = [np.asarray(k.R, dtype=np.float64).copy() for k in kins]
        goals_p, goals_R = carried(carry, self.p0, R0)
        self.goal_p: list[np.ndarray[Any, Any]] = goals_p
        self.goal_R: list[np.ndarray[Any, Any]] = goals_R
        # the moves toward these goals (the planned ones assumed the grasps as drawn)
        self.moves = [
            dataclasses.replace(mv, pose=np.concatenate([p, matrix_to_rotvec(R)]))
            for mv, p, R in zip(plan.moves, goals_p, goals_R, strict=True)
        ]
        line = self.p0[1] - self.p0[0]
        line[2] = 0.0  # (the squeeze along the horizontal line between the hands)
        n = float(np.linalg.norm(line))
        u = line / n if n > 1e-6 else np.array([1.0, 0.0, 0.0])
        self.u0 = [u, -u]  # each hand's inward direction, at the start
        self.squeeze = carry.squeeze_n
        # the spring's compression for the squeeze (fed forward; the loop trims it)
        self.inward = [carry.squeeze_n / k_line] * 2
        if before is not None and before.robots == self.robots:
            self.inward = list(before.inward)
        # half the weight, per hand (fed forward; its height error trims it:
        # the law's stiffness under a load is not quite its k)
        self.up = [plan.carry_mass_kg * GRAVITY / 2 / k_up] * 2
        if before is not None and before.robots == self.robots:
            self.up = list(before.up)
        self.height = [0.0, 0.0]  # each hand's height on the object's path, this cycle
        self.measured = [0.0, 0.0]
        # the same in plain floats, for the cycle
        self.turn = math.radians(carry.turn_deg)
        mid = (self.p0[0] + self.p0[1]) / 2
        self.mid = tuple(float(v) for v in mid)
        self.d = tuple(float(v) for v in carry.move_xyz_m)
        self.r = [tuple(float(v) for v in p - mid) for p in self.p0]
        self.p0t = [tuple(float(v) for v in p) for p in self.p0]
        self.gt = [tuple(float(v) for v in g) for g in self.goal_p]
        self.u0xy = [(float(v[0]), float(v[1])) for v in self.u0]
        self.uxy = list(self.u0xy)

    def index(self, robot: str) -> int:
        return self.robots.index(robot)

    def before(self, i: int, law: Any, seg_t: float, wrench_goal: Any) -> None:
        """Hand i's reference for this cycle (the law's ``ref`` rewritten in
        place; plain floats: about 5 us)."""
        s = min(max(seg_t / self.move_s, 0.0), 1.0)
        b = s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)  # the law's own blend
        a = self.turn * b
        c, sn = math.cos(a), math.sin(a)
        ux0, uy0 = self.u0xy[i]
        ux, uy = c * ux0 - sn * uy0, sn * ux0 + c * uy0
        self.uxy[i] = (ux, uy)
        mx, my, mz = self.mid
        dx, dy, dz = self.d
        rx, ry, rz = self.r[i]
        px, py, pz = self.p0t[i]
        gx, gy, gz = self.gt[i]
        k = self.inward[i]
        # the arc's point less the chord's (the law's own reference), the squeeze's
        # compression in along the line, the weight's share up
        sx = mx + dx * b + c * rx - sn * ry - (px + b * (gx - px)) + k * ux
        sy = my + dy * b + sn * rx + c * ry - (py + b * (gy - py)) + k * uy
        hz = mz + dz * b + rz
        self.height[i] = hz
        sz = hz - (pz + b * (gz - pz)) + self.up[i]
        ref = law.ref
        ref["start_p"] = (px + sx, py + sy, pz + sz)
        ref["goal_p"] = (gx + sx, gy + sy, gz + sz)
        f = self.squeeze
        wrench_goal[:3] = (f * ux, f * uy, 0.0)  # (in the plan: the log judges the squeeze by it)

    def after(self, i: int, law: Any, dt: float) -> None:
        """Hand i's squeeze, measured at its wrist, trims its compression."""
        w = law.applied
        ux, uy = self.uxy[i]
        f = float(w[0]) * ux + float(w[1]) * uy
        self.measured[i] = f
        x = self.inward[i] + KI_SQUEEZE * (self.squeeze - f) * dt
        self.inward[i] = min(max(x, 0.0), MAX_IN_M)
        z = self.up[i] + KI_UP * (self.height[i] - float(law.tcp_p[2])) * dt
        self.up[i] = min(max(z, -MAX_IN_M), MAX_IN_M)


def carry_moves(moves: list[MovePlan | None], run: CarryRun) -> list[MovePlan | None]:
    """The segment's moves with the carrying hands' goals from ``run``."""
    by = {mv.robot: mv for mv in run.moves}
    return [by.get(mv.robot, mv) if mv is not None else None for mv in moves]

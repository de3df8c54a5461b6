"""The SSC worker (paper priority 18): task planning, trajectories, control laws, coordination.

Each cycle it reads every robot's feedback (written by the ddm), advances
the task on the boards' sample clock (the feedback's ``step``: a simulation
running behind real time does not leave the references ahead), and writes
one command per robot: joint torques from the segment's control law for the
segment's robot, a joint PID hold for the others, every joint on, and the
session status. It computes nothing before every robot has reported (the
datum: feedback from each ESC). After the last segment and ``settle_s`` the
commands say the session is finished and the plan says done.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from redistro.config import load_config
from redistro.config.task import load_task
from redistro.control.cartesian import (
    ForceParams,
    HybridState,
    ImpedanceGains,
    TaskFrameCommand,
    hybrid_update,
    matrix_to_rotvec,
    pose_error,
    rotvec_to_matrix,
    slerp,
    start_state,
)
from redistro.control.dynamics import ArmModel
from redistro.control.pid import PidGains, PidState, pid_update
from redistro.control.trajectory import quintic
from redistro.localdata.block import Record
from redistro.localdata.layout import COMMAND, FEEDBACK, PLAN, SessionStatus
from redistro.process.worker import Worker
from redistro.robotmodel import Peg
from redistro.ssc.plan import SCHEMES, SegmentPlan, segment_plans

DOF = 7
ON = np.ones(DOF, dtype=bool)
AFTER = 255  # plan.segment once every segment is over


@dataclass
class RobotState:
    name: str
    model: ArmModel
    hold_q: np.ndarray[Any, Any]
    pid: PidState = field(default_factory=PidState)
    hybrid: HybridState | None = None
    cmd: TaskFrameCommand | None = None
    start_q: np.ndarray[Any, Any] = field(default_factory=lambda: np.zeros(DOF))
    start_p: np.ndarray[Any, Any] = field(default_factory=lambda: np.zeros(3))
    start_R: np.ndarray[Any, Any] = field(default_factory=lambda: np.eye(3))
    short_move: bool = False  # the goal is where the segment starts (within 2 mm)
    goal_p: np.ndarray[Any, Any] = field(default_factory=lambda: np.zeros(3))
    goal_rot: np.ndarray[Any, Any] = field(default_factory=lambda: np.zeros(3))


def f64(values: list[float]) -> np.ndarray[Any, Any]:
    return np.asarray(values, dtype=np.float64)


class SscWorker(Worker):
    def initialize(self) -> None:
        cfg = load_config(self.params.get("config"), list(self.params.get("overrides", [])))
        self.cfg = cfg
        task = load_task(self.params["task"], cfg)
        self.settle_s = task.settle_s
        self.plans: list[SegmentPlan] = segment_plans(task, cfg)
        self.robots = list(self.spec.robots)
        self.physics_hz = cfg.plant.physics_hz
        imp = cfg.ssc.impedance
        self.gains = ImpedanceGains(
            k=f64(imp.k),
            d=f64(imp.d),
            ki=f64(imp.ki),
            i_max=f64(imp.i_max),
            k_null=f64(imp.k_null),
            d_joint=f64(imp.d_joint),
            zeta=imp.zeta,
        )
        fc = cfg.ssc.force
        self.force = ForceParams(
            k_adm=fc.k_adm,
            k_adm_rot=fc.k_adm_rot,
            v_max=fc.v_max,
            w_max=fc.w_max,
            a_max=fc.a_max,
            alpha_max=fc.alpha_max,
            contact_n=fc.contact_n,
            ramp_s=fc.ramp_s,
        )
        p = cfg.ssc.pid
        self.pid = PidGains(f64(p.kp), f64(p.ki), f64(p.kd), f64(p.i_max_nm))
        peg = cfg.plant.peg
        self.states: list[RobotState] = []
        for r in self.robots:
            rc = cfg.robots[r]
            model = ArmModel(
                Peg(peg.side_m, peg.length_m, peg.mass_kg) if rc.peg else None, rc.base_xyz_m
            )
            self.states.append(RobotState(r, model, np.zeros(DOF)))
        ld = self.ld
        n = len(self.robots)
        self.fb_blocks = [ld.block("feedback", i) for i in range(n)]
        self.cmd_blocks = [ld.writer("command", i, role="worker") for i in range(n)]
        self.plan_blocks = [ld.writer("plan", i, role="worker") for i in range(n)]
        self.fbs = [Record(FEEDBACK) for _ in range(n)]
        self.cmds = [Record(COMMAND) for _ in range(n)]
        self.plan_recs = [Record(PLAN) for _ in range(n)]
        self.started = False
        self.t0_step = 0
        self.last_t = 0.0
        self.k = -1  # running segment (0-based); len(plans): settling; then done
        self.seg_start_t = 0.0
        self.cond_since: float | None = None
        self.done = False
        self.produced = 0

    # -- the cycle --

    def step(self, cycle: int) -> None:
        for block, rec in zip(self.fb_blocks, self.fbs, strict=True):
            block.read_into(rec.bytes)
        if any(int(rec["seq_src"]) == 0 for rec in self.fbs):
            return  # the datum: not every robot has reported yet
        step_now = max(int(rec["step"]) for rec in self.fbs)
        if not self.started:
            self.started = True
            self.t0_step = step_now
            for st, rec in zip(self.states, self.fbs, strict=True):
                st.hold_q = rec.array["q_rad"].copy()
            self.post(f"every robot reported; task starts ({len(self.plans)} segments)")
            self._begin(0, 0.0)
        t = (step_now - self.t0_step) / self.physics_hz
        dt = max(0.0, t - self.last_t)
        self.last_t = t
        self._advance(t)
        seg_t = t - self.seg_start_t
        plan = self.plans[self.k] if self.k < len(self.plans) else None
        status = SessionStatus.FINISHED if self.done else SessionStatus.IN_PROGRESS
        now = time.monotonic_ns()
        self.produced += 1
        for i, (st, rec) in enumerate(zip(self.states, self.fbs, strict=True)):
            fb = rec.array
            q = fb["q_rad"].astype(np.float64)
            qd = fb["qd_rad_s"].astype(np.float64)
            moving = plan is not None and plan.robot == st.name and not self.done
            pl = self.plan_recs[i].array
            pl["stamp_ns"] = now
            pl["cycle"] = cycle
            pl["t_s"] = t
            pl["segment"] = AFTER if self.k >= len(self.plans) else self.k + 1
            pl["segment_t_s"] = seg_t
            pl["moving"] = 1 if moving else 0
            pl["done"] = 1 if self.done else 0
            if moving:
                assert plan is not None
                tau, q_ref = self._law(st, plan, q, qd, fb["wrench"], seg_t, dt, pl)
            else:
                tau, q_ref = self._hold(st, q, qd, dt, pl)
            c = self.cmds[i].array
            c["stamp_ns"] = time.monotonic_ns()
            c["seq_src"] = self.produced
            c["tau_nm"] = tau
            c["q_cmd_rad"] = q_ref
            c["joint_on"] = ON
            c["session_status"] = status
            self.plan_blocks[i].publish(self.plan_recs[i].bytes)
            self.cmd_blocks[i].publish(self.cmds[i].bytes)

    # -- task planning --

    def _begin(self, k: int, t: float) -> None:
        """Start segment k at task time t (k == len(plans): settle, then done)."""
        self.k = k
        self.seg_start_t = t
        self.cond_since = None
        if k >= len(self.plans):
            for st, rec in zip(self.states, self.fbs, strict=True):
                st.hold_q = rec.array["q_rad"].copy()
                st.pid.reset()
            self.post(f"every segment done at t={t:.2f} s; settling {self.settle_s} s")
            return
        plan = self.plans[k]
        prev = self.plans[k - 1].robot if k > 0 else None
        for st, rec in zip(self.states, self.fbs, strict=True):
            q = rec.array["q_rad"].astype(np.float64)
            if st.name != plan.robot:
                if prev == st.name or k == 0:
                    st.hold_q = q.copy()  # it was moving: it holds where it is now
                    st.pid.reset()
                st.hybrid = None
                continue
            st.pid.reset()
            st.start_q = q.copy()
            kin = st.model.kinematics(q)
            st.start_p, st.start_R = kin.p.copy(), kin.R.copy()
            if plan.scheme in ("position", "force"):
                st.cmd = TaskFrameCommand(
                    plan.pose,
                    plan.force,
                    plan.selection if plan.scheme == "force" else np.zeros(6),
                    "tool" if plan.frame == "tool" else "world",
                )
                carried = st.hybrid.integral.copy() if st.hybrid is not None else None
                st.hybrid = start_state(st.cmd, kin)
                if carried is not None:
                    # the same robot stays under Cartesian control: keep what
                    # the integral learned (a fresh one would let the pose sag
                    # back to its uncompensated error at every segment start)
                    st.hybrid.integral = carried
                st.short_move = bool(
                    np.linalg.norm(st.cmd.goal_p - kin.p) < 0.002
                    and np.linalg.norm(matrix_to_rotvec(st.cmd.goal_R @ kin.R.T)) < 0.01
                )
            else:
                st.hybrid = None
                goal = st.model.kinematics(plan.q_goal)
                st.goal_p, st.goal_rot = goal.p.copy(), matrix_to_rotvec(goal.R)
        self.post(f"segment {k + 1}/{len(self.plans)} {plan.name}: {plan.robot} {plan.scheme}")

    def _advance(self, t: float) -> None:
        if self.done:
            return
        seg_t = t - self.seg_start_t
        if self.k >= len(self.plans):
            if seg_t >= self.settle_s:
                self.done = True
                self.post(f"task finished at t={t:.2f} s")
            return
        plan = self.plans[self.k]
        if seg_t >= plan.duration_s or self._ended_early(plan, t):
            self._begin(self.k + 1, t)

    def _ended_early(self, plan: SegmentPlan, t: float) -> bool:
        if plan.hold_s <= 0 or t - self.seg_start_t < plan.move_s:
            return False
        i = self.robots.index(plan.robot)
        pl = self.plan_recs[i].array
        ok = True
        if plan.pose_within_m > 0 or plan.rot_within_rad > 0:
            e = pose_error(
                pl["tcp_xyz_m"],
                rotvec_to_matrix(pl["tcp_rot_xyz"]),
                plan.pose[:3],
                rotvec_to_matrix(plan.pose[3:]),
            )
            if plan.pose_within_m > 0 and float(np.linalg.norm(e[:3])) > plan.pose_within_m:
                ok = False
            if plan.rot_within_rad > 0 and float(np.linalg.norm(e[3:])) > plan.rot_within_rad:
                ok = False
        if plan.force_within_n > 0:
            err = (plan.force - pl["wrench_task"]) * plan.selection
            if not pl["contact"] or float(np.linalg.norm(err[:3])) > plan.force_within_n:
                ok = False
        if not ok:
            self.cond_since = None
            return False
        if self.cond_since is None:
            self.cond_since = t
        return t - self.cond_since >= plan.hold_s

    # -- control laws --

    def _hold(
        self, st: RobotState, q: np.ndarray[Any, Any], qd: np.ndarray[Any, Any], dt: float, pl: Any
    ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
        g = st.model.gravity(q)
        zero = np.zeros(DOF)
        tau = pid_update(self.pid, st.pid, q, qd, st.hold_q, zero, g, ON, dt)
        self._pose_into(st, q, pl)
        pl["scheme"] = SCHEMES["hold"]
        pl["q_goal_rad"] = st.hold_q
        pl["contact"] = 0
        return tau, st.hold_q

    def _law(
        self,
        st: RobotState,
        plan: SegmentPlan,
        q: np.ndarray[Any, Any],
        qd: np.ndarray[Any, Any],
        wrench: np.ndarray[Any, Any],
        seg_t: float,
        dt: float,
        pl: Any,
    ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
        pl["scheme"] = SCHEMES[plan.scheme]
        g = st.model.gravity(q)
        if plan.scheme == "joint":
            q_ref, qd_ref, _ = quintic(st.start_q, plan.q_goal, plan.move_s, seg_t)
            tau = pid_update(self.pid, st.pid, q, qd, q_ref, qd_ref, g, ON, dt)
            self._pose_into(st, q, pl)
            pl["goal_xyz_m"] = st.goal_p
            pl["goal_rot_xyz"] = st.goal_rot
            pl["q_goal_rad"] = plan.q_goal
            pl["contact"] = 0
            return tau, q_ref
        assert st.cmd is not None and st.hybrid is not None
        kin = st.model.kinematics(q)
        p_ref, v_ref, a_lin = quintic(st.start_p, st.cmd.goal_p, plan.move_s, seg_t)
        s = min(max(seg_t / plan.move_s, 0.0), 1.0)
        blend = 10 * s**3 - 15 * s**4 + 6 * s**5
        R_ref = slerp(st.start_R, st.cmd.goal_R, blend)
        # angular reference speed: the rotation's axis times the blend's rate
        axis = matrix_to_rotvec(st.cmd.goal_R @ st.start_R.T)
        sd = (30 * s**2 - 60 * s**3 + 30 * s**4) / plan.move_s if s < 1.0 else 0.0
        sdd = (60 * s - 180 * s**2 + 120 * s**3) / plan.move_s**2 if s < 1.0 else 0.0
        v6 = np.concatenate([v_ref, axis * sd])
        a6 = np.concatenate([a_lin, axis * sdd])
        inertia = st.model.task_inertia(q, kin.J)
        tau, applied = hybrid_update(
            self.gains,
            self.force,
            st.hybrid,
            st.cmd,
            kin,
            q,
            qd,
            g,
            p_ref,
            R_ref,
            v6,
            np.asarray(wrench, dtype=np.float64),
            st.start_q,
            seg_t,
            dt,
            # the integral learns in free space, once the reference stands
            # still: in position segments, and in force segments until the
            # first contact (the descent to the hole: the arm's posture
            # changes and, held, the approach's integral let the tip drift
            # 0.3-0.4 mm sideways, onto the mouth's edge); then it is held:
            # in contact a wall takes whatever it pushes, and a wound-up
            # integral jams the peg
            integrate=(st.short_move or seg_t >= plan.move_s)
            and (plan.scheme == "position" or (plan.scheme == "force" and not st.hybrid.contact)),
            a_ref=a6,
            inertia=inertia,
        )
        pl["tcp_xyz_m"] = kin.p
        pl["tcp_rot_xyz"] = matrix_to_rotvec(kin.R)
        pl["goal_xyz_m"] = plan.pose[:3]
        pl["goal_rot_xyz"] = plan.pose[3:]
        pl["ref_xyz_m"] = p_ref
        pl["wrench_task"] = applied
        pl["wrench_goal"] = plan.force if plan.scheme == "force" else np.zeros(6)
        pl["selection"] = plan.selection if plan.scheme == "force" else np.zeros(6)
        pl["contact"] = 1 if st.hybrid.contact else 0
        return tau, q

    @staticmethod
    def _pose_into(st: RobotState, q: np.ndarray[Any, Any], pl: Any) -> None:
        kin = st.model.kinematics(q)
        pl["tcp_xyz_m"] = kin.p
        pl["tcp_rot_xyz"] = matrix_to_rotvec(kin.R)
        pl["goal_xyz_m"] = kin.p
        pl["goal_rot_xyz"] = matrix_to_rotvec(kin.R)
        pl["ref_xyz_m"] = kin.p
        pl["wrench_task"] = 0.0
        pl["wrench_goal"] = 0.0
        pl["selection"] = 0

"""The SSC worker (paper priority 18): task planning, trajectories, control laws, coordination.

Each cycle it reads every robot's feedback (written by the ddm), advances
the task on the boards' sample clock (the feedback's ``step``: a simulation
running behind real time does not leave the references ahead), and writes
one command per robot: joint torques from the segment's control law for the
segment's robot, a joint PID hold for the others, every joint on, and the
session status. It computes nothing before every robot has reported (the
datum: feedback from each ESC). After the last segment and ``settle_s`` the
commands say the session is finished and the plan says done.

The hot path works in place: the feedback, command and plan records' fields
are views made once; a Cartesian segment is one call of
:class:`~redistro.control.cartesian.CartesianLaw` (a compiled kernel) on the
rigid-body terms Pinocchio gives once per quantity; what is constant over a
segment (its goal, wrench and selection in the plan) is written when it
begins.

Past the house's ~400 lines: planning, the laws and the search's phases
act on the same robot states in the same cycle.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from redistro import kernels
from redistro.config.model import TRIP_M
from redistro.control.cartesian import (
    ForceParams,
    ImpedanceGains,
    TaskFrameCommand,
    matrix_to_rotvec,
    move_gains,
    pose_error,
    rotvec_to_matrix,
)
from redistro.control.cartesian_law import CartesianLaw
from redistro.control.dynamics import ArmModel
from redistro.control.pid import PidGains, PidLoop, PidState
from redistro.control.search import Phase, SpiralSearch
from redistro.control.trajectory import QuinticRef
from redistro.localdata.block import Record
from redistro.localdata.layout import COMMAND, FEEDBACK, PLAN, SessionStatus
from redistro.process import hooks
from redistro.process.worker import Worker
from redistro.robotmodel import PLATE, Peg
from redistro.ssc import parallel
from redistro.ssc.carry import CarryRun, carry_moves
from redistro.ssc.clearance import ClearanceWatch
from redistro.ssc.follow import Follow
from redistro.ssc.operator import Operator
from redistro.ssc.plan import SCHEMES, MovePlan, SegmentPlan, segment_plans
from redistro.ssc.search_steps import steer

DOF = 7
RETREAT_S = 2.0  # a failed search lifts the tool off in this long [s]
RETREAT_HOLD_S = 0.5  # ... and holds it there this long before the task ends [s]
ON = np.ones(DOF, dtype=bool)
AFTER = 255  # plan.segment once every segment is over


@dataclass
class RobotState:
    """One robot of the group: its model, its law, its records' views."""

    name: str
    model: ArmModel
    law: CartesianLaw
    tcp_offset_m: float
    base: np.ndarray[Any, Any]
    fb: Record
    cmd: Record
    plan: Record
    hold_q: np.ndarray[Any, Any] = field(default_factory=lambda: np.zeros(DOF))
    pid: PidState = field(default_factory=PidState)
    cartesian: bool = False  # the running segment drives it through the law
    start_q: np.ndarray[Any, Any] = field(default_factory=lambda: np.zeros(DOF))
    short_move: bool = False  # the goal is where the segment starts (within 2 mm)
    # per-cycle scratch
    g: np.ndarray[Any, Any] = field(default_factory=lambda: np.zeros(DOF))
    qd_ref: np.ndarray[Any, Any] = field(default_factory=lambda: np.zeros(DOF))
    qdd_ref: np.ndarray[Any, Any] = field(default_factory=lambda: np.zeros(DOF))
    zero: np.ndarray[Any, Any] = field(default_factory=lambda: np.zeros(DOF))
    R: np.ndarray[Any, Any] = field(default_factory=lambda: np.eye(3))
    t: np.ndarray[Any, Any] = field(default_factory=lambda: np.zeros(3))
    views: dict[str, np.ndarray[Any, Any]] = field(default_factory=dict)
    to_records: Any = None  # the law's outputs -> plan and command records
    search: SpiralSearch | None = None  # the running force segment's search
    gains0: np.ndarray[Any, Any] = field(default_factory=lambda: np.zeros(0))  # the move's
    gains_cfg: np.ndarray[Any, Any] = field(default_factory=lambda: np.zeros(0))  # the config's
    fast_z: float = -math.inf  # in the hole: down fast below this height ...
    slow_z: float = -math.inf  # ... to this one, then at the law's own speed
    goal_z_n: float = 0.0  # the segment's goal force along z
    follow: Follow | None = None  # its move follows another hand (ssc/follow.py) ...
    holder: Any = None  # ... this robot's state
    let_go: bool = False  # its gripper opened as the last segment ended

    def __post_init__(self) -> None:
        fb, cmd, pl = self.fb.array, self.cmd.array, self.plan.array
        self.views = {
            "q": fb["q_rad"],
            "qd": fb["qd_rad_s"],
            "wrench": fb["wrench"],
            "tau": cmd["tau_nm"],
            "q_cmd": cmd["q_cmd_rad"],
            "tcp": pl["tcp_xyz_m"],
            "rot": pl["tcp_rot_xyz"],
            "goal": pl["goal_xyz_m"],
            "goal_rot": pl["goal_rot_xyz"],
            "ref": pl["ref_xyz_m"],
            "wrench_task": pl["wrench_task"],
            "wrench_goal": pl["wrench_goal"],
            "selection": pl["selection"],
            "q_goal": pl["q_goal_rad"],
            "search_xy": pl["search_xy_m"],
        }
        cmd["joint_on"] = ON
        self.to_records = _LawCopier(self.law, self.cmd, self.plan)
        self.on = ON.copy()

    def loops(self, gains: PidGains) -> None:
        """The joint PID bound to this robot's arrays: holding ``hold_q``, or
        tracking a joint segment's quintic (written into the command's q_cmd)."""
        v = self.views
        self.hold_loop = PidLoop(
            gains, self.pid, v["q"], v["qd"], self.hold_q, self.zero, self.g, self.on, v["tau"]
        )
        self.quintic = QuinticRef(v["q_cmd"], self.qd_ref, self.qdd_ref)
        self.joint_loop = PidLoop(
            gains, self.pid, v["q"], v["qd"], v["q_cmd"], self.qd_ref, self.g, self.on, v["tau"]
        )

    def hold_plan(self) -> None:
        """The plan's constant fields while the robot holds its pose."""
        self.plan["scheme"] = SCHEMES["hold"]
        self.plan["contact"] = 0
        self.plan["phase"] = Phase.NONE
        self.search = None
        v = self.views
        v["q_goal"][...] = self.hold_q
        v["wrench_task"][...] = 0.0
        v["wrench_goal"][...] = 0.0
        v["selection"][...] = 0


class _LawCopier:
    """Copies the law's outputs into the command (torques) and the plan (the
    applied wrench, the TCP pose, the reference): two kernel calls."""

    def __init__(self, law: CartesianLaw, cmd: Record, plan: Record) -> None:
        out = law.out.reshape(1).view(np.uint8)
        parts = []
        for rec, fields in (
            (cmd, [(law.tau, "tau_nm")]),
            (plan, [(law.applied, "wrench_task"), (law.tcp_p, "tcp_xyz_m")]),
        ):
            spec = rec.array.dtype.fields
            assert spec is not None
            rows = [
                (kernels.address_in(out, v), int(spec[name][1]), v.nbytes) for v, name in fields
            ]
            if rec is plan:
                for v, name in ((law.tcp_rot, "tcp_rot_xyz"), (law.ref_p, "ref_xyz_m")):
                    rows.append((kernels.address_in(out, v), int(spec[name][1]), v.nbytes))
            parts.append((out, rec.array.reshape(1).view(np.uint8), kernels.copy_table(rows)))
        self.runs: list[Any] = []
        for src, dst, table in parts:
            if kernels.AVAILABLE:
                p = kernels.plan("copy", src=src, dst=dst, table=table)
                run = kernels.KERNELS.copy
                self.runs.append(lambda p=p, run=run: run(p))
            else:
                self.runs.append(
                    lambda src=src, dst=dst, table=table: kernels.copy_rows(src, dst, table)
                )

    def __call__(self) -> None:
        for run in self.runs:
            run()


def f64(values: list[float]) -> np.ndarray[Any, Any]:
    return np.asarray(values, dtype=np.float64)


class SscWorker(Worker):
    def initialize(self) -> None:
        cfg = self.cfg = self.spec.cfg()
        task = self.spec.task()
        self.settle_s = task.settle_s
        self.plans: list[SegmentPlan] = segment_plans(task, cfg)
        self.robots = list(self.spec.robots)
        self.physics_hz = cfg.plant.physics_hz
        self.gains, self.force, self.pid = _law_params(cfg)
        peg = cfg.workcell.peg
        ld = self.ld
        n = len(self.robots)
        self.fb_blocks = [ld.block("feedback", i) for i in range(n)]
        self.cmd_blocks = [ld.writer("command", i, role="worker") for i in range(n)]
        self.plan_blocks = [ld.writer("plan", i, role="worker") for i in range(n)]
        self.states: list[RobotState] = []
        for r in self.robots:
            rc = cfg.robots[r]
            tool = Peg(peg.side_m, peg.length_m, peg.mass_kg) if rc.peg else None
            model = ArmModel(tool, rc.base_xyz_m)
            offset = peg.length_m if tool is not None else PLATE[1]
            base = f64(rc.base_xyz_m)
            law = CartesianLaw(self.gains, self.force, offset, base)
            st = RobotState(
                r, model, law, offset, base, Record(FEEDBACK), Record(COMMAND), Record(PLAN)
            )
            st.gains_cfg, st.gains0 = law.gains.copy(), law.gains.copy()
            self.states.append(st)
        for st in self.states:
            st.loops(self.pid)
        self.fbs = [st.fb for st in self.states]
        self.plan_recs = [st.plan for st in self.states]
        self.started = False
        self.t0_step = 0
        self.last_t = 0.0
        self.k = -1  # running segment (0-based); len(plans): settling; then done
        self.seg_start_t = 0.0
        self.law_start_t = 0.0  # the moving law's clock (a failed search's lift restarts it)
        # per robot: its move in the running segment (None: it holds), the
        # move it is driven by now (None once a guarded move met its
        # contact), whether it met it, since when its end conditions held
        self.seg_moves: list[MovePlan | None] = [None] * n
        self.carry: CarryRun | None = None  # the running segment's carry (two hands, one object)
        self.k_trans = [float(v) for v in cfg.ssc.impedance.k[:3]]
        self.moving: list[MovePlan | None] = [None] * n
        self.contacted = [False] * n
        self.cond_since: list[float | None] = [None] * n
        self.done = False
        self.failed = ""  # why the task could not be done (a search found no hole)
        self.retreat_end_t = 0.0  # when the failed task's lift is over
        self.produced = 0
        # the arms' clearance, in every cycle (ssc/clearance.py), and what
        # acts on this worker from outside (the fault harness; none normally)
        self.watch = ClearanceWatch(cfg, self.robots, 1.0 / cfg.ssc.rate_hz)
        self.qs = [st.views["q"] for st in self.states]
        make = hooks.factory("ssc_hooks")
        self.hooks = make(self.spec.node) if make else None
        # the robots whose laws this process runs (all; an arm worker its own),
        # and its part in a parallel SSC (ssc/parallel.py; none in a serial one)
        self.mine = list(range(n))
        self.narrates = True  # it says what the task does (an arm worker only its own arm)
        self.fail_robot, self.fail_t = -1, 0.0  # the last _fail's robot and time
        self.arm, self.lead = parallel.parts(self, _grip, RETREAT_S + RETREAT_HOLD_S)
        # the operator's pause, resume and jog (ssc/operator.py; a serial SSC's)
        serial = self.arm is None and self.lead is None
        self.operator = Operator(self) if serial else None

    def idle(self, deadline_ns: int) -> bool:
        """A jog's planning, in slices (none: one call, nothing done)."""
        return self.operator.idle() if self.operator is not None else False

    # -- the cycle --

    def step(self, cycle: int) -> None:
        if self.lead is not None:
            self.lead.step(cycle)  # the task's clock, after the arms' laws
            return
        if not self.read_feedback():
            return  # the datum: not every robot has reported yet
        step_now = max(rec["step"] for rec in self.fbs)
        arm = self.arm
        if arm is not None:
            if not arm.take():
                return  # (the task's clock has not started it)
        elif not self.started:
            self.start_task(step_now)
        t = (step_now - self.t0_step) / self.physics_hz
        dt = max(0.0, t - self.last_t)
        self.last_t = t
        if arm is None:
            if not self.estop_request:
                self._clearance(t)
            arms_m, cell_m = self.watch.arms_m, self.watch.cell_m
        else:
            arms_m, cell_m = arm.clearance()
        if self.hooks is not None:
            self.hooks.steer(self.states, dt)
        op = self.operator
        if op is not None:
            op.take(t, dt)  # (the operator's command; paused, the segment's clock stops)
        if arm is None and (op is None or not op.paused):
            self._advance(t)
        seg_t = t - self.seg_start_t
        law_t = t - self.law_start_t
        status = SessionStatus.FINISHED if self.done else SessionStatus.IN_PROGRESS
        segment = AFTER if self.k >= len(self.plans) else self.k + 1
        done = 1 if self.done else 0
        failed = 1 if self.failed else 0
        now = time.monotonic_ns()
        self.produced += 1
        for i in self.mine:
            st = self.states[i]
            pl = st.plan
            pl["stamp_ns"] = now
            pl["cycle"] = cycle
            pl["t_s"] = t
            pl["segment"] = segment
            pl["segment_t_s"] = seg_t
            pl["done"] = done
            pl["failed"] = failed
            pl["arms_clearance_m"] = arms_m
            pl["cell_clearance_m"] = cell_m
            mv = self.moving[i]
            if mv is not None and not self.done:
                pl["moving"] = 1
                self._law(st, mv, law_t, dt, t)
                if mv.contact_n > 0:
                    self._guarded(i, st, mv, t)
            else:
                pl["moving"] = 0
                if op is not None and op.paused:
                    op.hold(i, st, dt, t)
                else:
                    self._hold(st, dt)
            self.plan_blocks[i].publish(pl.bytes)
        # every robot's command at once, then one wake of the ddm: it sends
        # them together (a wake per robot cost the ddm a whole step each)
        for i in self.mine:
            c = self.states[i].cmd
            c["stamp_ns"] = time.monotonic_ns()
            c["seq_src"] = self.produced
            c["session_status"] = status
            self.cmd_blocks[i].publish(c.bytes)
        if arm is None:
            self.wake_ddm()  # (in a parallel SSC the clock's worker, once every arm's is out)

    def read_feedback(self) -> bool:
        """Every robot's feedback into its record; whether each has reported."""
        for block, rec in zip(self.fb_blocks, self.fbs, strict=True):
            block.read_into(rec.bytes)
        return all(rec["seq_src"] for rec in self.fbs)

    def start_task(self, step_now: int) -> None:
        """Every robot reported: the task's clock starts at this sample."""
        self.started = True
        self.t0_step = step_now
        for st in self.states:
            st.hold_q[...] = st.views["q"]
        self.post(f"every robot reported; task starts ({len(self.plans)} segments)")
        self._begin(0, 0.0)

    def _clearance(self, t: float) -> None:
        """Ask for the group's e-stop when a measured arm comes within TRIP_M
        of another or of the work-cell (before they touch)."""
        hit = self.watch.check(self.qs, t)
        if hit is None:
            return
        self.estop_request = True
        self.post(
            f"{hit.links[0]} and {hit.links[1]} {hit.distance_m * 100:.1f} cm apart at "
            f"t={t:.2f} s, {max(hit.ahead_m, 0.0) * 100:.1f} cm once stopped at the speed "
            f"they close (under {TRIP_M * 100:g} cm): e-stop",
            logging.ERROR,
        )

    # -- task planning --

    def _begin(self, k: int, t: float) -> None:
        """Start segment k at task time t (k == len(plans): settle, then done)."""
        self.k = k
        self.seg_start_t = self.law_start_t = t
        self.cond_since = [None] * len(self.states)
        self.contacted = [False] * len(self.states)
        was = self.moving
        if k >= len(self.plans):
            self.moving = self.seg_moves = [None] * len(self.states)
            self.carry = None
            for st in self.states:
                st.hold_q[...] = st.views["q"]
                st.pid.reset()
                st.cartesian = False
                st.hold_plan()
            if self.narrates:
                self.post(f"every segment done at t={t:.2f} s; settling {self.settle_s} s")
            return
        plan = self.plans[k]
        self.seg_moves = [plan.move_of(st.name) for st in self.states]
        self.carry = None if plan.carry is None else self._carry_run(plan)
        if self.carry is not None:
            self.seg_moves = carry_moves(self.seg_moves, self.carry)
        self.moving = list(self.seg_moves)
        for st, mv, moved in zip(self.states, self.moving, was, strict=True):
            if mv is None:
                if moved is not None or k == 0:
                    st.hold_q[...] = st.views["q"]  # it was moving: it holds where it is now
                    st.pid.reset()
                st.cartesian = False
                st.hold_plan()
            else:
                _start_move(st, mv, self.states)
        if self.narrates:
            moves = ", ".join(f"{m.robot} {m.scheme}" for m in plan.moves) or "every robot holds"
            self.post(f"segment {k + 1}/{len(self.plans)} {plan.name}: {moves}")

    def _carry_run(self, plan: SegmentPlan) -> CarryRun:
        """A carry: from where the carry before it left the hands (its goals),
        else from where they are (measured)."""
        sts = [self.states[self.robots.index(mv.robot)] for mv in plan.moves]
        kins = [st.model.kinematics(st.views["q"].astype(np.float64)) for st in sts]
        k = self.k_trans
        return CarryRun(plan, kins, min(k[0], k[1]), k[2], self.carry)

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
        if self.failed:
            if t >= self.retreat_end_t:
                self._begin(len(self.plans), t)  # lifted off: hold, then end
        elif seg_t >= plan.duration_s or self._ended_early(plan, t):
            for st, mv in zip(self.states, self.moving, strict=True):
                if mv is not None and search_open(st, self.lead is not None):
                    why = f"hole not found within the segment's {plan.duration_s:g} s"
                    self._fail(st, mv, t, why, closing=True)
                    return
            _grip(self.states, self.seg_moves, t, self.post)
            self._begin(self.k + 1, t)

    def _ended_early(self, plan: SegmentPlan, t: float) -> bool:
        """Every moving robot's end conditions (those that have any; with
        ``until: any``, one robot's) met: a guarded move's contact, any
        time; the tolerances held for their hold_s, once the moves are over."""
        over = t - self.seg_start_t >= plan.move_s
        held = []
        for i, mv in enumerate(self.seg_moves):
            if mv is None or not mv.ends_early:
                continue
            held.append(self.contacted[i] if mv.contact_n > 0 else over and self._held(i, mv, t))
        return bool(held) and (any(held) if plan.until == "any" else all(held))

    def _held(self, i: int, mv: MovePlan, t: float) -> bool:
        if not _within(self.plan_recs[i].array, mv):
            self.cond_since[i] = None
            return False
        since = self.cond_since[i]
        if since is None:
            since = self.cond_since[i] = t
        return t - since >= mv.hold_s

    def _guarded(self, i: int, st: RobotState, mv: MovePlan, t: float) -> None:
        """A guarded move at its first contact (the wrist's force over the
        move's contact_n): the robot holds where it is from now on."""
        f = st.views["wrench"]
        if math.sqrt(float(f[0] * f[0] + f[1] * f[1] + f[2] * f[2])) <= mv.contact_n:
            return
        self.contacted[i] = True
        self._stop(i, st)
        st.plan["contact"] = 1
        self.post(f"{st.name} {mv.skill}: contact at t={t:.2f} s, holding there")

    def _stop(self, i: int, st: RobotState) -> None:
        """A moving robot holds where it is from now on, for the rest of the segment."""
        self.moving[i] = None
        st.hold_q[...] = st.views["q"]
        st.pid.reset()
        st.cartesian = False
        st.hold_plan()

    # -- control laws --

    def _hold(self, st: RobotState, dt: float) -> None:
        """A joint PID holding ``hold_q`` (gravity compensated)."""
        v = st.views
        q = v["q"]
        st.model.gravity_into(q, st.g)
        st.hold_loop.update(dt)
        v["q_cmd"][...] = st.hold_q
        _pose(st, q, goal=True)

    def _law(self, st: RobotState, plan: MovePlan, seg_t: float, dt: float, t: float) -> None:
        v = st.views
        q = v["q"]
        if not st.cartesian:  # a joint segment: a quintic in joint space, a joint PID
            st.quintic.at(seg_t)
            st.model.gravity_into(q, st.g)
            st.joint_loop.update(dt)
            _pose(st, q, goal=False)
            return
        law = st.law
        st.model.terms_into(q, law.J, law.R, law.t, law.M, law.g)
        if st.follow is not None:
            law.t -= st.follow.update(st.holder)
        law.q[...] = q
        law.qd[...] = v["qd"]
        law.wrench[...] = v["wrench"]
        if st.search is not None:
            steer(self, st, plan, seg_t, dt, t)  # the search (ssc/search_steps.py)
        c = self.carry if plan.skill == "carry" else None
        hand = c.index(st.name) if c is not None else -1
        if c is not None:
            c.before(hand, law, seg_t, v["wrench_goal"])
        # the integral learns in free space, once the reference stands still:
        # in position segments, and in force segments until the first
        # contact (the descent to the hole: the arm's posture changes and,
        # held, the approach's integral let the tip drift 0.3-0.4 mm
        # sideways, onto the mouth's edge); then it is held: in contact a
        # wall takes whatever it pushes, and a wound-up integral jams the peg
        integrate = (st.short_move or seg_t >= plan.move_s) and (
            (plan.scheme == "position" and c is None)
            or (plan.scheme == "force" and not law.contact)
        )  # (a carry never: the hands hold the object, and its squeeze has a loop of its own)
        law.update(seg_t, dt, seg_t, integrate)
        if c is not None:
            c.after(hand, law, dt)
        st.to_records()
        v["q_cmd"][...] = q
        st.plan["contact"] = 1 if law.contact else 0

    def _fail(
        self, st: RobotState, plan: MovePlan, t: float, why: str, closing: bool = False
    ) -> None:
        """The task cannot be done (the search found no hole; ``closing``: its
        segment ended with the search still open): the robot lifts its tool
        straight up to the segment's start height under position control (off
        the surface it pressed, so that the next session starts free), every
        other robot holds, then the task ends ``failed``."""
        if closing:
            close_search(st)
        self.failed = f"{plan.name}: {why}"
        self.fail_robot, self.fail_t = self.states.index(st), t
        if self.narrates or not closing:  # (an arm worker: the clock's worker said it)
            self.post(f"{self.failed}; the tool lifts off and the task stops", logging.ERROR)
        q = st.views["q"].astype(np.float64)
        kin = st.model.kinematics(q)
        lift = np.concatenate(
            [kin.p[:2], [max(float(kin.p[2]), float(plan.pose[2]))], plan.pose[3:]]
        )
        cmd = TaskFrameCommand(lift, np.zeros(6), np.zeros(6), "world")
        st.law.start(cmd, kin.p, kin.R, RETREAT_S, q, st.law.integral.copy())
        st.short_move = False
        st.views["wrench_goal"][...] = 0.0
        st.views["selection"][...] = 0
        st.views["goal"][...] = lift[:3]
        st.plan["scheme"] = SCHEMES["position"]
        self.law_start_t = t  # the lift's own clock (the segment's goes on, for its figures)
        self.retreat_end_t = t + RETREAT_S + RETREAT_HOLD_S
        for k, other in enumerate(self.states):  # (their moves' clock restarts: they stop)
            if other is not st and self.moving[k] is not None:
                self._stop(k, other)


def _start_move(st: RobotState, mv: MovePlan, states: list[RobotState]) -> None:
    """A robot's move begins: its law or its quintic, its plan's goal."""
    let_go, st.let_go = st.let_go, False
    q = st.views["q"].astype(np.float64)
    v = st.views
    st.pid.reset()
    st.start_q = q.copy()
    kin = st.model.kinematics(q)
    p0 = _follows(st, mv, states, kin.p)  # (following: its TCP in the plan's frame)
    st.plan["scheme"] = SCHEMES[mv.scheme]
    v["q_goal"][...] = mv.q_goal
    if mv.scheme in ("position", "force"):
        force = mv.scheme == "force"
        cmd = TaskFrameCommand(
            mv.pose,
            mv.force,
            mv.selection if force else np.zeros(6),
            "tool" if mv.frame == "tool" else "world",
        )
        # staying Cartesian keeps the integral (else the pose sags back at
        # each start); not into a carry (learned at the grasp: a bar turned
        # 8 mrad off), nor once the hand let go (a jolt at the free wrist)
        keep = st.cartesian and mv.skill != "carry" and not let_go
        carried = st.law.integral.copy() if keep else None
        move_gains(st.gains0, st.gains_cfg, mv.stiffness)
        st.law.gains[...] = st.gains0  # (a search may have changed them)
        st.law.start(cmd, p0, kin.R, mv.move_s, st.start_q, carried)
        st.cartesian = True
        st.short_move = bool(
            np.linalg.norm(cmd.goal_p - p0) < 0.002
            and np.linalg.norm(matrix_to_rotvec(cmd.goal_R @ kin.R.T)) < 0.01
        )
        v["goal"][...] = mv.pose[:3]
        v["goal_rot"][...] = mv.pose[3:]
        v["wrench_goal"][...] = mv.force if force else 0.0
        v["selection"][...] = mv.selection if force else 0
        st.plan["phase"] = Phase.NONE
        st.search = None
        if force and mv.search.pattern == "spiral":
            st.search = SpiralSearch(mv.search, mv.mouth_z_m)
            st.goal_z_n = float(mv.force[2])
            st.plan["phase"] = Phase.DESCENT
            st.plan["search_m"] = 0.0
            v["search_xy"][...] = 0.0
    else:
        st.cartesian = False
        st.quintic.start(st.start_q, mv.q_goal, mv.move_s)
        goal = st.model.kinematics(mv.q_goal)
        v["goal"][...] = goal.p
        v["goal_rot"][...] = matrix_to_rotvec(goal.R)
        v["wrench_task"][...] = 0.0
        v["wrench_goal"][...] = 0.0
        v["selection"][...] = 0
        st.plan["contact"] = 0


def _law_params(cfg: Any) -> tuple[ImpedanceGains, ForceParams, PidGains]:
    """The config's Cartesian law gains, force control and joint PID."""
    imp = cfg.ssc.impedance
    gains = ImpedanceGains(
        k=f64(imp.k),
        d=f64(imp.d),
        ki=f64(imp.ki),
        i_max=f64(imp.i_max),
        k_null=f64(imp.k_null),
        d_joint=f64(imp.d_joint),
        zeta=imp.zeta,
    )
    fc = cfg.ssc.force
    force = ForceParams(
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
    pid = PidGains(f64(p.kp), f64(p.ki), f64(p.kd), f64(p.i_max_nm))
    return gains, force, pid


OPEN = (Phase.DESCENT, Phase.SETTLE, Phase.SEARCH)


def search_open(st: RobotState, by_plan: bool) -> bool:
    """Whether the robot's search is still looking for the hole (``by_plan``:
    as its plan record says, where its law runs in another process)."""
    if by_plan:
        return int(st.plan["phase"]) in OPEN
    return st.search is not None and st.search.phase in OPEN


def close_search(st: RobotState) -> None:
    """The robot's search ends, the hole not found: the law's own gains back."""
    st.law.gains[...] = st.gains0
    if st.search is not None:
        st.search.phase = Phase.NOT_FOUND
    st.plan["phase"] = Phase.NOT_FOUND


def _follows(
    st: RobotState, mv: MovePlan, states: list[RobotState], p: np.ndarray[Any, Any]
) -> np.ndarray[Any, Any]:
    """A move's following of another hand set up (or none); ``p``, the
    TCP's measured position, in the frame the law will see."""
    st.follow = st.holder = None
    if mv.follows and mv.holder_pose is not None and mv.follow_point is not None:
        st.holder = next(h for h in states if h.name == mv.follows)
        st.follow = Follow(mv.holder_pose, mv.follow_point)
        out: np.ndarray[Any, Any] = p - st.follow.update(st.holder)
        return out
    return p


def _pose(st: RobotState, q: np.ndarray[Any, Any], goal: bool) -> None:
    """The TCP's pose into the plan (and, holding, as the goal and reference)."""
    st.model.pose_into(q, st.R, st.t)
    R, v = st.R, st.views
    off = st.tcp_offset_m
    tcp = v["tcp"]
    tcp[...] = st.t
    tcp += st.base
    x, y, z = R[0, 2] * off, R[1, 2] * off, R[2, 2] * off
    tcp[0] += x
    tcp[1] += y
    tcp[2] += z
    v["rot"][...] = _rotvec(R)
    v["ref"][...] = tcp
    if goal:
        v["goal"][...] = tcp
        v["goal_rot"][...] = v["rot"]


def _grip(states: list[RobotState], moves: list[MovePlan | None], t: float, post: Any) -> None:
    """As a segment ends, the grippers its grasps close and its releases
    open (in the robots' commands from now on: nothing per cycle)."""
    for st, mv in zip(states, moves, strict=True):
        if mv is not None and mv.gripper:
            st.cmd["gripper"] = 1 if mv.gripper == "close" else 0
            st.let_go = mv.gripper == "open"
            done = "closed" if mv.gripper == "close" else "opened"
            post(f"{st.name} {mv.skill}: gripper {done} at t={t:.2f} s")


def _within(pl: Any, mv: MovePlan) -> bool:
    """A robot's plan record inside its move's end tolerances (those given;
    the pose's against the plan's goal: a Cartesian move's pose, a joint
    move's TCP at its joint goal)."""
    if mv.pose_within_m > 0 or mv.rot_within_rad > 0:
        e = pose_error(
            pl["tcp_xyz_m"],
            rotvec_to_matrix(pl["tcp_rot_xyz"]),
            pl["goal_xyz_m"],
            rotvec_to_matrix(pl["goal_rot_xyz"]),
        )
        if mv.pose_within_m > 0 and float(np.linalg.norm(e[:3])) > mv.pose_within_m:
            return False
        if mv.rot_within_rad > 0 and float(np.linalg.norm(e[3:])) > mv.rot_within_rad:
            return False
    if mv.force_within_n > 0:
        err = (mv.force - pl["wrench_task"]) * mv.selection
        if not pl["contact"] or float(np.linalg.norm(err[:3])) > mv.force_within_n:
            return False
    return True


def _rotvec(R: np.ndarray[Any, Any]) -> tuple[float, float, float]:
    """The rotation vector of R, in plain floats (:func:`matrix_to_rotvec`)."""
    (a, b, c_), (d, e, f), (g, h, i) = R.tolist()
    c = max(-1.0, min(1.0, (a + e + i - 1.0) / 2.0))
    angle = math.acos(c)
    if angle < 1e-9 or math.pi - angle < 1e-6:
        x, y, z = matrix_to_rotvec(R).tolist()
        return x, y, z
    scale = angle / (2.0 * math.sin(angle))
    return (h - f) * scale, (c_ - g) * scale, (d - b) * scale

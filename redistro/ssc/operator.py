"""The operator's hand in the SSC worker: pause, resume and jog (``redistro ctl``).

Each cycle the worker reads the ``operator`` block (its manager took the
signed command, ``ssc/ctl.py``) and, on a new command:

- **pause**: every robot holds where it is: one moving under its Cartesian
  law keeps the law, restarted on the pose it is at with every axis under
  position control (a force axis's goal force goes to zero; the arm holds
  its place), anchored again where it comes to rest; one on a joint move
  too (its law's integral from nought); one that held already, its hold.
  The segment's clock stops; the answer waits until every joint is at rest.
- **resume**: the segment starts again from the current pose, its moves
  re-planned (the task's clock goes on from where it stopped).
- **jog** (paused, once at rest): the pose one robot's tool holds moves by
  a step of at most 5 mm or 2 degrees in the world frame. Its posture is
  found in the Idle state (damped least squares on the arm's model, a few
  iterations a slice), checked against the joint limits less the guard's
  margin and the planned clearance (``MIN_CLEARANCE_M``); then the robot's
  Cartesian law (taking over from the joint PID where it held) moves the
  tool there, its reference's peak speed under ``JOG_M_S`` and
  ``JOG_RAD_S``. The guard on the ESC and the clearance watch of every
  cycle apply as ever.

What it costs a cycle: one seqlocked read of the block (0.25 µs timed
alone); paused, each robot's hold instead of its move.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from redistro.config.model import MIN_CLEARANCE_M
from redistro.control.cartesian import move_gains
from redistro.localdata.block import Record
from redistro.localdata.layout import OPERATOR
from redistro.ssc.ctl import STATUS_TEXT, Command, Status
from redistro.ssc.plan import SCHEMES

if TYPE_CHECKING:
    from redistro.ssc.worker import RobotState, SscWorker

HOLD_S = 0.05  # a pause's hold: the law's reference settles on the pose in this long [s]
REST_RAD_S = 0.01  # paused: at rest once every joint is slower than this [rad/s] ...
REST_WAIT_S = 3.0  # ... or after this long [s]
HOLD_K = (1500.0, 1500.0, 1500.0, 30.0, 30.0, 30.0)  # a hold's stiffness [N/m, N m/rad]
JOG_M_S = 0.01  # a jog's peak tool speed [m/s] ...
JOG_RAD_S = 0.05  # ... and turn rate [rad/s]
JOG_MIN_S = 0.3  # the shortest jog [s]
JOG_SETTLE_S = 0.3  # a jog is done this long after its move, once at rest [s]
QUINTIC_PEAK = 1.875  # a quintic's peak speed over its mean
IK_POS_M = 2e-5  # the jog's posture: within this of the stepped pose ...
IK_ROT_RAD = 2e-4  # ... and this of its rotation
IK_ITERATIONS = 60
IK_PER_SLICE = 4


class Operator:
    """The worker's part of the operator's commands (a serial SSC's worker)."""

    def __init__(self, worker: SscWorker) -> None:
        from redistro.config.limits import joint_limits

        self.w = worker
        self.block = worker.ld.block("operator")
        self.rec = Record(OPERATOR)
        self.seen = 0
        self.paused = False
        self.limits = joint_limits(worker.cfg)
        self.by_law = [False] * len(worker.states)  # paused: held by its Cartesian law ...
        self.free = [False] * len(worker.states)  # ... out of contact (its integral learns)
        self.stopping = False  # paused, the robots not yet at rest (the answer waits)
        self.since = 0.0  # task time paused so far, in this pause [s]
        self.total = 0.0  # task time paused in every pause so far [s]
        self.planning: Iterator[None] | None = None  # a jog's posture, found in Idle
        self.jog: tuple[int, float, float] | None = None  # (robot, start [s], length [s])
        self.jog_end = 0.0  # (task time) [s]

    # -- each cycle --

    def take(self, t: float, dt: float) -> None:
        """A new command acted on; paused, the segment's clock held."""
        self.block.read_into(self.rec.bytes)
        seq = int(self.rec["seq"])
        if seq != self.seen:
            self.seen = seq
            self._act(Command(int(self.rec["command"])), seq, t)
        if self.paused:
            w = self.w
            w.seg_start_t += dt  # (the segment's clock stops)
            w.law_start_t += dt
            self.since += dt
            self.total += dt
            for st in w.states:
                st.plan["paused_s"] = self.total
            if self.stopping and (self.since >= REST_WAIT_S or self._at_rest()):
                self.stopping = False
                for i, st in enumerate(w.states):
                    if self.by_law[i]:
                        self._hold_here(st)  # (anchored where it came to rest)
                self._answer(self.seen, Command.PAUSE, Status.DONE)
                w.post(f"operator pause: every robot at rest {self.since:.2f} s after it")

    def _at_rest(self) -> bool:
        return all(float(np.abs(st.views["qd"]).max()) <= REST_RAD_S for st in self.w.states)

    def _act(self, cmd: Command, seq: int, t: float) -> None:
        w = self.w
        status = Status.DONE
        if cmd == Command.PAUSE:
            if not w.started or w.done or w.failed:
                status = Status.NOT_NOW
            elif not self.paused:
                self._pause(t)
                status = Status.UNDER_WAY  # (done once every robot is at rest)
        elif cmd == Command.RESUME:
            if not self.paused:
                status = Status.NOT_NOW
            elif self.jog is not None or self.planning is not None:
                status = Status.BUSY
            else:
                self._resume(t)
        elif cmd == Command.JOG:
            if not self.paused:
                status = Status.NOT_NOW
            elif self.jog is not None or self.planning is not None:
                status = Status.BUSY
            else:
                i = int(self.rec["robot"])
                self.planning = self._plan(i, np.array(self.rec.array["step"], dtype=np.float64))
                status = Status.UNDER_WAY
        else:
            return  # (stop and e-stop: the manager's)
        self._answer(seq, cmd, status)

    def _answer(self, seq: int, cmd: Command, status: Status, why: str = "") -> None:
        for st in self.w.states:
            pl = st.plan
            pl["op_seq"] = seq
            pl["op_command"] = int(cmd)
            pl["op_status"] = int(status)
            pl["paused"] = 1 if self.paused else 0
        if status not in (Status.DONE, Status.UNDER_WAY):
            text = why or STATUS_TEXT[status]
            self.w.post(f"operator {cmd.name.lower()}: {text}", logging.WARNING)

    def _pause(self, t: float) -> None:
        w = self.w
        for i, st in enumerate(w.states):
            self.free[i] = not int(st.plan["contact"])
            self.by_law[i] = False
            if w.moving[i] is None:
                continue  # (it holds already: its PID, integral and all, goes on)
            # its Cartesian law holds the pose it is at; a joint move's too (a
            # joint PID set on the pose it was at overshot it, settled for
            # seconds and let the tool sag mm), its integral from nought
            self._hold_here(st, learned=st.cartesian)
            w.moving[i] = None
            self.by_law[i] = True
        self.paused, self.since, self.stopping = True, 0.0, True
        w.post(f"operator pause at t={t:.2f} s: every robot holds")

    def _hold_here(self, st: RobotState, learned: bool = True) -> None:
        """The robot's Cartesian law restarted on the pose it is at, every axis
        under position control: the arm comes to rest there, and what a force
        axis pressed with goes to zero as the arm holds its place.
        ``learned``: the law's integral goes on (else from nought)."""
        from redistro.control.cartesian import TaskFrameCommand, matrix_to_rotvec

        q = st.views["q"].astype(np.float64)
        kin = st.model.kinematics(q)
        pose = np.concatenate([kin.p, matrix_to_rotvec(kin.R)])
        none = np.zeros(6)
        cmd = TaskFrameCommand(pose, none, none, "world")
        move_gains(st.law.gains, st.gains_cfg, HOLD_K)  # (stiffer than a move's: it stands)
        integral = st.law.integral.copy() if learned else np.zeros_like(st.law.integral)
        st.law.start(cmd, kin.p, kin.R, HOLD_S, q, integral)
        st.follow = st.holder = None
        st.search = None
        st.short_move = True
        v = st.views
        v["goal"][...] = pose[:3]
        v["goal_rot"][...] = pose[3:]
        v["wrench_goal"][...] = 0.0
        v["selection"][...] = 0
        st.plan["scheme"] = SCHEMES["position"]

    def _resume(self, t: float) -> None:
        w = self.w
        self.paused = False
        for i, st in enumerate(w.states):
            st.plan["paused"] = 0
            if self.by_law[i]:  # (a robot that holds in the segment: where it is now)
                st.hold_q[...] = st.views["q"]
                st.pid.reset()
                self.by_law[i] = False
        w.carry = None  # (a carry re-planned from the hands' measured poses)
        w.post(f"operator resume at t={t:.2f} s after {self.since:.2f} s: the segment re-planned")
        w._begin(w.k, t)

    def hold(self, i: int, st: RobotState, dt: float, t: float) -> None:
        """A paused robot's law: its Cartesian law on the pose it stopped at
        (or jogs to), or the joint PID holding it."""
        jog = self.jog
        jogging = jog is not None and jog[0] == i
        if jogging and jog is not None and jog[1] < 0:  # (the jog's clock starts now)
            jog = self.jog = (i, t, jog[2])
        if self.by_law[i]:
            v = st.views
            q = v["q"]
            law = st.law
            st.model.terms_into(q, law.J, law.R, law.t, law.M, law.g)
            law.q[...] = q
            law.qd[...] = v["qd"]
            law.wrench[...] = v["wrench"]
            law_t, still = (
                (t - jog[1], jog[2]) if jogging and jog is not None else (self.since, HOLD_S)
            )
            # (its integral learns once the reference stands still, out of contact)
            law.update(law_t, dt, law_t, self.free[i] and not self.stopping and law_t >= still)
            st.to_records()
            v["q_cmd"][...] = q
        else:
            self.w._hold(st, dt)
        if jogging and jog is not None and t - jog[1] >= jog[2]:
            self._jogged(st, t, jog[2])

    def _jogged(self, st: RobotState, t: float, length: float) -> None:
        """A jog's move is over: answered once the arm is at rest (or later than that)."""
        if t - self.jog_end < JOG_SETTLE_S:
            return
        if float(np.abs(st.views["qd"]).max()) > REST_RAD_S and t - self.jog_end < REST_WAIT_S:
            return
        self.jog = None
        self._answer(self.seen, Command.JOG, Status.DONE)
        step = self.rec.array["step"]
        self.w.post(
            f"operator jog of {st.name} done at t={t:.2f} s: "
            f"({step[0] * 1e3:.2f}, {step[1] * 1e3:.2f}, {step[2] * 1e3:.2f}) mm in "
            f"{length:.2f} s"
        )

    # -- Idle --

    def idle(self) -> bool:
        """One slice of a jog's planning; whether there is more."""
        if self.planning is None:
            return False
        try:
            next(self.planning)
        except StopIteration:
            self.planning = None
            return False
        return True

    def _plan(self, i: int, step: np.ndarray[Any, Any]) -> Iterator[None]:
        """The jog's posture (in slices), checked; then the jog is set to start."""
        from redistro.control.cartesian import matrix_to_rotvec, rotvec_to_matrix

        w = self.w
        st = w.states[i]
        q = st.views["q"].astype(np.float64)  # (at rest)
        # the step moves the pose the robot holds, not one sample of where
        # it is (a joint PID's hold wanders within its torque's quantum)
        if self.by_law[i]:
            p_hold, R_hold = st.views["goal"].copy(), rotvec_to_matrix(st.views["goal_rot"])
        else:
            held = st.model.kinematics(st.hold_q.astype(np.float64))
            p_hold, R_hold = held.p, held.R
        p_goal = p_hold + step[:3]
        R_goal = rotvec_to_matrix(step[3:]) @ R_hold
        reached = False
        for k in range(IK_ITERATIONS):
            if k % IK_PER_SLICE == IK_PER_SLICE - 1:
                yield
            kin = st.model.kinematics(q)
            e = np.concatenate([p_goal - kin.p, kin.R @ matrix_to_rotvec(kin.R.T @ R_goal)])
            if np.linalg.norm(e[:3]) < IK_POS_M and np.linalg.norm(e[3:]) < IK_ROT_RAD:
                reached = True
                break
            J = kin.J
            q = q + J.T @ np.linalg.solve(J @ J.T + 1e-6 * np.eye(6), e)
        if not reached:
            self._refuse(Status.UNREACHED, st.name, "no posture reaches the step")
            return
        why = self.limits.outside(q)
        if why:
            self._refuse(Status.LIMITS, st.name, why)
            return
        yield
        qs = {s.name: (q if s is st else s.hold_q.astype(np.float64)) for s in w.states}
        near = w.watch.group.closest(qs)
        if near.distance_m < MIN_CLEARANCE_M:
            where = f"{near.links[0]} and {near.links[1]} {near.distance_m * 100:.1f} cm apart"
            self._refuse(Status.CLEARANCE, st.name, where)
            return
        moved = float(np.linalg.norm(step[:3]))
        turned = float(np.linalg.norm(step[3:]))
        length = max(QUINTIC_PEAK * moved / JOG_M_S, QUINTIC_PEAK * turned / JOG_RAD_S, JOG_MIN_S)
        if not self.by_law[i]:  # (held by the joint PID: its law takes over, where it is)
            self._hold_here(st)
            self.by_law[i] = True
        from redistro.control.cartesian import TaskFrameCommand

        none = np.zeros(6)
        goal = np.concatenate([p_goal, matrix_to_rotvec(R_goal)])
        start = st.model.kinematics(st.views["q"].astype(np.float64))
        st.law.start(TaskFrameCommand(goal, none, none, "world"), start.p, start.R, length, q,
                     st.law.integral.copy())  # fmt: skip
        st.views["goal"][...] = goal[:3]
        st.views["goal_rot"][...] = goal[3:]
        self.jog = (i, -1.0, length)  # (its clock starts at the next cycle)
        self.jog_end = w.last_t + length

    def _refuse(self, status: Status, robot: str, why: str) -> None:
        self._answer(self.seen, Command.JOG, status, f"{robot} refused: {why}")

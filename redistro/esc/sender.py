"""ESC Command Sender & Safety Guard (paper priority 18).

Before every command it checks, in this order: the feedback is finite; joint
speeds, measured joint torques and the wrist force and moment are within the
limits of ``esc.safety``; every joint is inside its position limits less the
margin, and can stop inside them at the configured deceleration
(q + qd|qd| / 2a; redistro/config/limits.py), or, resting outside them (a
session that ended there, an arm moved while powered off), is moving back
toward them no faster than ``recovery_qd_rad_s`` (and not further out than
``RECOVERY_DRIFT_RAD_S``, the speed a measurement reads at rest): a robot
can always be brought back; the command is finite and its torques within
limits. (NaN passes every ``>`` test: finiteness is checked first.) A
violation freezes the robot at once through the sender's own driver, records
what tripped in the guard block (the manager ends the session ``unsafe``),
and the sender sends nothing more. Otherwise it releases the brakes of joints
that came under control, engages those of joints that left it, and writes
the torques.

Its commands come from the ESC's own pid (``control`` block; self-calibration
and positioning), or, in a strategy session, from the SSC (``command``
block, written by the ddm): then the robot stays frozen until the first
command arrives, every command sent adds one to the starving index
(``starving_sent``; the ddm pays it back when a fresh command arrives), and
a command with the session finished engages every brake.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from typing import Any

import numpy as np

from redistro import kernels
from redistro.config.limits import joint_limits
from redistro.esc import guard_layout
from redistro.esc.common import EscContext, plant_session
from redistro.localdata.block import Record
from redistro.localdata.layout import (
    COMMAND,
    CONTROL,
    COUNTER,
    FEEDBACK,
    GUARD,
    HOME,
    MANAGER,
    SessionStatus,
)
from redistro.process.worker import Worker

DOF = 7
TRACE_CYCLES = 400  # the cycles kept for the trace written when the guard trips
# a joint outside its limits (less the margin) that moves further out faster
# than this is refused: what the tachometers read of a joint at rest
RECOVERY_DRIFT_RAD_S = 0.02


class Violation(Exception):
    def __init__(self, quantity: str, joint: int, value: float, limit: float, unit: str) -> None:
        where = "wrist" if joint < 0 else f"joint {joint + 1}"
        if unit:
            super().__init__(
                f"{where} {quantity} {value:.4g} {unit} over the limit {limit:.4g} {unit}"
            )
        else:  # a value that is no number at all
            super().__init__(f"{where} {quantity} ({value})")
        self.quantity = quantity
        self.joint = joint
        self.value = value
        self.limit = limit


def check(
    q: np.ndarray,
    qd: np.ndarray,
    tau: np.ndarray,
    wrench: np.ndarray,
    tau_cmd: np.ndarray,
    qd_max: np.ndarray,
    tau_max: np.ndarray,
    force_max: float,
    moment_max: float,
    q_lo: np.ndarray | None = None,
    q_hi: np.ndarray | None = None,
    stop_k: np.ndarray | None = None,
    recovery_qd: float = 0.0,
) -> None:
    """Raise Violation naming the first limit broken (pure; unit-tested).

    q_lo, q_hi: position limits less the margin [rad]; stop_k: per joint
    1 / (2 deceleration) [s^2/rad], the stopping distance is qd|qd| stop_k;
    recovery_qd: a joint outside [q_lo, q_hi] may move back toward them at
    this speed at most [rad/s] (0: never), and no faster than
    RECOVERY_DRIFT_RAD_S further out."""
    for name, v in (
        ("position", q),
        ("velocity", qd),
        ("torque", tau),
    ):
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            j = int(bad[0])
            raise Violation(f"measured {name} not finite", j, float(v[j]), 0.0, "")
    if not np.all(np.isfinite(wrench)):
        raise Violation("wrench not finite", -1, float("nan"), 0.0, "")
    over = np.flatnonzero(np.abs(qd) > qd_max)
    if over.size:
        j = int(over[0])
        raise Violation("velocity", j, float(qd[j]), float(qd_max[j]), "rad/s")
    over = np.flatnonzero(np.abs(tau) > tau_max)
    if over.size:
        j = int(over[0])
        raise Violation("measured torque", j, float(tau[j]), float(tau_max[j]), "N m")
    f = float(np.linalg.norm(wrench[:3]))
    if f > force_max:
        raise Violation("force", -1, f, force_max, "N")
    m = float(np.linalg.norm(wrench[3:]))
    if m > moment_max:
        raise Violation("moment", -1, m, moment_max, "N m")
    if q_lo is not None and q_hi is not None and stop_k is not None:
        for j in range(len(q)):
            if q[j] > q_hi[j]:
                if recovery_qd > 0 and -recovery_qd <= qd[j] <= RECOVERY_DRIFT_RAD_S:
                    continue  # on its way back (or at rest): recovering
                raise Violation("position", j, float(q[j]), float(q_hi[j]), "rad")
            if q[j] < q_lo[j]:
                if recovery_qd > 0 and -RECOVERY_DRIFT_RAD_S <= qd[j] <= recovery_qd:
                    continue
                raise Violation("position", j, float(q[j]), float(q_lo[j]), "rad")
            stop = float(q[j] + qd[j] * abs(qd[j]) * stop_k[j])
            if stop > q_hi[j]:
                raise Violation("stopping position", j, stop, float(q_hi[j]), "rad")
            if stop < q_lo[j]:
                raise Violation("stopping position", j, stop, float(q_lo[j]), "rad")
    bad = np.flatnonzero(~np.isfinite(tau_cmd))
    if bad.size:
        j = int(bad[0])
        raise Violation("commanded torque not finite", j, float(tau_cmd[j]), 0.0, "")
    over = np.flatnonzero(np.abs(tau_cmd) > tau_max)
    if over.size:
        j = int(over[0])
        raise Violation("commanded torque", j, float(tau_cmd[j]), float(tau_max[j]), "N m")


def screen(
    fb: Any,
    src: Any,
    finished: bool,
    step: int,
    lim: Any,
    on: np.ndarray[Any, Any],
    released: np.ndarray[Any, Any],
    tau: np.ndarray[Any, Any],
    trace: np.ndarray[Any, Any],
    at: np.ndarray[Any, Any],
) -> int:
    """The guard's screen of one command (the reference of the
    ``guard_prepare`` kernel, esc/guard_kernel.c): the joints on and their
    torques (``on``, ``tau``; none once the session is ``finished``), a
    trace row (TRACE_ROW: the cycle ``at["cycle"]``, the boards' ``step``),
    and the flags: bit 1 a figure not finite or over its limit in ``lim``
    (LIMITS, esc/guard_layout.py; :func:`check` names which), bit 2 the
    joints on differ from ``released``."""
    on[...] = (src["joint_on"] != 0) & (not finished)
    tau[...] = np.where(on, src["tau_nm"], 0.0)
    row = trace[int(at["rows"]) % len(trace)]
    at["rows"] += 1
    q, qd = fb["q_rad"], fb["qd_rad_s"]
    row["cycle"], row["step"] = at["cycle"], step
    row["q"], row["qd"], row["tau"], row["tau_cmd"] = q, qd, fb["tau_nm"], tau
    measured = np.concatenate([q, qd, fb["tau_nm"], tau, fb["wrench"]])
    stop = q + qd * np.abs(qd) * lim["stop_k"]
    flags = 0
    if (
        not np.isfinite(measured).all()
        or (q < lim["q_lo"]).any()
        or (q > lim["q_hi"]).any()
        or (stop < lim["q_lo"]).any()
        or (stop > lim["q_hi"]).any()
        or (np.abs(qd) > lim["qd_max"]).any()
        or (np.abs(fb["tau_nm"]) > lim["tau_max"]).any()
        or (np.abs(tau) > lim["tau_max"]).any()
        or _norm3(fb["wrench"][:3]) > lim["force_max"]
        or _norm3(fb["wrench"][3:]) > lim["moment_max"]
    ):
        flags |= 1
    if (on != released).any():
        flags |= 2
    return flags


def _norm3(v: Any) -> float:
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    return math.sqrt(x * x + y * y + z * z)  # (as the kernel sums: bit for bit)


class Sender(Worker):
    def initialize(self) -> None:
        ctx = EscContext.load(self.spec)
        self.robot = ctx.robot
        lim = ctx.cfg.esc.safety
        self.qd_max = np.asarray(lim.qd_max_rad_s, dtype=np.float64)
        self.tau_max = np.asarray(lim.tau_max_nm, dtype=np.float64)
        self.force_max = lim.force_max_n
        self.moment_max = lim.moment_max_nm
        jl = joint_limits(ctx.cfg)
        self.q_lo, self.q_hi = jl.inner_lower, jl.inner_upper
        self.stop_k = 1.0 / (2.0 * jl.decel)
        self.recovery_qd = lim.recovery_qd_rad_s
        self.driver = ctx.driver(plant_session(self.spec))
        self.driver.open(owner=False)  # the manager froze the robot before we existed
        ld = self.ld
        self.guard_block = ld.writer("guard", 0, role="sender")
        self.feedback_block = ld.block("feedback", 0)
        self.home_block = ld.block("home", 0)
        self.from_ssc = self.spec.node_params.from_ssc
        if self.from_ssc:
            self.command_block = ld.block("command", 0)
            self.cmd = Record(COMMAND)
            self.sent_block = ld.writer("starving_sent", role="sender")
            self.stamp_block = ld.writer("command_stamp", role="sender")
            self.sent = Record(COUNTER)
            self.stamp = Record(COUNTER)
        else:
            self.control_block = ld.block("control", 0)
            self.ctl = Record(CONTROL)
        # the gripper follows the SSC's command (one comparison a cycle; the
        # DIO write only when it changes); open at power-on
        self.gripper = self.from_ssc and ctx.hw.gripper is not None
        self.gripper_closed = 0
        self.manager_block = ld.block("manager")
        self.fb = Record(FEEDBACK)
        self.home = Record(HOME)
        self.mgr = Record(MANAGER)
        self.guard = Record(GUARD)
        self.released = np.zeros(DOF, dtype=bool)
        self.tripped = False
        self.on = np.zeros(DOF, dtype=bool)
        self.tau_cmd = self.driver.tau_cmd  # what the driver sends
        self.guard_tau = self.guard.array["tau_nm"]
        # the last cycles as the guard saw them, written out if it trips:
        # per row cycle, board step, q, qd, tau (measured), tau commanded
        self.trace = np.zeros(TRACE_CYCLES, guard_layout.TRACE_ROW)
        self.trace_at = np.zeros((), guard_layout.TRACE_AT)  # rows written, this cycle
        self.cycle_now = self.trace_at["cycle"]
        run_dir = os.path.dirname(self.spec.messages_path)
        self.trace_path = os.path.join(run_dir, f"trip-{self.robot}.json") if run_dir else ""
        self._plan_screen()
        self._prepare: Any = self._prepare_numpy
        if kernels.AVAILABLE:
            plan = kernels.plan("guard_prepare", **self._prepare_args)
            run = kernels.KERNELS.guard_prepare
            self._prepare = lambda: run(plan)

    def _plan_screen(self) -> None:
        """The guard's screen: the command prepared (joints on, their
        torques) and every figure against its limit in one kernel call;
        anything it flags is checked again by check(), which names the
        first limit broken. Its buffers (esc/guard_layout.py)."""
        src = self.cmd if self.from_ssc else self.ctl
        fields = src.array.dtype.fields
        assert fields is not None
        fbf, homef = FEEDBACK.fields, HOME.fields
        assert fbf is not None and homef is not None
        gl = self.guard_limits = np.zeros((), guard_layout.LIMITS)
        gl["qd_max"], gl["tau_max"] = self.qd_max, self.tau_max
        gl["force_max"], gl["moment_max"] = self.force_max, self.moment_max
        gl["q_lo"], gl["q_hi"], gl["stop_k"] = self.q_lo, self.q_hi, self.stop_k
        fb_off = np.zeros((), guard_layout.FB_OFF)
        for name, field in (
            ("q", "q_rad"),
            ("qd", "qd_rad_s"),
            ("tau", "tau_nm"),
            ("wrench", "wrench"),
        ):
            fb_off[name] = fbf[field][1]
        src_off = np.zeros((), guard_layout.SRC_OFF)
        src_off["tau"], src_off["joint_on"] = fields["tau_nm"][1], fields["joint_on"][1]
        src_off["session_status"] = (
            fields["session_status"][1] if "session_status" in fields else -1
        )
        home_off = np.zeros((), guard_layout.HOME_OFF)
        home_off["step"] = homef["step"][1]
        self._prepare_args = {
            "fb": self.fb.array.reshape(1).view(np.uint8),
            "fb_off": fb_off,
            "src": src.array.reshape(1).view(np.uint8),
            "src_off": src_off,
            "home": self.home.array.reshape(1).view(np.uint8),
            "home_off": home_off,
            "limits": gl,
            "on": self.on,
            "released": self.released,
            "tau": self.tau_cmd,
            "trace": self.trace,
            "trace_at": self.trace_at,
        }

    def step(self, cycle: int) -> None:
        self.manager_block.read_into(self.mgr.bytes)
        if self.tripped or self.mgr["estop"]:
            return  # frozen: nothing goes out any more
        self.feedback_block.read_into(self.fb.bytes)
        if self.from_ssc:
            self.command_block.read_into(self.cmd.bytes)
            if self.cmd["seq_src"] == 0:
                return  # no command yet: the robot stays frozen
        else:
            self.control_block.read_into(self.ctl.bytes)
        self.home_block.read_into(self.home.bytes)
        self.cycle_now[...] = cycle
        flags = self._prepare()
        on, tau_cmd = self.on, self.tau_cmd
        self.guard["cycle"] = cycle
        if flags & 1:
            fb = self.fb.array
            try:
                check(
                    fb["q_rad"],
                    fb["qd_rad_s"],
                    fb["tau_nm"],
                    fb["wrench"],
                    tau_cmd,
                    self.qd_max,
                    self.tau_max,
                    self.force_max,
                    self.moment_max,
                    self.q_lo,
                    self.q_hi,
                    self.stop_k,
                    self.recovery_qd,
                )
            except Violation as v:
                self._trip(cycle, v)
                return
        # brakes on before a joint's torque goes to zero; its torque out
        # before its brake comes off (the amplifier is inhibited while braked)
        up: list[int] = []
        if flags & 2:
            up = np.flatnonzero(on & ~self.released).tolist()
            down = np.flatnonzero(~on & self.released).tolist()
            if down:
                self.driver.engage_brakes(down)
            self.released[...] = on
            self.guard.array["released"] = on
        self.driver.send()
        if up:
            self.driver.release_brakes(up)
        self.guard["sent_cycle"] = cycle
        self.guard_tau[...] = tau_cmd
        self.guard_block.publish(self.guard.bytes)
        if self.gripper and int(self.cmd["gripper"]) != self.gripper_closed:
            self.gripper_closed = int(self.cmd["gripper"])
            self.driver.set_gripper(bool(self.gripper_closed))
        if self.from_ssc:
            now = time.monotonic_ns()
            self.sent["count"] += 1
            self.sent["stamp_ns"] = now
            self.sent_block.publish(self.sent.bytes)
            self.stamp["count"] = self.cmd["seq_src"]
            self.stamp["stamp_ns"] = self.cmd["stamp_ns"]
            self.stamp_block.publish(self.stamp.bytes)

    def _prepare_numpy(self) -> int:
        """The arithmetic of the ``guard_prepare`` kernel: :func:`screen`."""
        src = self.cmd.array if self.from_ssc else self.ctl.array
        finished = self.from_ssc and int(src["session_status"]) == SessionStatus.FINISHED
        return screen(
            self.fb.array, src, finished, int(self.home["step"]), self.guard_limits,
            self.on, self.released, self.tau_cmd, self.trace, self.trace_at,
        )  # fmt: skip

    def _trip(self, cycle: int, v: Violation) -> None:
        self.driver.freeze()
        frozen_ns = time.monotonic_ns()
        self.tripped = True
        text = f"{self.robot} {v}"
        g = self.guard
        g["tripped"] = 1
        g["trip_cycle"] = cycle
        g["trip_step"] = self.home["step"]
        g["trip_ns"] = frozen_ns
        g["trip_joint"] = v.joint
        g["trip_value"] = v.value
        g["trip_limit"] = v.limit
        g.array["trip_quantity"] = v.quantity.encode()[:24]
        g.array["trip_text"] = text.encode()[:112]
        g.array["released"] = 0
        g.array["tau_nm"] = 0.0
        self.guard_block.publish(g.bytes)
        self.wake_manager = True  # the manager ends the session now, not next tick
        self.post(f"unsafe: {text}; robot frozen", logging.ERROR)
        # the trace is written at Cleanup, off real-time priority: here it
        # would hold the CPUs (and the simulated plant) right after a trip

    def _write_trace(self) -> None:
        """The last cycles before the trip, oldest first, as JSON columns."""
        if not self.trace_path:
            return
        traced = int(self.trace_at["rows"])
        n = min(traced, TRACE_CYCLES)
        start = traced - n
        rows = self.trace[np.arange(start, traced) % TRACE_CYCLES]
        doc = {
            "cycle": rows["cycle"].astype(np.int64).tolist(),
            "step": rows["step"].astype(np.int64).tolist(),
            "q_rad": rows["q"].tolist(),
            "qd_rad_s": rows["qd"].tolist(),
            "tau_nm": rows["tau"].tolist(),
            "tau_cmd_nm": rows["tau_cmd"].tolist(),
        }
        try:
            from redistro import files

            with files.writing(self.trace_path) as f:
                json.dump({"robot": self.robot, "cycles": n, **doc}, f)
            self.post(f"the last {n} cycles before the trip: {self.trace_path}")
        except OSError as exc:
            self.post(f"trip trace not written: {exc}", logging.WARNING)

    def cleanup(self) -> None:
        if self.tripped:
            self._write_trace()
        self.driver.close()

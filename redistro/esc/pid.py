"""ESC PID Computation (paper priority 16): joint PID with gravity compensation.

Tracks the setpoint block (the calibration's joint reference) from this
cycle's feedback; gravity g(q) from Pinocchio on the plant's own arm model.
Publishes the torques in the control block for the sender.
"""

from __future__ import annotations

import numpy as np

from redistro.control.dynamics import ArmModel
from redistro.control.pid import PidGains, PidLoop, PidState
from redistro.esc.common import EscContext
from redistro.localdata.block import Record
from redistro.localdata.layout import CONTROL, FEEDBACK, HOME, SETPOINT
from redistro.process.worker import Worker
from redistro.robotmodel import Peg


class Pid(Worker):
    def initialize(self) -> None:
        ctx = EscContext.load(self.spec)
        cfg = ctx.cfg
        g = cfg.esc.pid
        self.gains = PidGains(
            np.asarray(g.kp, dtype=np.float64),
            np.asarray(g.ki, dtype=np.float64),
            np.asarray(g.kd, dtype=np.float64),
            np.asarray(g.i_max_nm, dtype=np.float64),
        )
        peg = None
        if cfg.robots[ctx.robot].peg:
            p = cfg.workcell.peg
            peg = Peg(p.side_m, p.length_m, p.mass_kg)
        self.model = ArmModel(peg)
        self.state = PidState()
        ld = self.ld
        self.control_block = ld.writer("control", 0, role="pid")
        self.feedback_block = ld.block("feedback", 0)
        self.setpoint_block = ld.block("setpoint", 0)
        self.fb = Record(FEEDBACK)
        self.sp = Record(SETPOINT)
        self.out = Record(CONTROL)
        self.home_block = ld.block("home", 0)
        self.home = Record(HOME)
        self.sample_s = 1.0 / cfg.plant.physics_hz
        self.last_step = -1
        # field views, made once (the cycle works in place)
        fb, sp, o = self.fb.array, self.sp.array, self.out.array
        self.q, self.qd = fb["q_rad"], fb["qd_rad_s"]
        self.q_ref, self.qd_ref = sp["q_rad"], sp["qd_rad_s"]
        self.sp_on = sp["joint_on"].view(np.bool_)
        self.on = o["joint_on"].view(np.bool_)
        self.tau = o["tau_nm"]
        self.g = np.zeros(7)
        self.loop = PidLoop(
            self.gains,
            self.state,
            self.q,
            self.qd,
            self.q_ref,
            self.qd_ref,
            self.g,
            self.on,
            self.tau,
        )

    def step(self, cycle: int) -> None:
        self.feedback_block.read_into(self.fb.bytes)
        self.setpoint_block.read_into(self.sp.bytes)
        self.home_block.read_into(self.home.bytes)
        # the integral advances by the time between the samples (boards' clock)
        step = self.home["step"]
        dt = (step - self.last_step) * self.sample_s if self.last_step >= 0 else 0.0
        self.last_step = step
        on = self.on
        if self.sp["cycle"] == 0:
            on[:] = False  # no reference yet
        else:
            on[...] = self.sp_on
        self.model.gravity_into(self.q, self.g)
        self.loop.update(min(max(dt, 0.0), 10 * self.period_ns / 1e9))
        self.out["stamp_ns"] = self.due_ns
        self.out["cycle"] = cycle
        self.control_block.publish(self.out.bytes)

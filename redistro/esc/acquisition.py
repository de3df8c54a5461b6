"""ESC Data Acquisition (paper priority 19): the boards -> feedback in Local Data.

Every cycle it reads the robot through its own driver and publishes the
feedback block (q, qd, joint torque, wrist wrench) and the home block (home
switches, the encoder latches taken on their edges). When the calibration
asks for zero offsets (``setpoint.offset_seq`` changed) it takes them out of
every position from that cycle on and says so in ``home.offset_seq``.
"""

from __future__ import annotations

import numpy as np

from redistro.esc.common import EscContext, plant_session
from redistro.localdata.block import Record
from redistro.localdata.layout import FEEDBACK, HOME, SETPOINT
from redistro.process.worker import Worker


class Acquisition(Worker):
    def initialize(self) -> None:
        ctx = EscContext.load(self.params)
        self.driver = ctx.driver(plant_session(self.spec))
        self.driver.open(owner=False)  # the manager froze the robot before we existed
        self.driver.jump_limit_rad_s = ctx.cfg.esc.safety.encoder_jump_rad_s
        ld = self.ld
        self.feedback_block = ld.writer("feedback", 0, role="acquisition")
        self.home_block = ld.writer("home", 0, role="acquisition")
        self.setpoint_block = ld.block("setpoint", 0)
        self.fb = Record(FEEDBACK)
        self.home = Record(HOME)
        self.sp = Record(SETPOINT)
        self.offset = np.zeros(7)
        self.offset_seq = 0
        self.samples = 0

    def step(self, cycle: int) -> None:
        self.setpoint_block.read_into(self.sp.bytes)
        seq = self.sp["offset_seq"]
        if seq != self.offset_seq:
            new = self.sp.array["offset_rad"].copy()
            self.driver.shift_zero(new - self.offset)
            self.offset = new
            self.offset_seq = seq
            self.post(f"zero offsets applied (request {seq})")
        fb = self.driver.read_feedback()
        self.samples += 1
        a = self.fb.array
        a["stamp_ns"] = fb.stamp_ns
        a["seq_src"] = self.samples
        a["q_rad"] = fb.q_rad
        a["qd_rad_s"] = fb.qd_rad_s
        a["tau_nm"] = fb.tau_nm
        a["wrench"] = fb.wrench
        a["step"] = fb.step
        self.feedback_block.publish(self.fb.bytes)
        h = self.home.array
        h["stamp_ns"] = fb.stamp_ns
        h["step"] = fb.step
        h["home_switch"] = fb.home
        h["latch_count"] = fb.latch_count
        h["latch_edge"] = fb.latch_edge
        h["latch_q_rad"] = fb.latch_q_rad
        h["offset_rad"] = self.offset
        h["offset_seq"] = self.offset_seq
        self.home_block.publish(self.home.bytes)

    def cleanup(self) -> None:
        self.driver.close()

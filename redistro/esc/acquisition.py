"""ESC Data Acquisition (paper priority 19): the boards -> feedback in Local Data.

Every cycle it reads the robot through its own driver and publishes the
feedback block (q, qd, joint torque, wrist wrench) and the home block (home
switches, the encoder latches taken on their edges). When the calibration
asks for zero offsets (``setpoint.offset_seq`` changed) it takes them out of
every position from that cycle on and says so in ``home.offset_seq``.
"""

from __future__ import annotations

import numpy as np

from redistro import kernels
from redistro.esc.common import EscContext, plant_session
from redistro.localdata.block import Record
from redistro.localdata.layout import EXCHANGE, FEEDBACK, HOME, SETPOINT
from redistro.process.worker import Worker


class Acquisition(Worker):
    def initialize(self) -> None:
        ctx = EscContext.load(self.spec)
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
        self.calibrating = self.spec.node_params.calibrates
        self.to_ddm = self.spec.node_params.from_ssc  # a strategy session: a ddm
        if self.to_ddm:
            self.exchange_block = self.ld.block("exchange", 0)
            self.exchange = Record(EXCHANGE)
        # the driver's decoded figures -> the two records, one table each
        fb_fields = {
            "stamp_ns": "stamp_ns",
            "q": "q_rad",
            "qd": "qd_rad_s",
            "tau": "tau_nm",
            "wrench": "wrench",
            "step": "step",
        }
        home_fields = {
            "stamp_ns": "stamp_ns",
            "step": "step",
            "home": "home_switch",
            "latch_count": "latch_count",
            "latch_edge": "latch_edge",
            "latch_q": "latch_q_rad",
        }
        self._to_fb = kernels.copier(self.driver.arena, self.fb.array, fb_fields)
        self._to_home = kernels.copier(self.driver.arena, self.home.array, home_fields)

    def step(self, cycle: int) -> None:
        if self.calibrating:  # only a self-calibration asks for zero offsets
            self.setpoint_block.read_into(self.sp.bytes)
            seq = self.sp["offset_seq"]
            if seq != self.offset_seq:
                new = self.sp.array["offset_rad"].copy()
                self.driver.shift_zero(new - self.offset)
                self.offset = new
                self.offset_seq = seq
                h = self.home.array
                h["offset_rad"] = new
                h["offset_seq"] = seq
                self.post(f"zero offsets applied (request {seq})")
        self.driver.sample()
        self.samples += 1
        self._to_fb()
        self.fb["seq_src"] = self.samples
        self.feedback_block.publish(self.fb.bytes)
        if self.to_ddm:
            self.exchange_block.read_into(self.exchange.bytes)
            if self.exchange["feedback_wanted"]:
                self.wake_ddm()  # a new sample for the group
        self._to_home()
        self.home_block.publish(self.home.bytes)

    def cleanup(self) -> None:
        self.driver.close()

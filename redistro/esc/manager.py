"""The ESC Manager: the node's timer and watchdog, and its robot's last line of safety.

Before any worker exists it opens the robot-level driver and freezes the
robot, then presets the encoder counters from the positions file (when it is
valid) and marks that file unclean until the session ends. Every tick it
looks at the guard (a tripped sender ends the session ``unsafe``) and at the
segments (done ends it ``ok``; failed ends it ``abnormal``). On any fault and
on every exit path it freezes the robot through its own driver, before and
after the workers end. At the end it records the final joint positions:
clean when they were known at the start or the self-calibration corrected
them.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from redistro.ddm.exchange import exchange_report
from redistro.drivers import positions
from redistro.drivers.io.bank import PlantWatch
from redistro.drivers.robot import RobotDriver
from redistro.errors import NodeFault
from redistro.esc.common import EscContext, plant_session
from redistro.localdata.block import Block, Record
from redistro.localdata.layout import COMMAND, COUNTER, GUARD, SETPOINT, SessionStatus
from redistro.process.manager import Manager, wait_in_start
from redistro.process.result import EscResult
from redistro.process.spec import NodeSpec

log = logging.getLogger(__name__)

# How long a node waits for the plant it drives to come up (the plant's own
# start-up bound: PlantProcess.start's).
PLANT_START_S = 30.0


class EscManager(Manager):
    def __init__(self, spec: NodeSpec, spec_path: str) -> None:
        super().__init__(spec, spec_path)
        self.robot = spec.robots[0] if spec.robots else ""
        self.driver: RobotDriver | None = None
        self.frozen_ns: list[int] = []
        self.refused = False
        self.calibrating = False
        self.known_at_start = False
        self.positions_note = ""
        self.positions_path = ""
        self.blocks: dict[str, Block] = {}

    def initialize(self) -> None:
        params = self.spec.node_params
        self.ctx = EscContext.load(self.spec)
        self.robot = self.ctx.robot
        self.positions_path = params.positions_file
        self.calibrating = params.calibrates
        self.from_ssc = params.from_ssc
        ld = self.ld
        assert ld is not None
        self.blocks = {
            n: ld.block(n, 0)
            for n in ("guard", "setpoint", "home", "calibration", "command", "exchange")
        }
        self.sent_block = ld.block("starving_sent")
        self.delivered_block = ld.block("starving_delivered")
        self.sent = Record(COUNTER)
        self.delivered = Record(COUNTER)
        self.cmd = Record(COMMAND)
        self.starving_limit = self.ctx.cfg.ddm.starving_limit_cycles
        self.wait_first_s = self.ctx.cfg.ddm.connect_timeout_s
        self.starving_max = 0
        self.first_command_cycle = 0
        self.guard_block = self.blocks["guard"]
        self.setpoint_block = self.blocks["setpoint"]
        self.guard = Record(GUARD)
        self.sp = Record(SETPOINT)
        # the plant is started beside the nodes: its start-up overlaps theirs
        plant = PlantWatch(plant_session(self.spec))
        try:
            wait_in_start(self.spec, plant.running, "the plant not running", PLANT_START_S)
        finally:
            plant.close()
        driver = self.ctx.driver(plant_session(self.spec))
        driver.open()  # checks the chassis, then freezes: brakes on, DAC zero
        self.driver = driver
        self._freeze("start")
        if self.positions_path:
            try:
                pos = positions.read(self.positions_path, [self.robot])
                driver.preset_encoders(np.asarray(pos.q_rad[self.robot]))
                self.known_at_start = True
                self.positions_note = f"preset from {self.positions_path} (session {pos.session})"
                # until this session ends cleanly the file does not say where the arm is
                positions.write(self.positions_path, self.spec.session_id, pos.q_rad, clean=False)
            except positions.PositionsUnknown as exc:
                self.positions_note = str(exc)
                if not self.calibrating:
                    self.refused = True
                    raise NodeFault(
                        "abnormal",
                        f"motion refused: {exc}; run a self-calibration first",
                    ) from None
        self._message(
            "manager", logging.INFO, f"{self.robot}: frozen; positions {self.positions_note}"
        )

    def _freeze(self, why: str) -> None:
        if self.driver is None:
            return
        try:
            self.driver.freeze()
            self.frozen_ns.append(time.monotonic_ns())
        except Exception as exc:  # the plant may be gone: say so, never mask the exit
            self._message("manager", logging.ERROR, f"freeze ({why}) failed: {exc}")

    def _check_guard(self) -> None:
        self.guard_block.read_into(self.guard.bytes)
        if self.guard["tripped"]:
            text = self.guard.array["trip_text"].item().decode(errors="replace")
            raise NodeFault("unsafe", text)

    def on_wake(self) -> None:
        self._check_guard()

    def on_tick(self, cycle: int) -> bool:
        self._check_guard()
        if self.from_ssc:
            return self._check_commands(cycle)
        self.setpoint_block.read_into(self.sp.bytes)
        if self.sp["failed"]:
            self._drain_messages()
            why = self.last_error.get("calibration", "the segments cannot go on (see messages)")
            raise NodeFault("abnormal", f"{self.robot}: {why}")
        return bool(self.sp["done"])

    def _check_commands(self, cycle: int) -> bool:
        """Strategy sessions: the SSC's commands must keep coming (starving
        index within its limit); a finished session ends the node."""
        self.blocks["command"].read_into(self.cmd.bytes)
        if int(self.cmd["seq_src"]) == 0:
            if cycle > self.wait_first_s * self.spec.rate_hz:
                raise NodeFault(
                    "starving",
                    f"{self.robot}: no command from the SSC within {self.wait_first_s} s",
                )
            return False
        if not self.first_command_cycle:
            self.first_command_cycle = cycle
        if int(self.cmd["session_status"]) == SessionStatus.FINISHED:
            return True
        self.sent_block.read_into(self.sent.bytes)
        self.delivered_block.read_into(self.delivered.bytes)
        index = int(self.sent["count"]) - int(self.delivered["count"])
        self.starving_max = max(self.starving_max, index)
        if index > self.starving_limit:
            raise NodeFault(
                "starving",
                f"{self.robot}: starving index {index} over the limit {self.starving_limit} "
                f"(no fresh command for {index} cycles) at cycle {cycle}",
            )
        return False

    def on_fault(self, reason: str, message: str) -> None:
        self._freeze(reason)

    def before_end(self) -> None:
        self._freeze("end")

    def cleanup(self) -> None:
        self._freeze("end, workers gone")
        esc = self.result.esc = EscResult(robot=self.robot)
        if not self.blocks:  # initialization failed early
            if self.driver is not None:
                self.driver.close()
            return
        home = self.blocks["home"].read()
        cal = self.blocks["calibration"].read()
        guard = self.blocks["guard"].read()
        applied = int(home["offset_seq"]) > 0
        offset = np.asarray(home["offset_rad"], dtype=np.float64)
        if self.calibrating:
            esc.calibration = {
                "applied": applied,
                "found": [bool(v) for v in cal["found"]],
                "edges": [int(v) for v in cal["edges"]],
                "offset_found_rad": [float(v) for v in cal["offset_found_rad"]],
            }
        if int(guard["tripped"]):
            esc.violation = {
                "quantity": bytes(guard["trip_quantity"]).decode(),
                "joint": int(guard["trip_joint"]) + 1 if int(guard["trip_joint"]) >= 0 else None,
                "value": float(guard["trip_value"]),
                "limit": float(guard["trip_limit"]),
                "cycle": int(guard["trip_cycle"]),
                "sample_step": int(guard["trip_step"]),
                "frozen_monotonic_ns": int(guard["trip_ns"]),
                "text": bytes(guard["trip_text"]).decode(errors="replace"),
            }
        esc.freeze_monotonic_ns = list(self.frozen_ns)
        if self.from_ssc:
            ex = self.blocks["exchange"].read()
            esc.ddm = exchange_report(ex)
            esc.ddm["starving_index_max"] = self.starving_max
        final = None
        if self.driver is not None:
            try:
                fb = self.driver.read_feedback()
                final = fb.q_rad - offset
            except Exception as exc:
                self._message("manager", logging.ERROR, f"final positions unreadable: {exc}")
        known = self.known_at_start or applied
        esc.positions = {
            "file": self.positions_path,
            "at_start": self.positions_note,
            "known_at_end": bool(known and final is not None),
            "q_rad": [float(v) for v in final] if final is not None else None,
        }
        if self.positions_path and final is not None and not self.refused:
            positions.write(
                self.positions_path, self.spec.session_id, {self.robot: final}, clean=known
            )
        if self.driver is not None:
            self.driver.close()

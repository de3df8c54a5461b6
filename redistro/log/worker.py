"""The ESC-side recorder (ESC-only sessions: self-calibration, positioning).

The last stage of the ESC cycle: it logs the robot's feedback, the joint
reference (setpoint), the PID's torques, what the sender sent (guard) and
the node's timing, plus segment changes and a guard trip as events. A
strategy session is logged by the SSC's logger instead.
"""

from __future__ import annotations

from redistro.esc.common import EscContext
from redistro.localdata.block import Record
from redistro.localdata.layout import GUARD, SETPOINT
from redistro.log.recorder import CycleRecorder, robots_meta
from redistro.process.worker import Worker


class EscRecorder(Worker):
    def initialize(self) -> None:
        ctx = EscContext.load(self.params)
        r = ctx.robot
        self.segments = [str(s["name"]) for s in self.params.get("segments", [])]
        meta = robots_meta(ctx.cfg, [r])
        meta["task"] = str(self.params.get("task_name", ""))
        meta["segments"] = {r: self.segments}
        topics: list[tuple[str, str, int | None]] = [
            (f"/{r}/feedback", "feedback", 0),
            (f"/{r}/setpoint", "setpoint", 0),
            (f"/{r}/control", "control", 0),
            (f"/{r}/guard", "guard", 0),
        ]
        self.robot = r
        self.rec = CycleRecorder(self.ld, self.spec, topics, str(self.params["run_dir"]), meta)
        self.sp_block = self.ld.block("setpoint", 0)
        self.guard_block = self.ld.block("guard", 0)
        self.sp = Record(SETPOINT)
        self.guard = Record(GUARD)
        self.segment = 0
        self.tripped = 0
        self.rec.start()

    def step(self, cycle: int) -> None:
        self.rec.record(cycle, self.due_ns)
        self.sp_block.read_into(self.sp.bytes)
        k = int(self.sp["segment"])
        if k != self.segment:
            self.segment = k
            name = self.segments[k - 1] if 1 <= k <= len(self.segments) else ""
            self.rec.event(
                "segments",
                cycle,
                robot=self.robot,
                segment=k,
                name=name,
                done=bool(self.sp["done"]),
            )
        self.guard_block.read_into(self.guard.bytes)
        if int(self.guard["tripped"]) and not self.tripped:
            self.tripped = 1
            text = bytes(self.guard.array["trip_text"]).decode(errors="replace")
            self.rec.event("events", cycle, event="guard trip", robot=self.robot, text=text)

    def cleanup(self) -> None:
        self.rec.close()

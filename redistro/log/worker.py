"""The ESC-side recorder (ESC-only sessions: self-calibration, positioning).

Off the cycle, on its own timer (``log.drain_hz``), it drains the log ring
the manager fills at every tick and logs the robot's feedback, the joint
reference (setpoint), the PID's torques, what the sender sent (guard) and
the node's timing, plus segment changes and a guard trip as events. A
strategy session is logged by the SSC's logger instead.
"""

from __future__ import annotations

from redistro.localdata.layout import GUARD, SETPOINT
from redistro.log.recorder import CycleRecorder, log_topics, robots_meta
from redistro.process.worker import Worker


class EscRecorder(Worker):
    def initialize(self) -> None:
        r = self.spec.robots[0]
        self.segments = [str(s["name"]) for s in self.spec.node_params.segments]
        meta = robots_meta(self.spec.cfg(), [r])
        meta["task"] = self.spec.node_params.task_name
        meta["segments"] = {r: self.segments}
        topics = log_topics(self.spec)  # the manager captures the same
        self.robot = r
        self.rec = CycleRecorder(self.ld, self.spec, topics, self.spec.node_params.run_dir, meta)
        self.sp = self.rec.view(1, SETPOINT)  # the recorded cycle's, in the frame
        self.guard = self.rec.view(3, GUARD)
        self.segment = 0
        self.tripped = 0
        self.rec.start()

    def step(self, cycle: int) -> None:
        self.rec.drain(self._cycle)

    def _cycle(self, cycle: int) -> None:
        """Segment changes and a guard trip, as events, from a recorded cycle."""
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
        if int(self.guard["tripped"]) and not self.tripped:
            self.tripped = 1
            text = bytes(self.guard.array["trip_text"]).decode(errors="replace")
            self.rec.event("events", cycle, event="guard trip", robot=self.robot, text=text)

    def cleanup(self) -> None:
        self.rec.close(self._cycle)  # (the cycles since the last drain first)

"""The amplifiers' watchdog: a robot whose DAC boards' watchdog registers
(when armed, non-zero) have not moved for the watchdog time has its
amplifiers cut, as real amplifiers do when the controller stops writing."""

from __future__ import annotations

from typing import Any

import numpy as np


class AmplifierWatchdog:
    """The watchdog over a chassis' DAC boards. ``joint_cut``: the joints
    whose amplifiers are cut (a view the kernels hold); ``trips``: each cut,
    robot, step and time."""

    def __init__(
        self, timeout_ns: int, n_boards: int, robot_boards: list[list[int]], n: int
    ) -> None:
        self.timeout_ns = timeout_ns
        self.values = [0] * n_boards  # each DAC board's watchdog register, last seen
        self.moved_ns = [0] * n_boards  # when it last moved
        self.robot_boards = robot_boards  # each robot's DAC boards
        self.joint_cut = np.zeros(n, dtype=bool)
        self.due = 0  # when the earliest armed board's watchdog runs out (0: none armed)
        self.any_cut = False
        self.tripped = [False] * len(robot_boards)
        self.trips: list[dict[str, Any]] = []  # robot, monotonic_ns, step

    def check(self, registers: Any, now_ns: int, rigs: Any, next_step: int) -> bool:
        """True while any robot is cut (``joint_cut`` says which joints).
        Per step it only looks for moved registers (a chassis has a few DAC
        boards: plain ints); the rest runs when the earliest armed board's
        time is up, or while a robot is cut."""
        values = registers.tolist()
        if values != self.values:
            for b, (v, old) in enumerate(zip(values, self.values, strict=True)):
                if v != old:
                    self.moved_ns[b] = now_ns
            self.values = values
            armed = [t for t, v in zip(self.moved_ns, values, strict=True) if v]
            self.due = min(armed) + self.timeout_ns if armed else 0
        if not (self.due and now_ns > self.due) and not self.any_cut:
            return False
        cut = [
            bool(v) and now_ns - t > self.timeout_ns
            for t, v in zip(self.moved_ns, values, strict=True)
        ]
        self.joint_cut[:] = False
        for i, rig in enumerate(rigs):
            tripped = any(cut[b] for b in self.robot_boards[i])
            if tripped and not self.tripped[i] and len(self.trips) < 1000:
                self.trips.append({"robot": rig.name, "step": next_step, "monotonic_ns": now_ns})
            self.tripped[i] = tripped
            self.joint_cut[rig.sl] = tripped
        self.any_cut = any(self.tripped)
        return self.any_cut

"""The benchmark worker: spins for ``work_us`` microseconds each cycle.

params: work_us (busy work per cycle, default 0), message_every (post a message
box line every N cycles, default 0 = never), idle_us (Idle work after each
cycle, in slices of this many µs, never ending: it shows the Idle state
running between cycles and giving way to the next sync; default 0 = none).
"""

from __future__ import annotations

import time

from redistro.process.worker import Worker


class BusyWorker(Worker):
    def initialize(self) -> None:
        self.work_ns = int(float(self.params.get("work_us", 0)) * 1000)
        self.message_every = int(self.params.get("message_every", 0))
        self.idle_ns = int(float(self.params.get("idle_us", 0)) * 1000)

    def wants_idle(self) -> bool:
        return self.idle_ns > 0

    def idle(self, deadline_ns: int) -> bool:
        end = time.monotonic_ns() + self.idle_ns
        while time.monotonic_ns() < end:
            pass
        return True  # always more: the runner stops it at the deadline or the sync

    def step(self, cycle: int) -> None:
        end = time.perf_counter_ns() + self.work_ns
        while time.perf_counter_ns() < end:
            pass
        if self.message_every and cycle % self.message_every == 0:
            self.post(f"cycle {cycle}: {self.work_ns / 1000:.0f} us of work done")

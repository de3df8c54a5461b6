"""The node's interval timer: ITIMER_REAL delivering SIGALRM, taken with sigtimedwait.

The kernel forwards ITIMER_REAL by whole intervals on the monotonic clock, so
tick k is due at ``start_ns + k * period_ns``. SIGALRM does not queue: ticks
that pass while the manager is late are coalesced, and :meth:`IntervalTimer.due`
tells how many were missed.
"""

from __future__ import annotations

import signal
import time


class IntervalTimer:
    def __init__(self, rate_hz: float) -> None:
        # setitimer works in whole microseconds: use the period the kernel will keep.
        period_us = max(1, round(1e6 / rate_hz))
        self.period_ns = period_us * 1000
        self.start_ns = 0
        self._last_k = 0

    @property
    def period_s(self) -> float:
        return self.period_ns / 1e9

    def start(self) -> None:
        period = self.period_ns / 1e9
        self.start_ns = time.monotonic_ns()
        signal.setitimer(signal.ITIMER_REAL, period, period)
        self._last_k = 0

    def stop(self) -> None:
        signal.setitimer(signal.ITIMER_REAL, 0, 0)

    def due(self, now_ns: int) -> tuple[int, int, int]:
        """For a tick taken at ``now_ns``: (due_ns, lateness_ns, missed_ticks)."""
        k = max(1, (now_ns - self.start_ns) // self.period_ns)
        due_ns = self.start_ns + k * self.period_ns
        missed = max(0, k - self._last_k - 1)
        self._last_k = max(self._last_k, k)
        return due_ns, now_ns - due_ns, missed


class LockstepTicks:
    """The tick source of a lockstep session (``session.clock: lockstep``):
    the plant sends the SIGALRM each tick (``redistro.plant.lockstep``) once
    every node has done the last one, so a tick is never late nor missed.
    The period stays the node's: the control laws' time step."""

    def __init__(self, rate_hz: float) -> None:
        period_us = max(1, round(1e6 / rate_hz))
        self.period_ns = period_us * 1000
        self.start_ns = 0

    @property
    def period_s(self) -> float:
        return self.period_ns / 1e9

    def start(self) -> None:
        self.start_ns = time.monotonic_ns()

    def stop(self) -> None:
        pass

    def due(self, now_ns: int) -> tuple[int, int, int]:
        return now_ns, 0, 0


def tick_source(rate_hz: float, clock: str) -> IntervalTimer | LockstepTicks:
    """The manager's tick source for ``session.clock``."""
    return LockstepTicks(rate_hz) if clock == "lockstep" else IntervalTimer(rate_hz)

"""What may disturb the simulated plant from outside: the interface.

The chassis offers a few points where a disturbance acts on the simulated
work-cell and its boards (a force on a wrist, a counter glitch, a stuck
home switch, a corrupted receiver); a :class:`Disturbance` decides when and
which. The plant process takes one from the session's hooks
(:mod:`redistro.process.hooks`, ``plant_disturbance``): the fault harness
installs its own; a normal run has none and pays nothing.
"""

from __future__ import annotations

from typing import Any, Protocol


class Disturbance(Protocol):
    def before_physics(self, chassis: Any) -> None:
        """Before each physics step: act on the world or the devices."""

    def after_sample(self, chassis: Any) -> None:
        """After the boards were sampled: change what they give."""

    def on_boards(self, now_ns: int) -> None:
        """The step just published is on the boards (CLOCK_MONOTONIC ns)."""

"""Finding a hole the controller does not meet where it believes it is.

A force segment with ``search.pattern: spiral`` goes through these phases
(``Phase``, recorded in every cycle's plan):

1. descent: the task's goal force draws the tool down until contact;
2. settle: in contact off the hole, the push drops to ``search.force_n``
   and the contact height is taken once it has settled;
3. search: the goal in the hole's plane runs an Archimedean spiral
   (r = pitch theta / 2 pi) about the believed centre at ``speed_m_s`` along
   the path, the plane's stiffness raised against the sliding friction;
4. in the hole: a fall of ``drop_m`` below the contact height, or the push
   gone (under half of ``force_n``) with the tip already half of that
   lower (or a contact already below the believed mouth): the goal in the
   plane stops where the tip is, the law goes back to free space along the
   axis (no spring wound up, no goal force fed forward: the peg goes down
   at the approach's speed, not thrown at the bottom), and the task's goal
   force pushes the peg home once it meets the bottom; a contact again
   within ``2 drop_m`` of the search's height was a slip, not the hole: the
   search goes on where it was;
5. not found: the spiral passed ``max_radius_m`` or the search ran
   ``timeout_s``; the task ends as a clean failure.

Pure arithmetic on plain floats: a few microseconds per cycle.
"""

from __future__ import annotations

import enum
import math
from typing import Protocol

# the reference's acceleration down the hole, once in [m/s^2]
DESCENT_ACCEL_M_S2 = 0.1
# contact this far below the believed mouth: the peg is already in the hole
IN_HOLE_BELOW_MOUTH_M = 0.005
# the push gone with the tip this many drop_m below the contact: in the hole
# (a peg caught by one edge in the slot the walls make dips 0.2-0.3 mm)
PUSH_GONE_BELOW = 0.5
# in the hole, a contact less than this many drop_m below where the search
# began is the surface again (the drop was a slip): the search goes on
RESUME_BELOW_CONTACT = 2.0


class SearchParams(Protocol):
    """What the search reads of its parameters (``config.task.Search``):
    lengths [m], speed [m/s], times [s]."""

    @property
    def touch_m_s(self) -> float: ...
    @property
    def pitch_m(self) -> float: ...
    @property
    def speed_m_s(self) -> float: ...
    @property
    def max_radius_m(self) -> float: ...
    @property
    def timeout_s(self) -> float: ...
    @property
    def drop_m(self) -> float: ...
    @property
    def settle_s(self) -> float: ...
    @property
    def force_n(self) -> float: ...
    @property
    def stiffness_n_m(self) -> float: ...
    @property
    def max_lateral_n(self) -> float: ...
    @property
    def yaw_stiffness_nm_rad(self) -> float: ...
    @property
    def descent_m_s(self) -> float: ...
    @property
    def slow_above_m(self) -> float: ...


class Phase(enum.IntEnum):
    NONE = 0
    DESCENT = 1
    SETTLE = 2
    SEARCH = 3
    IN_HOLE = 4
    NOT_FOUND = 5


class SpiralSearch:
    """One segment's search; ``step`` once per cycle, before the law."""

    def __init__(self, p: SearchParams, mouth_z_m: float) -> None:
        self.p = p
        self.mouth_z = mouth_z_m
        self.b = p.pitch_m / (2.0 * math.pi)
        self.phase = Phase.DESCENT
        self.theta = 0.0
        self.ox = self.oy = 0.0
        self.path_m = 0.0
        self.t_phase = 0.0
        self.t_contact: float | None = None
        self.t_search: float | None = None
        self.z_contact = 0.0
        self.why = ""
        self.false_drops = 0

    @property
    def radius_m(self) -> float:
        return self.b * self.theta

    def step(self, t: float, dt: float, contact: bool, z: float, push_n: float) -> Phase:
        """The phase after this cycle: t the segment's time [s], contact
        felt, z the TCP's height [m], push_n the tool's push down [N]."""
        ph = self.phase
        if ph == Phase.DESCENT:
            if contact:
                self.t_contact = t
                if z < self.mouth_z - IN_HOLE_BELOW_MOUTH_M:
                    self._to(Phase.IN_HOLE, t)
                else:
                    self._to(Phase.SETTLE, t)
        elif ph == Phase.SETTLE:
            if t - self.t_phase >= self.p.settle_s:
                self.z_contact = z
                self.t_search = t
                self._to(Phase.SEARCH, t)
        elif ph == Phase.IN_HOLE:
            if (
                contact
                and self.t_search is not None
                and t - self.t_phase >= self.p.settle_s
                and self.z_contact - z < RESUME_BELOW_CONTACT * self.p.drop_m
            ):
                # it met the surface again where it searched: no hole there
                self.false_drops += 1
                self._to(Phase.SEARCH, t)
        elif ph == Phase.SEARCH:
            below = self.z_contact - z
            if below > self.p.drop_m or (
                push_n < 0.5 * self.p.force_n and below > PUSH_GONE_BELOW * self.p.drop_m
            ):
                self._to(Phase.IN_HOLE, t)
            elif t - (self.t_search or t) > self.p.timeout_s:
                self.why = (
                    f"hole not found within {self.p.timeout_s:g} s of search "
                    f"(spiral at {self.radius_m * 1e3:.1f} mm)"
                )
                self._to(Phase.NOT_FOUND, t)
            else:
                ds = self.p.speed_m_s * dt
                r = self.b * self.theta
                self.theta += ds / math.sqrt(r * r + self.b * self.b)
                r = self.b * self.theta
                if r > self.p.max_radius_m:
                    self.why = f"hole not found within {self.p.max_radius_m * 1e3:g} mm"
                    self._to(Phase.NOT_FOUND, t)
                else:
                    self.path_m += ds
                    self.ox, self.oy = r * math.cos(self.theta), r * math.sin(self.theta)
        return self.phase

    def _to(self, phase: Phase, t: float) -> None:
        self.phase = phase
        self.t_phase = t

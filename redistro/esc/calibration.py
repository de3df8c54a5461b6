"""ESC Self-calibration (paper priority 17): the joint reference of ESC-local motion.

It runs the node's segments in order and publishes the joint reference the
pid worker tracks (the setpoint block); the sender then checks and sends.
Segment kinds (params ``segments``, built by :mod:`redistro.esc.plan`):

- ``sweep``: a quintic move of every joint to the initial position plus
  ``delta_rad`` (paper Table 6.II: -Range clockwise, then +Range
  counter-clockwise). The encoder boards latch the counter on every edge of
  each joint's home switch; the sweeps collect those latches.
- ``position``: a quintic move to ``goal_rad``. A position segment after the
  sweeps runs in the corrected frame: the zero offsets are worked out from the
  latched edges, the acquisition is asked to take them out of every position,
  and the move starts once it has (same cycle for the pid and this worker).

Zero offset of a joint: the switch turns on ``hysteresis/2`` inside its
window and off ``hysteresis/2`` outside, so the rising edges met moving down
and moving up lie symmetrically about the window's centre, and so do the
falling edges. The centre is the mean of the midpoints of whichever pairs
were seen; offset = centre (as measured) - the configured home angle.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from redistro.control.trajectory import QuinticRef
from redistro.drivers.io.registers import EDGE_FALLING, EDGE_RISING
from redistro.esc.common import EscContext
from redistro.localdata.block import Record
from redistro.localdata.layout import CALIBRATION, FEEDBACK, HOME, SETPOINT
from redistro.process.worker import Worker

DOF = 7


@dataclass
class Segment:
    name: str
    kind: str  # "sweep" | "position"
    duration_s: float
    delta_rad: float = 0.0
    goal_rad: np.ndarray | None = None


def zero_offsets(
    rising: list[list[float]],
    falling: list[list[float]],
    home_angle_rad: np.ndarray,
    window_rad: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """(offset [rad], found mask) per joint from the latched edge positions.

    rising/falling: per joint, the measured positions of the edges seen. A
    pair is the lowest and highest edge of one kind, at least half a window
    apart (one met moving down, one moving up).
    """
    n = len(home_angle_rad)
    offset = np.zeros(n)
    found = np.zeros(n, dtype=bool)
    for j in range(n):
        mids = []
        for edges in (rising[j], falling[j]):
            if edges and max(edges) - min(edges) > window_rad[j] / 2:
                mids.append((max(edges) + min(edges)) / 2)
        if mids:
            offset[j] = float(np.mean(mids)) - home_angle_rad[j]
            found[j] = True
    return offset, found


class Calibration(Worker):
    def initialize(self) -> None:
        ctx = EscContext.load(self.spec)
        s = ctx.hw.sensors
        self.robot = ctx.robot
        self.home_angle = np.asarray(s.home_angle_rad, dtype=np.float64)
        self.window = np.asarray(s.home_window_rad, dtype=np.float64)
        self.segments = [
            Segment(
                name=str(d["name"]),
                kind=str(d["kind"]),
                duration_s=float(d["duration_s"]),
                delta_rad=float(d.get("delta_rad", 0.0)),
                goal_rad=np.asarray(d["goal_rad"], dtype=np.float64) if "goal_rad" in d else None,
            )
            for d in self.spec.node_params.segments
        ]
        self.settle_s = self.spec.node_params.settle_s
        # Segments are timed by the boards' sample clock (home.step): the same
        # as wall time on real hardware; on a simulation that falls behind real
        # time the reference slows with the physics instead of running ahead.
        self.sample_ns = 1e9 / ctx.cfg.plant.physics_hz
        self.now_ns = 0
        ld = self.ld
        self.setpoint_block = ld.writer("setpoint", 0, role="calibration")
        self.calib_block = ld.writer("calibration", 0, role="calibration")
        self.feedback_block = ld.block("feedback", 0)
        self.home_block = ld.block("home", 0)
        self.sp = Record(SETPOINT)
        self.cal = Record(CALIBRATION)
        self.fb = Record(FEEDBACK)
        self.home = Record(HOME)
        self.index = -1  # running segment; -1 before the first
        self.seg_t0_ns = 0
        self.seg_q0 = np.zeros(DOF)
        self.q_init = np.zeros(DOF)
        self.ref = np.zeros(DOF)  # the last reference published
        self.rising: list[list[float]] = [[] for _ in range(DOF)]
        self.falling: list[list[float]] = [[] for _ in range(DOF)]
        self.latch_seen = np.zeros(DOF, dtype=np.uint32)
        self.waiting_offsets = False
        self.end_ns = 0
        # field views, made once (the cycle works in place)
        self.latch_count = self.home.array["latch_count"]
        sp = self.sp.array
        self.sp_q, self.sp_qd, self.sp_qdd = sp["q_rad"], sp["qd_rad_s"], sp["qdd_rad_s2"]
        self.quintic = QuinticRef(self.sp_q, self.sp_qd, self.sp_qdd)
        self._new = np.zeros(DOF, dtype=bool)

    # -- the cycle --

    def step(self, cycle: int) -> None:
        self.feedback_block.read_into(self.fb.bytes)
        self.home_block.read_into(self.home.bytes)
        self.now_ns = int(self.home["step"] * self.sample_ns)
        sp = self.sp.array
        if self.index < 0:
            self.q_init = self.fb.array["q_rad"].copy()
            self.ref = self.q_init.copy()
            self.latch_seen[...] = self.latch_count
            self._start(0, self.q_init)
        seg = self.segments[self.index] if self.index < len(self.segments) else None
        if seg is not None and seg.kind == "sweep":
            self._collect_edges()
        if self.waiting_offsets:
            if self.home["offset_seq"] == self.sp["offset_seq"]:
                # this cycle's feedback is in the corrected frame: so is the reference
                self.waiting_offsets = False
                self.ref = self.ref - sp["offset_rad"]
                self.cal["applied"] = 1
                self.calib_block.publish(self.cal.bytes)
                self._start(self.index, self.ref)
            self._hold(cycle)
            return
        if seg is None:
            self._hold(cycle)
            if self.now_ns >= self.end_ns and not self.sp["done"]:
                self.sp["done"] = 1
                self._hold(cycle)
                self.post("all segments done")
            return
        t = (self.now_ns - self.seg_t0_ns) / 1e9
        self.quintic.at(t)
        self.ref = self.sp_q
        self._publish(cycle)
        if t >= seg.duration_s:
            self._finish_segment(seg, self._goal(seg))

    def _goal(self, seg: Segment) -> np.ndarray:
        if seg.kind == "sweep":
            return self.q_init + seg.delta_rad
        assert seg.goal_rad is not None
        return seg.goal_rad

    def _start(self, index: int, q0: np.ndarray) -> None:
        self.index = index
        self.seg_q0 = np.asarray(q0, dtype=np.float64).copy()
        self.ref = self.seg_q0.copy()
        if index < len(self.segments):
            self.seg_t0_ns = self.now_ns
            seg = self.segments[index]
            self.quintic.start(self.seg_q0, self._goal(seg), seg.duration_s)
            self.sp["segment"] = index + 1
            self.post(f"segment {index + 1} {seg.name} ({seg.kind}, {seg.duration_s:g} s)")
        else:  # settling: the last segment's clock runs on (segment_t_s past its duration)
            self.end_ns = self.now_ns + int(self.settle_s * 1e9)

    def _finish_segment(self, seg: Segment, goal: np.ndarray) -> None:
        nxt = self.index + 1
        if seg.kind == "sweep" and (
            nxt >= len(self.segments) or self.segments[nxt].kind != "sweep"
        ):
            if not self._conclude():
                return
            self.index = nxt
            if nxt < len(self.segments):
                self.waiting_offsets = True  # the next segment starts in the corrected frame
            else:
                self._start(nxt, goal)
            return
        self._start(nxt, goal)

    def _collect_edges(self) -> None:
        if not np.count_nonzero(np.not_equal(self.latch_count, self.latch_seen, out=self._new)):
            return  # no new latch (most cycles)
        h = self.home.array
        counts = h["latch_count"].astype(np.int64)
        seen = self.latch_seen.astype(np.int64)
        new = np.flatnonzero(counts != seen)
        for j in new.tolist():
            if counts[j] - seen[j] > 1:
                self.post(
                    f"joint {j + 1}: {counts[j] - seen[j] - 1} home edge(s) "
                    "passed between two samples",
                    logging.WARNING,
                )
            q = float(h["latch_q_rad"][j])
            edge = int(h["latch_edge"][j])
            if edge == EDGE_RISING:
                self.rising[j].append(q)
            elif edge == EDGE_FALLING:
                self.falling[j].append(q)
        self.latch_seen[...] = self.latch_count
        if new.size:
            self.cal.array["edges"] = [
                len(r) + len(f) for r, f in zip(self.rising, self.falling, strict=True)
            ]
            self.calib_block.publish(self.cal.bytes)

    def _conclude(self) -> bool:
        """Work out the zero offsets after the sweeps; False (and failed) if a joint has none."""
        offset, found = zero_offsets(self.rising, self.falling, self.home_angle, self.window)
        c = self.cal.array
        c["found"] = found
        c["offset_found_rad"] = offset
        self.calib_block.publish(self.cal.bytes)
        if not found.all():
            missing = ", ".join(str(j + 1) for j in np.flatnonzero(~found))
            self.post(
                f"self-calibration failed: no home switch found on joint(s) {missing} "
                "within the sweep range",
                logging.ERROR,
            )
            self.sp["failed"] = 1
            self.index = len(self.segments)
            self.end_ns = 2**62
            return False
        text = " ".join(f"{v:+.5f}" for v in offset)
        self.post(f"zero offsets found [rad]: {text}")
        self.sp.array["offset_rad"] = offset
        self.sp["offset_seq"] = self.sp["offset_seq"] + 1
        return True

    def _hold(self, cycle: int) -> None:
        """Publish the last reference, standing still."""
        if self.sp_q is not self.ref:
            self.sp_q[...] = self.ref
            self.ref = self.sp_q
        self.sp_qd[...] = 0.0
        self.sp_qdd[...] = 0.0
        self._publish(cycle)

    def _publish(self, cycle: int) -> None:
        """Publish the setpoint record (its reference already in place)."""
        self.sp["stamp_ns"] = self.due_ns
        self.sp["cycle"] = cycle
        self.sp.array["joint_on"] = 0 if self.sp["failed"] else 1
        self.sp["segment_t_s"] = max(0.0, (self.now_ns - self.seg_t0_ns) / 1e9)
        self.setpoint_block.publish(self.sp.bytes)

"""A parallel SSC (``ssc.parallel_arms``): each robot's law in a worker of its
own, the task's clock in one more (paper 000's parallel stages).

The node's plan (``ssc/plan.py``) puts one SSC worker per robot in stage 0
(``arm.<robot>``: they run in parallel, each on the robot it owns) and the
clock's worker in stage 1: the collecting point between the stages is the
token that hands it every arm's cycle. Each worker keeps the whole task's
state (every robot's model and moves: what a segment's start needs, a hand
that follows another's, the two hands of a carry), but only one process
acts on it:

- an arm worker runs its robot's law or hold, its search and its guarded
  contact, and publishes that robot's plan and command; the segments it
  runs come from the clock (it starts each one on the clock's time, so a
  segment begins on the same clock in every arm);
- the clock's worker reads the arms' plans (their contacts, their
  searches' end, their poses against their end conditions), watches the
  arms' clearance, decides the segments (its ``_advance``), and publishes
  the ``clock`` block the arms take at their next cycle; it wakes the ddm
  once, when every arm's command is out.

Per cycle this costs the clock's worker a read of each plan and one write;
each arm a read of the clock. A segment therefore ends one cycle after
its end condition holds (the serial SSC ends it in the same cycle).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

from redistro.control.search import Phase
from redistro.localdata.block import Record
from redistro.localdata.layout import SSC_CLOCK

if TYPE_CHECKING:
    from redistro.ssc.worker import SscWorker


def parts(
    w: SscWorker, grip: Callable[..., None], retreat_s: float
) -> tuple[ArmSide | None, ClockSide | None]:
    """An SSC worker's part: an arm's (param ``arm``), the clock's (``lead``),
    or none. ``grip``: what a segment's end does to the grippers;
    ``retreat_s``: a failed search's lift and hold."""
    if "arm" in w.params:
        return ArmSide(w, int(w.params["arm"]), grip), None
    if w.params.get("lead"):
        return None, ClockSide(w, retreat_s)
    return None, None


class ArmSide:
    """In an arm worker: the clock's decisions taken, at the top of a cycle."""

    def __init__(self, w: SscWorker, arm: int, grip: Callable[..., None]) -> None:
        self.w = w
        self.grip = grip
        w.mine = [arm]
        w.narrates = False
        self.block = w.ld.block("clock")
        self.rec = Record(SSC_CLOCK)
        self.quiet = lambda *_: None

    def take(self) -> bool:
        """The clock's latest decisions applied; False before the task starts."""
        w, c = self.w, self.rec
        self.block.read_into(c.bytes)
        if not c["started"]:
            return False
        if not w.started:
            w.started = True
            w.t0_step = int(c["t0_step"])
            for i in w.mine:
                w.states[i].hold_q[...] = w.states[i].views["q"]
        fr = int(c["fail_robot"])
        if fr in w.mine and not w.failed and w.moving[fr] is not None:
            # the segment ended with this robot's search open (the clock said it)
            plan = w.plans[w.k]
            why = f"hole not found within the segment's {plan.duration_s:g} s"
            mv = w.moving[fr]
            assert mv is not None
            w._fail(w.states[fr], mv, float(c["fail_t_s"]), why, closing=True)
        if c["failed"] and not w.failed:
            w.failed = "another arm's search found no hole"
            for i in w.mine:
                if w.moving[i] is not None:
                    w._stop(i, w.states[i])
        seg, start = int(c["segment"]), float(c["seg_start_t_s"])
        if seg != w.k and (w.failed or seg < w.k):
            w._begin(seg, start)  # (after a failure: straight to the end)
        while w.k < seg:
            if 0 <= w.k < len(w.plans):
                self.grip(w.states, w.seg_moves, start, self.quiet)
            w._begin(w.k + 1, start)
        w.done = bool(c["done"])
        return True

    def clearance(self) -> tuple[float, float]:
        return float(self.rec["arms_clearance_m"]), float(self.rec["cell_clearance_m"])


class ClockSide:
    """In the clock's worker: the arms' cycle read, the task advanced, the
    clock published for the arms' next cycle."""

    def __init__(self, w: SscWorker, retreat_s: float) -> None:
        self.w = w
        self.retreat_s = retreat_s
        w.mine = []
        ld = w.ld
        self.plan_reads = [ld.block("plan", i) for i in range(len(w.states))]
        self.block = ld.writer("clock", role="worker")
        self.rec = Record(SSC_CLOCK)
        self.rec["fail_robot"] = -1

    def step(self, cycle: int) -> None:
        w, c = self.w, self.rec
        w.wake_ddm()  # every arm's command is out (the collecting point): one send
        for block, rec in zip(self.plan_reads, w.plan_recs, strict=True):
            block.read_into(rec.bytes)
        c["cycle"] = cycle
        if w.read_feedback():
            step_now = max(rec["step"] for rec in w.fbs)
            if not w.started:
                w.start_task(step_now)
            t = (step_now - w.t0_step) / w.physics_hz
            w.last_t = t
            self.learn()
            if not w.estop_request:
                w._clearance(t)
            w._advance(t)
            c["started"] = 1
            c["t0_step"] = w.t0_step
            c["segment"] = w.k
            c["seg_start_t_s"] = w.seg_start_t
            c["done"] = 1 if w.done else 0
            c["failed"] = 1 if w.failed else 0
            c["fail_robot"] = w.fail_robot
            c["fail_t_s"] = w.fail_t
            c["arms_clearance_m"] = w.watch.arms_m
            c["cell_clearance_m"] = w.watch.cell_m
        self.block.publish(c.bytes)

    def learn(self) -> None:
        """What the arms' laws met in their cycle: a guarded move's contact
        (its arm holds from then on), a search that found no hole (the task
        fails: every arm holds once that one has lifted off)."""
        w = self.w
        running = w.k + 1  # (the plan record's 1-based segment)
        for i, st in enumerate(w.states):
            pl, mv = st.plan, w.moving[i]
            if mv is None or int(pl["segment"]) != running:
                continue  # (an arm not yet in this segment says nothing of it)
            if mv.contact_n > 0 and not pl["moving"]:
                w.contacted[i] = True
                w.moving[i] = None
            elif int(pl["phase"]) == Phase.NOT_FOUND and not w.failed:
                w.failed = f"{w.plans[w.k].name}: {st.name}'s search found no hole"
                w.retreat_end_t = float(pl["t_s"]) + self.retreat_s
                w.moving = [None] * len(w.states)
                w.post(f"{st.name}'s search found no hole: every arm holds", logging.INFO)

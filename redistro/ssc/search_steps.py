"""How a segment's search steers the SSC's Cartesian law, phase by phase
(:class:`redistro.control.search.SpiralSearch` keeps the phases): the goal
in the hole's plane, the plane's stiffness, the push along z, and the law's
speed down the hole. The law's records are written by field name
(control/cartesian_layout.py)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from redistro.control.search import DESCENT_ACCEL_M_S2, Phase

if TYPE_CHECKING:
    from redistro.ssc.plan import MovePlan
    from redistro.ssc.worker import RobotState, SscWorker

X, Y, Z, RX, RY, RZ = 0, 1, 2, 3, 4, 5  # Cartesian axes, in the law's 6-vectors
DEEP_IN = 3.0  # this many search.drop_m below the contact: in the hole for sure
TOUCH_ABOVE_M = 0.003  # a searching descent slows to search.touch_m_s this far above the mouth


def steer(w: SscWorker, st: RobotState, plan: MovePlan, seg_t: float, dt: float, t: float) -> None:
    """One cycle of the search: its next phase, and the law set for it."""
    srch = st.search
    assert srch is not None
    law = st.law
    before = srch.phase
    phase = srch.step(seg_t, dt, law.contact, float(law.tcp_p[2]), -float(law.applied[2]))
    gains = law.gains
    if phase == Phase.DESCENT:
        near = abs(float(law.tcp_p[2]) - plan.mouth_z_m) < TOUCH_ABOVE_M
        # near the mouth as drawn: touch gently; past it, untouched, the
        # peg is going into the hole: the law's own speed again
        gains["v_max"] = srch.p.touch_m_s if near else st.gains0["v_max"]
    elif phase == Phase.SETTLE and before != phase:
        gains["v_max"] = st.gains0["v_max"]
        gains["k"][RZ] = srch.p.yaw_stiffness_nm_rad  # in touch: the search's soft yaw
        _push(st, -srch.p.force_n)
        w.post(f"{st.name}: contact off the hole at t={t:.2f} s; searching")
    elif phase == Phase.SEARCH:
        _searching(w, st, plan, before, t)
    elif phase == Phase.IN_HOLE:
        _in_hole(w, st, plan, before, seg_t, t)
    elif phase == Phase.NOT_FOUND and before != phase:
        gains[...] = st.gains0
        w._fail(st, plan, t, srch.why)
    st.plan["phase"] = phase


def _push(st: RobotState, force_n: float) -> None:
    """The goal force along z: the law's and the plan's."""
    st.law.cmd["goal_wrench"][Z] = force_n
    st.views["wrench_goal"][2] = force_n


def _goal_xy(law: Any, x: float, y: float) -> None:
    ref = law.ref
    ref["start_p"][X] = ref["goal_p"][X] = x
    ref["start_p"][Y] = ref["goal_p"][Y] = y


def _searching(w: SscWorker, st: RobotState, plan: MovePlan, before: Phase, t: float) -> None:
    """The search's spiral: the plane's stiffness, the goal leading the tip."""
    srch, law = st.search, st.law
    assert srch is not None
    gains = law.gains
    if before != Phase.SEARCH:
        gains[...] = st.gains0
        st.fast_z = st.slow_z = -math.inf
        gains["k"][X] = gains["k"][Y] = srch.p.stiffness_n_m
        gains["k"][RZ] = srch.p.yaw_stiffness_nm_rad
        if before == Phase.IN_HOLE:  # a slip, not the hole: search on
            _push(st, -srch.p.force_n)
            w.post(f"{st.name}: no hole there (t={t:.2f} s); searching on")
    x, y = plan.pose[0] + srch.ox, plan.pose[1] + srch.oy
    # the goal leads the tip by at most max_lateral_n / stiffness: a peg
    # caught on an edge is not loaded up until it snaps free
    tx, ty = float(law.tcp_p[0]), float(law.tcp_p[1])
    dx, dy = x - tx, y - ty
    lead = math.sqrt(dx * dx + dy * dy)
    cap = srch.p.max_lateral_n / srch.p.stiffness_n_m
    if lead > cap:
        x, y = tx + dx * cap / lead, ty + dy * cap / lead
    _goal_xy(law, x, y)
    xy = st.views["search_xy"]
    xy[0], xy[1] = srch.ox, srch.oy
    st.plan["search_m"] = srch.path_m


def _in_hole(
    w: SscWorker, st: RobotState, plan: MovePlan, before: Phase, seg_t: float, t: float
) -> None:
    """In the hole: stop where the tip is; the push dying away after the
    drop; down fast once deep enough, at the law's own speed near the
    bottom."""
    srch, law = st.search, st.law
    assert srch is not None
    gains = law.gains
    if before != Phase.IN_HOLE:
        _dropped_in(w, st, plan, before, t)
    elif law.contact and srch.t_search is not None and seg_t - srch.t_phase < srch.p.settle_s:
        # just dropped, the push still dying away: not a contact yet (else
        # the goal force is fed forward again and throws the peg down)
        law.release()
    elif law.tcp_p[2] < st.fast_z:
        # deep enough not to be a slip: down fast (what meets the tool
        # higher up meets it at the law's own speed)
        gains["v_max"] = srch.p.descent_m_s
        gains["a_max"] = DESCENT_ACCEL_M_S2
        st.fast_z = -math.inf
    elif law.tcp_p[2] < st.slow_z:
        # near the bottom: the law's own speed (braking at the descent's
        # acceleration; the law's own comes back at the bottom's contact)
        gains["v_max"] = st.gains0["v_max"]
        st.slow_z = -math.inf
    elif law.contact and gains["a_max"] != st.gains0["a_max"]:
        gains["a_max"] = st.gains0["a_max"]


def _dropped_in(w: SscWorker, st: RobotState, plan: MovePlan, before: Phase, t: float) -> None:
    """The peg found the hole: stop where the tip is, the task's own
    stiffness and push."""
    srch, law = st.search, st.law
    assert srch is not None
    p = law.tcp_p
    _goal_xy(law, float(p[0]), float(p[1]))
    law.gains[...] = st.gains0
    _push(st, st.goal_z_n)
    if before == Phase.DESCENT:
        return  # (a peg that met nothing before the bottom keeps the task's own law)
    # the yaw stays as soft as the search had it: a stiffer yaw now would
    # snap back whatever the walls turned (a jolt at the wrist)
    law.gains["k"][RZ] = srch.p.yaw_stiffness_nm_rad
    # ... and the tilt as soft as the config has it, where the move held it
    # stiffer for the search (a long peg's tip on the spiral): the walls
    # guide the peg now, and a hole held by another hand tilts under the
    # push (a stiff wrist wedged the peg 2.4 mm above the bottom)
    for ax in (RX, RY):
        law.gains["k"][ax] = min(law.gains["k"][ax], st.gains_cfg["k"][ax])
        law.gains["d"][ax] = min(law.gains["d"][ax], st.gains_cfg["d"][ax])
    # the peg is falling in: free space again along z (no spring wound up,
    # no goal force fed forward), down the hole at the search's descent
    # speed to a little above its bottom as drawn (below the mouth the
    # search met), then at the law's own speed
    law.release()
    st.fast_z = srch.z_contact - DEEP_IN * srch.p.drop_m
    st.slow_z = srch.z_contact - plan.hole_depth_m + srch.p.slow_above_m
    w.post(
        f"{st.name}: in the hole at t={t:.2f} s, {srch.path_m * 1e3:.1f} mm "
        f"of search, {srch.radius_m * 1e3:.2f} mm from the believed centre"
    )

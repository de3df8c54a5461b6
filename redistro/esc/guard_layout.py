"""The sender's guard kernel's buffers with fields (``guard_prepare``; its
reference is esc/sender.py, Sender._prepare_numpy), declared once."""

from __future__ import annotations

import numpy as np

from redistro.kernel_layouts import Table

F8, I8 = "<f8", "<i8"
DOF = 7

LIMITS = np.dtype(
    [
        ("qd_max", F8, DOF),  # [rad/s]
        ("tau_max", F8, DOF),  # [N m], commanded and measured
        ("force_max", F8),  # the wrist force's magnitude [N]
        ("moment_max", F8),  # ... moment's [N m]
        ("q_lo", F8, DOF),  # the position limits less the margin [rad]
        ("q_hi", F8, DOF),
        ("stop_k", F8, DOF),  # 1 / (2 deceleration) [s^2/rad]
    ]
)
# where the fields the guard reads lie in the feedback, the command, the home block
FB_OFF = np.dtype([("q", I8), ("qd", I8), ("tau", I8), ("wrench", I8)])
SRC_OFF = np.dtype([("tau", I8), ("joint_on", I8), ("session_status", I8)])  # status -1: none
HOME_OFF = np.dtype([("step", I8)])
# one cycle as the guard saw it (the trace written when it trips)
TRACE_ROW = np.dtype(
    [
        ("cycle", F8),
        ("step", F8),
        ("q", F8, DOF),
        ("qd", F8, DOF),
        ("tau", F8, DOF),
        ("tau_cmd", F8, DOF),
    ]
)
TRACE_AT = np.dtype([("rows", I8), ("cycle", I8)])  # rows written so far, this cycle

LAYOUTS = {
    "guard_prepare": {
        "limits": LIMITS,
        "fb_off": FB_OFF,
        "src_off": SRC_OFF,
        "home_off": HOME_OFF,
        "trace": Table(TRACE_ROW),
        "trace_at": TRACE_AT,
    }
}

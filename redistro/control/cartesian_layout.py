"""The Cartesian law kernel's buffers (``cartesian_law``; its reference is
:class:`redistro.control.cartesian.CartesianLaw`), declared once: each a
record of float64 fields, built by the law and read by the C kernel
(control/cartesian_kernel.c) through offsets generated from these."""

from __future__ import annotations

import numpy as np

F8 = "<f8"

# the rigid-body terms of this cycle, and the cycle's times
KIN = np.dtype(
    [
        ("J", F8, (6, 7)),  # the tool frame's Jacobian, LOCAL_WORLD_ALIGNED
        ("R", F8, (3, 3)),  # the tool frame's rotation
        ("t", F8, 3),  # ... and position [m]
        ("M", F8, (7, 7)),  # the joint-space inertia, upper triangle as CRBA leaves it
        ("g", F8, 7),  # gravity torques [N m]
        ("q", F8, 7),
        ("qd", F8, 7),
        ("wrench", F8, 6),  # the wrist sensor's, sensor frame [N, N m]
        ("seg_t", F8),  # time in the segment [s]
        ("dt", F8),  # the cycle [s]
        ("t_task", F8),  # time in the task [s]
        ("integrate", F8),  # 1: integral action on
    ]
)
# the segment's reference: a quintic in position, the same blend about one axis
REF = np.dtype(
    [
        ("start_p", F8, 3),
        ("goal_p", F8, 3),
        ("start_R", F8, (3, 3)),
        ("goal_R", F8, (3, 3)),
        ("axis", F8, 3),  # rotation vector of goal_R start_R^T
        ("move_s", F8),
    ]
)
CMD = np.dtype([("selection", F8, 6), ("goal_wrench", F8, 6), ("q_null", F8, 7)])
GAINS = np.dtype(
    [
        ("k", F8, 6),
        ("d", F8, 6),
        ("ki", F8, 6),
        ("i_max", F8, 6),
        ("k_null", F8, 7),
        ("d_joint", F8, 7),
        ("zeta", F8),
        ("k_adm", F8),
        ("k_adm_rot", F8),
        ("v_max", F8),
        ("w_max", F8),
        ("a_max", F8),
        ("alpha_max", F8),
        ("contact_n", F8),
        ("ramp_s", F8),
        ("tcp_offset", F8),  # the TCP along the tool frame's z [m]
        ("base", F8, 3),  # the robot's base in the world [m]
    ]
)
# what HybridState holds, between cycles
STATE = np.dtype(
    [
        ("R_task", F8, (3, 3)),
        ("xi", F8, 6),
        ("xi_v", F8, 6),
        ("a_ref", F8, 6),
        ("integral", F8, 6),
        ("contact", F8),
        ("contact_t", F8),
        ("ramp", F8),
        ("spring0", F8, 3),  # the spring's push along the force axes at contact
    ]
)
OUT = np.dtype(
    [
        ("tau", F8, 7),
        ("applied", F8, 6),  # the wrench the tool applies, task axes
        ("tcp_p", F8, 3),
        ("tcp_rot", F8, 3),  # rotation vector
        ("ref_p", F8, 3),  # the position reference
    ]
)

LAYOUTS = {
    "cartesian_law": {
        "kin": KIN,
        "ref": REF,
        "cmd": CMD,
        "gains": GAINS,
        "state": STATE,
        "out": OUT,
    }
}

"""The joint kernels' buffers with fields (``joint_pid``, ``quintic``; their
references are in control/pid.py and control/trajectory.py), declared once."""

from __future__ import annotations

import numpy as np

F8 = "<f8"
DOF = 7

PID_GAINS = np.dtype([("kp", F8, DOF), ("ki", F8, DOF), ("kd", F8, DOF), ("i_max", F8, DOF)])
PID_DT = np.dtype([("dt", F8)])  # the cycle [s]
QUINTIC_TIME = np.dtype([("duration", F8), ("t", F8)])  # the move's length, the time in it [s]

LAYOUTS = {
    "joint_pid": {"gains": PID_GAINS, "dt": PID_DT},
    "quintic": {"time": QUINTIC_TIME},
}

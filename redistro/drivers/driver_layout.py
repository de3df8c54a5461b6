"""The robot-level driver's decode kernel's buffers with fields
(``driver_decode``; its reference is drivers/robot.py,
RobotDriver._decode_numpy), declared once."""

from __future__ import annotations

import numpy as np

F8, I8 = "<f8", "<i8"

# what the driver keeps between samples
STATE = np.dtype(
    [
        ("have_ref", I8),  # the counters' reference is set
        ("prev_step", I8),  # the last sample's plant step (-1: none)
        ("step", I8),  # this sample's (the oldest board's)
        ("coherent", I8),  # every board of the sample from one plant step
    ]
)
PARAMS = np.dtype(
    [
        ("jump_limit_rad_s", F8),  # the plausibility check (0: off)
        ("physics_hz", F8),  # the boards' sample rate
        ("has_tach", F8),  # speeds from tachometers (else differentiated)
        ("has_torque", F8),  # torques from torque sensors (else the DAC readback)
        ("retry", F8),  # a snapshot of two plant steps: read again (no decode)
    ]
)
JUMP = np.dtype([("delta", F8), ("limit", F8), ("steps", F8)])  # a refused counter change [counts]
ONE_OFFSET = np.dtype([("at", I8)])  # a byte offset (-1: none)

LAYOUTS = {
    "driver_decode": {
        "state": STATE,
        "params": PARAMS,
        "out": JUMP,
        "strain_off": ONE_OFFSET,
        "cal_off": ONE_OFFSET,
    }
}

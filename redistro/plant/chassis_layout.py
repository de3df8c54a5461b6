"""The chassis kernels' buffers with fields (``chassis_apply``,
``chassis_sample``; their reference is plant/chassis.py), declared once."""

from __future__ import annotations

import numpy as np

from redistro.kernel_layouts import Table

I8 = "<i8"

# a readback: bytes of an out bank copied into an in bank (mask != 0: one
# 32-bit word, masked)
READBACK_ROW = np.dtype([("src", I8), ("dst", I8), ("size", I8), ("mask", I8)])
NOISE_AT = np.dtype([("row", I8)])  # the next row of the wrist noise block
STEP = np.dtype([("step", I8)])  # the plant's step, stamped on every board

LAYOUTS = {
    "chassis_apply": {"copy": Table(READBACK_ROW)},
    "chassis_sample": {"noise_at": NOISE_AT, "step": STEP},
}

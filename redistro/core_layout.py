"""The core kernels' tables (``copy``, ``seq_read``, ``seq_write``; their
reference is redistro/kernels.py and localdata's seqlocked blocks), declared
once: a row per field or block copied, byte offsets and sizes."""

from __future__ import annotations

import numpy as np

from redistro.kernel_layouts import Table

I8 = "<i8"

COPY_ROW = np.dtype([("src", I8), ("dst", I8), ("size", I8)])
# a seqlocked block: its counter and payload in the shared buffer, its copy elsewhere
SEQ_READ_ROW = np.dtype([("seq", I8), ("payload", I8), ("size", I8), ("dst", I8)])
SEQ_WRITE_ROW = np.dtype([("seq", I8), ("payload", I8), ("size", I8), ("src", I8)])

LAYOUTS = {
    "copy": {"table": Table(COPY_ROW)},
    "seq_read": {"table": Table(SEQ_READ_ROW)},
    "seq_write": {"table": Table(SEQ_WRITE_ROW)},
}

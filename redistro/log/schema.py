"""Message layouts of the session log, as numpy dtypes and ROS 1 message definitions.

A per-cycle message is a little-endian packed record: ``uint64 log_cycle`` then
the payload of a Local Data block (its dtype is packed already, so the raw
block bytes *are* the message body). That is exactly the ROS 1 wire
encoding of a message whose fields are those of the dtype in order (fixed
arrays carry no length), so standard robotics log viewers decode the file
with the ``ros1msg`` schema written beside each channel, and our own reader
turns a whole channel into one numpy array with :func:`dtype_from_ros1`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

# numpy scalar code -> ROS 1 primitive
_ROS1 = {
    "u1": "uint8",
    "i1": "int8",
    "u2": "uint16",
    "i2": "int16",
    "u4": "uint32",
    "i4": "int32",
    "u8": "uint64",
    "i8": "int64",
    "f4": "float32",
    "f8": "float64",
}
_NUMPY = {v: k for k, v in _ROS1.items()}

CYCLE_FIELD = ("log_cycle", "<u8")  # the recording node's cycle


def with_cycle(payload: np.dtype[Any]) -> np.dtype[Any]:
    """``uint64 log_cycle`` followed by the fields of ``payload`` (packed)."""
    fields = payload.fields
    assert fields is not None and payload.names is not None
    if payload.itemsize != sum(fields[n][0].itemsize for n in payload.names):
        raise ValueError("a logged block must be packed")
    return np.dtype([CYCLE_FIELD, *[(n, fields[n][0]) for n in payload.names]])


def ros1_definition(dtype: np.dtype[Any]) -> str:
    """The ROS 1 message definition of a packed structured dtype."""
    lines = []
    fields = dtype.fields
    assert fields is not None and dtype.names is not None
    for name in dtype.names:
        ft = fields[name][0]
        base, shape = ft.subdtype if ft.subdtype else (ft, ())
        if base.kind == "S":
            count = base.itemsize * int(np.prod(shape)) if shape else base.itemsize
            lines.append(f"uint8[{count}] {name}")
            continue
        if len(shape) > 1:
            raise ValueError(f"field {name}: only flat arrays can be logged")
        code = f"{base.kind}{base.itemsize}"
        if code not in _ROS1:
            raise ValueError(f"field {name}: no ROS 1 type for {base}")
        suffix = f"[{shape[0]}]" if shape else ""
        lines.append(f"{_ROS1[code]}{suffix} {name}")
    return "\n".join(lines) + "\n"


def dtype_from_ros1(text: str) -> np.dtype[Any]:
    """The packed numpy dtype of a ROS 1 definition written by :func:`ros1_definition`."""
    fields: list[tuple[str, Any]] = []
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        kind, _, name = line.partition(" ")
        count = 0
        if kind.endswith("]"):
            kind, _, n = kind[:-1].partition("[")
            count = int(n)
        code = _NUMPY.get(kind)
        if code is None:
            raise ValueError(f"unsupported field type {kind!r} in a log schema")
        fields.append((name.strip(), (f"<{code}", (count,)) if count else f"<{code}"))
    return np.dtype(fields)


def timing_dtype(n_procs: int) -> np.dtype[Any]:
    """One node's timing in one cycle: the manager's tick, and per process
    (Local Data process index) its heartbeat, lateness, busy time and counters."""
    return np.dtype(
        [
            CYCLE_FIELD,
            ("tick_due_ns", "<i8"),  # CLOCK_MONOTONIC
            ("tick_late_us", "<f4"),  # manager: tick taken - tick due
            ("heartbeat_cycle", "<u8", (n_procs,)),
            ("late_us", "<f4", (n_procs,)),  # woke - tick due (on-cycle workers; NaN otherwise)
            ("busy_us", "<f4", (n_procs,)),  # done - woke of its last step
            ("overruns", "<u4", (n_procs,)),
            ("skipped", "<u4", (n_procs,)),
            ("state", "u1", (n_procs,)),
        ]
    )

"""Message layouts of the session log, as numpy dtypes and ROS 2 message definitions.

A per-cycle message is ``uint64 log_cycle`` then the payload of a Local Data
block, as a ROS 2 message whose fields are those of the block's dtype in
order (fixed arrays carry no length; a text field is a ``uint8`` array):
CDR-encoded, as ROS 2 puts it on the wire and rosbag2 in its MCAP files
(the 4-byte encapsulation header, little-endian, then each field aligned
to its element's size from the header's end). The blocks are packed, so
the writer inserts the alignment's padding (:func:`cdr_runs`, worked out
once here: the writer process has no numpy), and our reader turns a whole
channel back into one packed numpy array (:func:`cdr_dtype`). Each
channel's ``ros2msg`` schema is written beside it: standard robotics
tools decode the file without redistro.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from redistro.log.frames import CDR_HEADER, STRUCT_CODES

# numpy scalar code -> ROS 2 primitive
_ROS = {
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
_NUMPY = {v: k for k, v in _ROS.items()}

CYCLE_FIELD = ("log_cycle", "<u8")  # the recording node's cycle


def with_cycle(payload: np.dtype[Any]) -> np.dtype[Any]:
    """``uint64 log_cycle`` followed by the fields of ``payload`` (packed)."""
    fields = payload.fields
    assert fields is not None and payload.names is not None
    if payload.itemsize != sum(fields[n][0].itemsize for n in payload.names):
        raise ValueError("a logged block must be packed")
    return np.dtype([CYCLE_FIELD, *[(n, fields[n][0]) for n in payload.names]])


def msg_definition(dtype: np.dtype[Any]) -> str:
    """The ROS 2 message definition (``.msg``) of a packed structured dtype."""
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
        if code not in _ROS:
            raise ValueError(f"field {name}: no ROS 2 type for {base}")
        suffix = f"[{shape[0]}]" if shape else ""
        lines.append(f"{_ROS[code]}{suffix} {name}")
    return "\n".join(lines) + "\n"


def dtype_from_msg(text: str) -> np.dtype[Any]:
    """The packed numpy dtype of a definition written by :func:`msg_definition`."""
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


def type_name(name: str) -> str:
    """A ROS 2 type name for a log channel's message: ``redistro/msg/`` and
    ``name`` in CamelCase (``feedback`` -> ``redistro/msg/Feedback``)."""
    parts = name.replace(".", "_").replace("/", "_").split("_")
    return "redistro/msg/" + "".join(p[:1].upper() + p[1:] for p in parts if p)


def _aligns(dtype: np.dtype[Any]) -> list[tuple[str, int, int, int]]:
    """Per field of a packed dtype: name, offset, size, CDR alignment."""
    fields = dtype.fields
    assert fields is not None and dtype.names is not None
    out = []
    for name in dtype.names:
        ft, off = fields[name][0], int(fields[name][1])
        base = ft.subdtype[0] if ft.subdtype else ft
        out.append((name, off, int(ft.itemsize), 1 if base.kind == "S" else int(base.itemsize)))
    return out


def cdr_runs(dtype: np.dtype[Any]) -> list[tuple[int, int, int]]:
    """How a packed message becomes its CDR body: (offset in the packed
    message, bytes, zero bytes of padding before them), contiguous fields
    merged (the header goes first, not counted here)."""
    runs: list[list[int]] = []
    at = 0  # in the CDR body
    for _name, off, size, align in _aligns(dtype):
        pad = -at % align
        if runs and pad == 0 and runs[-1][0] + runs[-1][1] == off:
            runs[-1][1] += size
        else:
            runs.append([off, size, pad])
        at += pad + size
    return [(a, b, c) for a, b, c in runs]


def cdr_dtype(dtype: np.dtype[Any]) -> np.dtype[Any]:
    """The dtype of a whole CDR message (header included) of a packed dtype's
    fields: each field at its aligned place."""
    names, formats, offsets = [], [], []
    fields = dtype.fields
    assert fields is not None
    at = 0
    for name, _off, size, align in _aligns(dtype):
        at += -at % align
        names.append(name)
        formats.append(fields[name][0])
        offsets.append(len(CDR_HEADER) + at)
        at += size
    return np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": len(CDR_HEADER) + at}
    )


def cdr_struct(dtype: np.dtype[Any]) -> str:
    """The ``struct`` format of a packed dtype's CDR body (header excluded;
    numeric fields only), padding included: for a writer without numpy."""
    out, at = "<", 0
    for name, _off, size, align in _aligns(dtype):
        pad = -at % align
        out += f"{pad}x" if pad else ""
        ft = dtype.fields[name][0]  # type: ignore[index]
        base, shape = ft.subdtype if ft.subdtype else (ft, ())
        count = int(np.prod(shape)) if shape else 1
        out += f"{count if shape else ''}{STRUCT_CODES[(base.kind, base.itemsize)]}"
        at += pad + size
    return out


LOGGED_BLOCKS = ("feedback", "command", "plan", "setpoint", "control", "guard")
MSG_FOLDER = "redistro/msg"  # the package's message definitions, beside its code


def package_messages() -> dict[str, str]:
    """Every redistro message a session log holds, as the ``.msg`` files of
    a ROS 2 package named ``redistro`` (file name -> text): one per logged
    Local Data block, ``Timing<n>`` for a node of ``n`` processes, a
    cycle's digest, the event and the message-box line. ``redistro/msg/`` holds them; a unit test
    keeps the two equal (``write_package_messages`` writes them anew)."""
    from redistro.localdata.layout import BLOCKS, MAX_PROCS
    from redistro.log import ros2

    out = {
        f"{type_name(b).rsplit('/', 1)[1]}.msg": msg_definition(with_cycle(BLOCKS[b][0]))
        for b in LOGGED_BLOCKS
    }
    for n in range(1, MAX_PROCS + 1):
        out[f"Timing{n}.msg"] = msg_definition(timing_dtype(n))
    out["Event.msg"] = ros2.EVENT_DEF
    out["CycleDigest.msg"] = ros2.CYCLE_DIGEST_DEF
    out["Message.msg"] = ros2.MESSAGE_DEF.split(ros2.SEPARATOR)[0]
    return out


def write_package_messages(root: str = ".") -> None:
    from pathlib import Path

    folder = Path(root) / MSG_FOLDER
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in package_messages().items():
        (folder / name).write_text(text)

"""Standard ROS 2 messages of the session log, CDR-encoded without numpy.

Each robot's feedback becomes, beside redistro's own channel,
``sensor_msgs/msg/JointState`` on ``/<robot>/joint_states`` (the arm's joints,
named ``<robot>_<URDF joint>``: position, velocity, effort) and
``geometry_msgs/msg/WrenchStamped`` on ``/<robot>/wrench`` (the wrist
sensor, in its frame ``<robot>_tool``), stamped with the cycle's log time.
The writer process makes them (off every cycle); what is constant (the
names, the frame) is encoded once per channel. Definitions are the ROS 2
ones, with their dependencies, as rosbag2 writes them into MCAP.
"""

from __future__ import annotations

import struct
from typing import Any

from redistro.log.frames import CDR_HEADER

SEPARATOR = "=" * 80 + "\n"

_TIME = "int32 sec\nuint32 nanosec\n"
_HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
_VECTOR3 = "float64 x\nfloat64 y\nfloat64 z\n"


def _with(main: str, *deps: tuple[str, str]) -> str:
    return main + "".join(f"{SEPARATOR}MSG: {name}\n{text}" for name, text in deps)


JOINT_STATE = "sensor_msgs/msg/JointState"
JOINT_STATE_DEF = _with(
    "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\n"
    "float64[] effort\n",
    ("std_msgs/Header", _HEADER),
    ("builtin_interfaces/Time", _TIME),
)
WRENCH_STAMPED = "geometry_msgs/msg/WrenchStamped"
WRENCH_STAMPED_DEF = _with(
    "std_msgs/Header header\ngeometry_msgs/Wrench wrench\n",
    ("std_msgs/Header", _HEADER),
    ("builtin_interfaces/Time", _TIME),
    ("geometry_msgs/Wrench", "geometry_msgs/Vector3 force\ngeometry_msgs/Vector3 torque\n"),
    ("geometry_msgs/Vector3", _VECTOR3),
)

# an event (a segment's start, a message, a state change): its JSON document
EVENT = "redistro/msg/Event"
EVENT_DEF = "string json\n"

# one a cycle beside a node's timing (``/<node>/digest``): the hash of that
# cycle's logged data but its wall-clock stamps (the run's digest chains them)
CYCLE_DIGEST = "redistro/msg/CycleDigest"
CYCLE_DIGEST_DEF = "uint64 log_cycle\nuint8[16] digest\n"

# a message-box line (a worker's or the manager's text), its levels those
# of rcl_interfaces/msg/Log (and of Python's logging)
MESSAGE = "redistro/msg/Message"
MESSAGE_DEF = _with(
    "uint8 DEBUG=10\nuint8 INFO=20\nuint8 WARN=30\nuint8 ERROR=40\nuint8 FATAL=50\n"
    "builtin_interfaces/Time stamp\nuint64 cycle\nuint8 level\nstring process\nstring text\n",
    ("builtin_interfaces/Time", _TIME),
)
LEVELS = {"DEBUG": 10, "INFO": 20, "WARNING": 30, "ERROR": 40, "CRITICAL": 50}
LEVEL_NAMES = {v: k for k, v in LEVELS.items()}

_STAMP = struct.Struct("<iI")


class Cdr:
    """A CDR body being written: each value aligned to its size from the
    body's start (after the 4-byte encapsulation header)."""

    def __init__(self) -> None:
        self.buf = bytearray()

    def _align(self, n: int) -> None:
        self.buf += bytes(-len(self.buf) % n)

    def u32(self, v: int) -> None:
        self._align(4)
        self.buf += struct.pack("<I", v)

    def i32(self, v: int) -> None:
        self._align(4)
        self.buf += struct.pack("<i", v)

    def u8(self, v: int) -> None:
        self.buf.append(v)

    def f32s(self, values: Any) -> None:
        self._align(4)
        self.buf += struct.pack(f"<{len(values)}f", *values)

    def f64s(self, values: Any) -> None:
        self._align(8)
        self.buf += struct.pack(f"<{len(values)}d", *values)

    def string(self, s: str) -> None:
        data = s.encode() + b"\0"
        self.u32(len(data))
        self.buf += data

    def strings(self, items: list[str]) -> None:
        self.u32(len(items))
        for s in items:
            self.string(s)


class Feedback:
    """The standard messages of one robot's feedback channel: ``fields``
    gives each source field's offset in the packed message (q_rad,
    qd_rad_s, tau_nm: a double per joint; wrench: six)."""

    def __init__(self, robot: str, joints: list[str], fields: dict[str, int]) -> None:
        n = len(joints)
        self.seq = 8 * n  # bytes of one sequence's doubles
        self.at = tuple(int(fields[k]) for k in ("q_rad", "qd_rad_s", "tau_nm", "wrench"))
        # the JointState after its stamp: "" frame, the names (constant), then the
        # three sequences at fixed places (each a u32 count, its doubles at 8)
        tail = Cdr()
        tail.buf += bytes(8)  # (the stamp's place: alignment counts from the body's start)
        tail.string("")
        tail.strings([f"{robot}_{j}" for j in joints])
        tail._align(4)
        self.js_head = bytes(tail.buf[8:])
        self.count = struct.pack("<I", n)
        self.js_pads: list[bytes] = []
        pos = len(tail.buf)
        for _ in range(3):
            pad = -(pos + 4) % 8 if n else 0
            self.js_pads.append(bytes(pad))
            pos += 4 + pad + 8 * n
        w = Cdr()
        w.buf += bytes(8)
        w.string(f"{robot}_tool")
        w._align(8)
        self.ws_head = bytes(w.buf[8:])

    def joint_state(self, packed: bytes, log_ns: int) -> bytes:
        stamp = _STAMP.pack(log_ns // 1_000_000_000, log_ns % 1_000_000_000)
        parts = [CDR_HEADER, stamp, self.js_head]
        for at, pad in zip(self.at[:3], self.js_pads, strict=True):
            parts += [self.count, pad, packed[at : at + self.seq]]
        return b"".join(parts)

    def wrench(self, packed: bytes, log_ns: int) -> bytes:
        stamp = _STAMP.pack(log_ns // 1_000_000_000, log_ns % 1_000_000_000)
        at = self.at[3]
        return b"".join((CDR_HEADER, stamp, self.ws_head, packed[at : at + 48]))  # (6 doubles)


def event(doc_json: str) -> bytes:
    """An event's message: its JSON document as one ROS 2 string."""
    data = doc_json.encode() + b"\0"
    return CDR_HEADER + struct.pack("<I", len(data)) + data


def event_json(message: bytes) -> str:
    """The JSON document of an event's message (ValueError: not one)."""
    if len(message) < 9 or message[:4] != CDR_HEADER:
        raise ValueError("an event message without its CDR header")
    (n,) = struct.unpack_from("<I", message, 4)
    if n < 1 or 8 + n != len(message) or message[-1] != 0:
        raise ValueError("an event message whose string does not fit it")
    return message[8 : 8 + n - 1].decode("utf-8")


def message(doc: dict[str, Any]) -> bytes:
    """A message-box line's message (``doc``: the recorder's event: stamp_ns,
    cycle, level name, process, text)."""
    ns = int(doc.get("stamp_ns") or 0)
    c = Cdr()
    c.buf += _STAMP.pack(ns // 1_000_000_000, ns % 1_000_000_000)
    level = LEVELS.get(str(doc.get("level")), 0)
    c.buf += struct.pack("<QB", int(doc.get("cycle") or 0), level)
    c.string(str(doc.get("process", "")))
    c.string(str(doc.get("text", "")))
    return CDR_HEADER + bytes(c.buf)


def message_doc(data: bytes) -> dict[str, Any]:
    """A message-box line back as the recorder's event (ValueError: not one)."""
    if len(data) < 4 + 17 or data[:4] != CDR_HEADER:
        raise ValueError("a message-box line without its CDR header")
    sec, nsec = _STAMP.unpack_from(data, 4)
    cycle, level = struct.unpack_from("<QB", data, 12)
    strings, at = [], 21
    for _ in range(2):
        at += -(at - 4) % 4
        if at + 4 > len(data):
            raise ValueError("a message-box line cut short")
        (n,) = struct.unpack_from("<I", data, at)
        if n < 1 or at + 4 + n > len(data) or data[at + 4 + n - 1] != 0:
            raise ValueError("a message-box line whose strings do not fit it")
        strings.append(data[at + 4 : at + 4 + n - 1].decode("utf-8"))
        at += 4 + n
    return {
        "cycle": cycle,
        "level": LEVEL_NAMES.get(level, str(level)),
        "process": strings[0],
        "text": strings[1],
        "stamp_ns": sec * 1_000_000_000 + nsec,
    }

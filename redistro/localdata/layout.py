"""The Local Data layout, declared once as numpy structured dtypes.

A segment is a sequence of blocks, each at a 64-byte (cache-line) boundary so
that two writers never share a line. Every dynamic block is *seqlocked*: a
``seq`` counter (odd while its single writer is writing) precedes the payload.
The table :data:`WRITERS` names the one process role allowed to write each
block, per node kind; :mod:`redistro.localdata.segment` enforces it.

Units are in the field names: ``_rad``, ``_rad_s``, ``_nm`` (N m), ``_n`` (N),
``_ns`` (CLOCK_MONOTONIC nanoseconds unless noted).
"""

from __future__ import annotations

import enum
import functools
import hashlib
from typing import Any

import numpy as np

MAGIC = b"RDSTLD01"
VERSION = 1
DOF = 7
MAX_PROCS = 16
MAX_ROBOTS = 16  # an SSC node's robots (the plant's bank drives at most 4: drivers/io/bank.py)
MSGBOX_SLOTS = 16
MSG_TEXT = 112
NAME = "S16"
ALIGN = 64


class ProcState(enum.IntEnum):
    """The four process states of the runtime (plus NONE before a process starts)."""

    NONE = 0
    INITIALIZATION = 1
    ROUTINE = 2
    CLEANUP = 3
    IDLE = 4


class SessionStatus(enum.IntEnum):
    NONE = 0
    IN_PROGRESS = 1
    FINISHED = 2


def _padded(dtype: np.dtype[Any], align: int = ALIGN) -> np.dtype[Any]:
    """The same fields at the same offsets, itemsize rounded up to ``align``."""
    fields = dtype.fields
    assert fields is not None and dtype.names is not None
    return _dtype_of(
        list(dtype.names),
        [fields[n][0] for n in dtype.names],
        [fields[n][1] for n in dtype.names],
        -(-dtype.itemsize // align) * align,
    )


def _dtype_of(names: list[str], formats: list[Any], offsets: list[int], size: int) -> np.dtype[Any]:
    spec: dict[str, Any] = {
        "names": names,
        "formats": formats,
        "offsets": offsets,
        "itemsize": size,
    }
    return np.dtype(spec)  # type: ignore[call-overload,no-any-return]


def seqlocked(payload: np.dtype[Any]) -> np.dtype[Any]:
    """A block: ``seq`` (u8, odd during a write) then ``data``, padded to 64 bytes."""
    return _padded(np.dtype([("seq", "<u8"), ("data", payload)]))


# -- header and static data (written once by the manager before any attach) --

HEADER = np.dtype(
    [
        ("magic", "S8"),
        ("layout_hash", "<u8"),
        ("version", "<u4"),
        ("n_procs", "<u4"),
        ("n_robots", "<u4"),
        ("creator_pid", "<i4"),
        ("created_unix_ns", "<i8"),  # CLOCK_REALTIME, for people
        ("session_id", "S32"),
        ("node", "S32"),
    ]
)


def static_dtype(n_procs: int, n_robots: int) -> np.dtype[Any]:
    return np.dtype(
        [
            ("rate_hz", "<f8"),
            ("period_ns", "<i8"),
            ("heartbeat_limit_cycles", "<u4"),
            ("node_kind", NAME),
            ("proc_names", NAME, (n_procs,)),
            ("proc_roles", NAME, (n_procs,)),
            ("proc_stage", "<i4", (n_procs,)),
            ("robot_names", NAME, (n_robots,)),
        ]
    )


# -- local dynamic data --

MANAGER = np.dtype(
    [
        ("state", "u1"),
        ("estop", "u1"),
        ("cycle", "<u8"),  # cycles the manager has run (one per tick taken)
        ("tick_due_ns", "<i8"),  # when the current cycle's tick was due
        ("tick_ns", "<i8"),  # when the manager took it
        ("overruns", "<u8"),  # ticks taken more than one period late
        ("missed_ticks", "<u8"),  # ticks that passed unseen (coalesced) in those overruns
        ("pid", "<i4"),
        ("fault_reason", NAME),  # the node's termination reason, set at its first fault
        ("fault_text", f"S{MSG_TEXT}"),  # ... and the message naming the cause
    ]
)

PROC_STATUS = np.dtype(
    [
        ("pid", "<i4"),
        ("state", "u1"),
        ("estop_request", "u1"),
        ("sched_policy", "u1"),  # redistro.ipc.sched.POLICY_CODES
        ("sched_priority", "<i2"),
        ("nice", "<i2"),
        ("cpu_mask", "<u8"),
        ("heartbeat_cycle", "<u8"),  # last manager cycle this process completed
        ("wake_ns", "<i8"),
        ("done_ns", "<i8"),
        ("cycles", "<u8"),
        ("overruns", "<u8"),  # wake-ups that found more than one sync queued
        ("skipped", "<u8"),  # the extra syncs found then: cycles this process did not run
        (
            "stage_timeouts",
            "<u8",
        ),  # cycles skipped: a previous stage did not finish, or no consistent input
        ("torn_reads", "<u8"),  # snapshot attempts that had to be retried
        ("idle_slices", "<u8"),  # slices of Idle work run between cycles
        ("idle_late", "<u8"),  # ... of which ended past their deadline (a host stall)
        ("cpu_s", "<f8"),  # CPU time spent in Routine (written at Cleanup)
        ("lateness_us", "<f4", (3,)),  # p50, p99, max over the run (written at Cleanup)
        ("compute_us", "<f4", (3,)),  # per step, wall time (preemption included)
        ("step_cpu_us", "<f4", (3,)),  # per step, this thread's CPU time: what a step costs
    ]
)

MSG_SLOT = _padded(
    np.dtype(
        [
            ("seq", "<u8"),
            ("number", "<u8"),  # which message (0, 1, 2, ...) the slot holds
            ("stamp_ns", "<i8"),
            ("level", "u1"),
            ("text", f"S{MSG_TEXT}"),
        ]
    )
)
MSGBOX = _padded(np.dtype([("head", "<u8"), ("slots", MSG_SLOT, (MSGBOX_SLOTS,))]))

EXCHANGE = np.dtype(  # data exchange status, per robot: the data from the other node (ddm)
    [
        ("updates", "<u8"),  # fresh records admitted and written to Local Data
        ("last_update_ns", "<i8"),
        ("dropped", "<u8"),  # records refused, all reasons
        ("fresh", "u1"),
        ("sent", "<u8"),  # records sent to the other node
        ("malformed", "<u8"),  # refused by decode (size, magic, version, kind, checksum)
        ("duplicate", "<u8"),
        ("out_of_order", "<u8"),
        ("stale", "<u8"),
        ("estop_in", "u1"),  # an e-stop came in from the other node
        ("estop_source", NAME),  # ... from this node
        ("link_lost", "u1"),
        ("latency_us", "<f4", (3,)),  # command: SSC Local Data write -> here (p50, p99, max)
        ("latency_n", "<u8"),
        # an ESC's ddm: wake it for each new sample (0 while it only replies to commands)
        ("feedback_wanted", "u1"),
        ("forged", "<u8"),  # well-formed, but not signed with the link's key (auth)
        ("foreign", "<u8"),  # connections refused: the link already had its peer
        ("linked", "u1"),  # the link's handshake is done: records flow both ways
    ]
)
COUNTER = np.dtype([("count", "<u8"), ("stamp_ns", "<i8")])
HOME = np.dtype(  # home switches and the encoder latches taken on their edges
    [
        ("stamp_ns", "<i8"),  # when the boards were read
        ("step", "<u8"),  # the boards' sample number (plant step on the simulated chassis)
        ("home_switch", "u1", (DOF,)),
        ("latch_count", "<u4", (DOF,)),  # home-edge latches so far (a new one: count changed)
        ("latch_edge", "u1", (DOF,)),  # 1 rising (switch came on), 2 falling, of the last latch
        ("latch_q_rad", "<f8", (DOF,)),  # joint position captured at the last latch [rad]
        ("offset_rad", "<f8", (DOF,)),  # zero offset taken out of every published q [rad]
        ("offset_seq", "<u4"),  # the calibration request whose offset is applied (0: none)
    ]
)

# -- ESC local dynamic data --

SETPOINT = np.dtype(  # the joint reference of ESC-local motion (self-calibration, positioning)
    [
        ("stamp_ns", "<i8"),
        ("cycle", "<u8"),  # manager cycle this setpoint belongs to
        ("q_rad", "<f8", (DOF,)),
        ("qd_rad_s", "<f8", (DOF,)),
        ("qdd_rad_s2", "<f8", (DOF,)),
        ("joint_on", "u1", (DOF,)),  # joints under control (their brakes released)
        ("segment", "u1"),  # 1-based index of the running segment; 0 before the first
        ("segment_t_s", "<f8"),  # time into that segment [s] (past the last one: settling)
        ("done", "u1"),  # 1: every segment finished, the session may end
        ("failed", "u1"),  # 1: the segments cannot go on (the reason is in the message box)
        ("offset_rad", "<f8", (DOF,)),  # zero offsets the acquisition is asked to apply [rad]
        ("offset_seq", "<u4"),  # request number of offset_rad (0: no request)
    ]
)
CALIBRATION = np.dtype(  # what the self-calibration found, per joint
    [
        ("edges", "u1", (DOF,)),  # home-switch edges seen in the sweeps
        ("found", "u1", (DOF,)),  # 1: the zero offset of this joint was found
        ("offset_found_rad", "<f8", (DOF,)),  # measured home position - configured home angle
        ("applied", "u1"),  # 1: the acquisition applies the offsets
    ]
)
CONTROL = np.dtype(  # the ESC's own control output (joint PID + gravity)
    [
        ("stamp_ns", "<i8"),
        ("cycle", "<u8"),
        ("tau_nm", "<f8", (DOF,)),
        ("joint_on", "u1", (DOF,)),
    ]
)
GUARD = np.dtype(  # the safety guard: what the sender sent, and whether it tripped
    [
        ("cycle", "<u8"),  # last cycle the sender ran the checks
        ("sent_cycle", "<u8"),  # last cycle a command went out
        ("tau_nm", "<f8", (DOF,)),  # torques sent [N m]
        ("released", "u1", (DOF,)),  # brakes the sender released
        ("tripped", "u1"),  # 1: a limit was violated; the robot is frozen
        ("trip_cycle", "<u8"),
        ("trip_step", "<u8"),  # board sample number of the offending feedback
        ("trip_ns", "<i8"),  # CLOCK_MONOTONIC when the sender froze the robot
        ("trip_joint", "i1"),  # 0-based joint, -1 for the wrist
        ("trip_value", "<f8"),
        ("trip_limit", "<f8"),
        ("trip_quantity", "S24"),
        ("trip_text", f"S{MSG_TEXT}"),
    ]
)

# -- local copy of Robot Group Shared Data, per robot --

COMMAND = np.dtype(
    [
        ("stamp_ns", "<i8"),  # command time stamp (when the command was produced)
        ("seq_src", "<u8"),  # the producer's command counter
        ("tau_nm", "<f8", (DOF,)),  # joint torque commands [N m]
        ("q_cmd_rad", "<f8", (DOF,)),  # joint position commands [rad]
        ("joint_on", "u1", (DOF,)),
        ("session_status", "u1"),  # SessionStatus
        ("gripper", "u1"),  # 1: the flange's gripper closed, 0: open
    ]
)
FEEDBACK = np.dtype(
    [
        ("stamp_ns", "<i8"),  # sampling time stamp
        ("seq_src", "<u8"),
        ("q_rad", "<f8", (DOF,)),
        ("qd_rad_s", "<f8", (DOF,)),
        ("tau_nm", "<f8", (DOF,)),  # joint torques [N m]
        ("wrench", "<f8", (6,)),  # wrist sensor: force [N] and torque [N m], sensor frame
        ("estop", "u1"),
        ("step", "<u8"),  # the boards' sample number (the plant's step on the simulated chassis)
    ]
)
PLAN = np.dtype(  # the SSC's view of one robot: segment, references, errors (worker)
    [
        ("stamp_ns", "<i8"),
        ("cycle", "<u8"),
        ("t_s", "<f8"),  # task time on the boards' sample clock [s]
        ("segment", "u1"),  # 1-based index of the running segment (0: before, 255: after)
        ("segment_t_s", "<f8"),
        ("moving", "u1"),  # 1: the segment moves this robot; 0: it holds its pose
        ("scheme", "u1"),  # 0 hold, 1 joint, 2 position, 3 force
        ("contact", "u1"),  # force segments: contact felt
        ("done", "u1"),  # 1: every segment finished
        ("failed", "u1"),  # 1: the task could not be done (the reason is in the message box)
        ("tcp_xyz_m", "<f8", (3,)),  # TCP position, world [m]
        ("tcp_rot_xyz", "<f8", (3,)),  # TCP rotation vector, world [rad]
        ("goal_xyz_m", "<f8", (3,)),
        ("goal_rot_xyz", "<f8", (3,)),
        ("ref_xyz_m", "<f8", (3,)),  # the reference the law tracked this cycle
        ("wrench_task", "<f8", (6,)),  # applied wrench, task axes [N, N m]
        ("wrench_goal", "<f8", (6,)),
        ("selection", "u1", (6,)),
        ("q_goal_rad", "<f8", (DOF,)),
        ("phase", "u1"),  # a force segment's search (control.search.Phase): 0 none, 1 descent, ...
        ("search_xy_m", "<f8", (2,)),  # the search's goal offset from the believed centre [m]
        ("search_m", "<f8"),  # the search's path so far [m]
        ("arms_clearance_m", "<f8"),  # the SSC's watch: the two arms' nearest links [m]
        ("cell_clearance_m", "<f8"),  # ... and the nearest link to the work-cell (not the tool)
        ("paused", "u1"),  # 1: the operator paused the task; every robot holds
        ("op_seq", "<u4"),  # the operator's last command the worker took (ssc/operator.py) ...
        ("op_command", "u1"),  # ... what it was (ssc/ctl.py: Command) ...
        ("op_status", "u1"),  # ... and how it ended (ssc/ctl.py: Status; 0 while under way)
        ("paused_s", "<f8"),  # task time paused so far [s] (the owner's budget adds it)
    ]
)

SSC_CLOCK = np.dtype(  # the task's clock, when each arm's law runs in a worker of its own
    [
        ("cycle", "<u8"),  # the cycle whose end decided it (the arms take it in the next)
        ("started", "u1"),  # 1: every robot reported; the task runs
        ("t0_step", "<u8"),  # the boards' sample number at the task's start
        ("segment", "<i4"),  # the running segment (0-based; len(segments): settling)
        ("seg_start_t_s", "<f8"),  # when it began [s, task time]
        ("done", "u1"),
        ("failed", "u1"),  # 1: the task could not be done; every arm holds
        ("fail_robot", "i1"),  # a robot whose search the segment's end found open (-1: none) ...
        ("fail_t_s", "<f8"),  # ... then [s, task time]
        ("arms_clearance_m", "<f8"),  # the watch's (ssc/clearance.py)
        ("cell_clearance_m", "<f8"),
    ]
)

OPERATOR = np.dtype(  # the operator's latest command, as the SSC manager took it (ssc/ctl.py)
    [
        ("seq", "<u4"),  # commands accepted so far: the latest's number
        ("command", "u1"),  # ssc/ctl.py: Command
        ("robot", "u1"),  # a jog's robot (index in the group)
        ("step", "<f8", (6,)),  # a jog's step: [m] along world x, y, z; [rad] about them
        ("cycle", "<u8"),  # the manager's cycle when it took it
        ("refused", "<u4"),  # commands refused so far (a bad signature, a replay, bad data)
        ("refused_why", "S48"),  # ... the last one's reason
    ]
)

# block name -> (payload dtype, count kind): "one", "proc" (per process), "robot" (per robot)
BLOCKS: dict[str, tuple[np.dtype[Any], str]] = {
    "manager": (MANAGER, "one"),
    "proc": (PROC_STATUS, "proc"),
    "exchange": (EXCHANGE, "robot"),
    "starving_sent": (COUNTER, "one"),
    "starving_delivered": (COUNTER, "one"),
    "command_stamp": (COUNTER, "one"),
    "home": (HOME, "robot"),
    "command": (COMMAND, "robot"),
    "feedback": (FEEDBACK, "robot"),
    "setpoint": (SETPOINT, "robot"),
    "calibration": (CALIBRATION, "robot"),
    "control": (CONTROL, "robot"),
    "guard": (GUARD, "robot"),
    "plan": (PLAN, "robot"),
    "clock": (SSC_CLOCK, "one"),
    "operator": (OPERATOR, "one"),
}

SELF = "<self>"
"""Writer of a per-process block: the process that owns that row."""

# block -> node kind -> role of its one writer. "*" applies to any node kind.
WRITERS: dict[str, dict[str, str]] = {
    "manager": {"*": "manager"},
    "proc": {"*": SELF},
    "msgbox": {"*": SELF},
    "exchange": {"*": "ddm"},
    "starving_sent": {"*": "sender"},
    "starving_delivered": {"*": "ddm"},
    "command_stamp": {"*": "sender"},
    "home": {"*": "acquisition"},
    "command": {"esc": "ddm", "ssc": "worker", "bench": "busy"},
    "feedback": {"esc": "acquisition", "ssc": "ddm", "bench": "busy"},
    "setpoint": {"esc": "calibration"},
    "calibration": {"esc": "calibration"},
    "control": {"esc": "pid"},
    "guard": {"esc": "sender"},
    "plan": {"ssc": "worker"},
    "clock": {"ssc": "worker"},
    "operator": {"ssc": "manager"},
}


@functools.cache
def segment_dtype(n_procs: int, n_robots: int) -> np.dtype[Any]:
    """The whole segment for a node with ``n_procs`` processes and ``n_robots`` robots.
    Kept (a dtype is immutable): every attach asks for it, and a watcher
    polling for a node's segment would build it again each time."""
    if not 1 <= n_procs <= MAX_PROCS:
        raise ValueError(f"n_procs must be 1..{MAX_PROCS}, got {n_procs}")
    if not 0 <= n_robots <= MAX_ROBOTS:
        raise ValueError(f"n_robots must be 0..{MAX_ROBOTS}, got {n_robots}")
    fields: list[tuple[str, np.dtype[Any], tuple[int, ...]]] = [
        ("header", _padded(HEADER), ()),
        ("static", _padded(static_dtype(n_procs, n_robots)), ()),
    ]
    counts = {"one": (), "proc": (n_procs,), "robot": (n_robots,)}
    for name, (payload, kind) in BLOCKS.items():
        fields.append((name, seqlocked(payload), counts[kind]))
        if name == "proc":
            fields.append(("msgbox", MSGBOX, (n_procs,)))
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    offset = 0
    for name, dt, shape in fields:
        names.append(name)
        formats.append((dt, shape) if shape else dt)
        offsets.append(offset)
        count = int(np.prod(shape)) if shape else 1
        offset += -(-dt.itemsize * count // ALIGN) * ALIGN
    return _dtype_of(names, formats, offsets, offset)


@functools.cache
def layout_hash(n_procs: int, n_robots: int) -> int:
    """A 64-bit hash of the declared layout; attach refuses a segment that
    differs. Kept: a view that attaches every few milliseconds (the owner
    waiting for its ESCs, ``redistro top``) would spend 6 ms on each."""
    descr = repr(segment_dtype(n_procs, n_robots).descr) + f"v{VERSION}"
    return int.from_bytes(hashlib.sha256(descr.encode()).digest()[:8], "little")

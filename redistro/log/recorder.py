"""The recording side of the session log, inside a node's logging worker.

The manager captures every cycle's logged blocks and the processes' status
rows into the node's log ring (:mod:`redistro.log.ring`). Whenever the
logging worker runs, :meth:`CycleRecorder.drain` takes every cycle of the
ring it has not recorded yet and sends each as one frame into a pipe, one
non-blocking write each. A separate, non-real-time writer process
(:mod:`redistro.log.writer`) drains the pipe into ``<node>.mcap`` in the run
folder: it cuts each frame into one message per channel and turns the
status rows into the timing message. So recording never waits on the file,
and neither a logging worker held off for a while nor a writer fallen
behind (the pipe full: the drain stops, the cycles wait in the ring) loses
anything, up to the ring's length; a cycle overwritten in the ring before it
was sent is missing from the count of frames recorded. At the end, ``dropped = the
manager's cycles - frames recorded``.

Events (segment changes, message-box text, the node's fault) go through the
same pipe as JSON; e-stops and process state changes the writer finds in
the frames.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from redistro.localdata import LocalData, MessageBox
from redistro.localdata.block import Record
from redistro.localdata.layout import BLOCKS, MANAGER, PROC_STATUS
from redistro.log import schema
from redistro.log.frames import FRAME, KIND_CYCLE, KIND_END, KIND_EVENT, KIND_HEADER
from redistro.log.ring import FRAME_HEAD, LogRing, RingLayout
from redistro.process.spawn import THREAD_ENV
from redistro.process.spec import NodeSpec

log = logging.getLogger(__name__)

PIPE_BUF = 4096  # a pipe write up to this size is all-or-nothing
PIPE_BYTES = 1 << 20  # asked for; the kernel may give less (fs.pipe-max-size)
WRITER_WAIT_S = 10.0
EVENT_WAIT_S = 2.0  # in lockstep, the longest an event waits for room in the pipe
RECORDERS = ("recorder", "logger")  # the logging workers' roles


def log_topics(spec: NodeSpec) -> list[tuple[str, str, int | None]]:
    """The channels a node logs, (topic, block, robot index); [] when it has
    no logging worker (or no run folder to log into)."""
    roles = {w.role: w for w in spec.workers}
    if "logger" in roles and spec.node_params.run_dir:  # the SSC
        topics: list[tuple[str, str, int | None]] = []
        for i, r in enumerate(spec.robots):
            topics += [
                (f"/{r}/feedback", "feedback", i),
                (f"/{r}/command", "command", i),
                (f"/{r}/plan", "plan", i),
            ]
        return topics
    if "recorder" in roles and spec.robots:  # an ESC of an ESC-only session
        r = spec.robots[0]
        return [
            (f"/{r}/feedback", "feedback", 0),
            (f"/{r}/setpoint", "setpoint", 0),
            (f"/{r}/control", "control", 0),
            (f"/{r}/guard", "guard", 0),
        ]
    return []


def digest_runs(dtype: np.dtype[Any]) -> list[tuple[int, int]]:
    """The byte runs of a logged message (log_cycle, then the block's fields)
    that a run's digest covers: all but the wall-clock stamps (``*_ns``)."""
    fields: dict[str, Any] = dict(dtype.fields or {})
    skips = sorted(
        (int(off), int(off) + ft.itemsize)
        for name, (ft, off, *_) in fields.items()
        if name.endswith("_ns")
    )
    runs: list[tuple[int, int]] = []
    at = 0
    for a, b in skips:
        if a > at:
            runs.append((at, a))
        at = max(at, b)
    if at < dtype.itemsize:
        runs.append((at, int(dtype.itemsize)))
    return runs


@dataclass
class Channel:
    topic: str
    dtype: np.dtype[Any]  # the message: log_cycle, then the block's fields
    offset: int  # of the block's payload in the frame payload
    block: str = ""  # the Local Data block's name

    @property
    def size(self) -> int:
        return int(self.dtype.itemsize) - 8


class CycleRecorder:
    """Records one node's cycles: ``topics`` are (topic, block name, robot index)."""

    def __init__(
        self,
        ld: LocalData,
        spec: NodeSpec,
        topics: list[tuple[str, str, int | None]],
        run_dir: str,
        meta: dict[str, Any],
    ) -> None:
        self.ld = ld
        self.spec = spec
        self.node = spec.node
        self.path = os.path.join(run_dir, f"{spec.node}.mcap")
        n = len(spec.workers)
        self.layout = RingLayout.of(topics, n)
        self.channels = [
            Channel(topic, schema.with_cycle(BLOCKS[name][0]), at, name)
            for (topic, name, _i), (_n, _x, at, _size) in zip(
                topics, self.layout.blocks, strict=True
            )
        ]
        self.timing_dtype = schema.timing_dtype(n)
        self.frame = bytearray(FRAME.size + self.layout.payload)
        if len(self.frame) > PIPE_BUF:
            raise ValueError(
                f"a cycle frame of {len(self.frame)} bytes does not fit one pipe write"
            )
        FRAME.pack_into(self.frame, 0, self.layout.payload, KIND_CYCLE, 0)
        self.mv = memoryview(self.frame)
        self.payload = self.mv[FRAME.size :]
        self.ring: LogRing | None = None
        self.manager = ld.block("manager")
        self.mrec = Record(MANAGER)
        self.boxes: list[MessageBox] = [ld.msgbox(j) for j in range(n)]
        self.names = [w.name for w in spec.workers]
        self.realtime_offset_ns = time.time_ns() - time.monotonic_ns()
        self.recorded = 0
        self.pipe_full = 0  # drains stopped by a full pipe (the cycles waited in the ring)
        self.overwritten = 0
        self.next = 1  # the next cycle to record
        self.events = 0
        self.events_dropped = 0
        self.first_cycle = 0
        self.last_cycle = 0
        self.meta = meta
        self.fd = -1
        self.proc: subprocess.Popen[bytes] | None = None

    def view(self, topic: int, dtype: np.dtype[Any]) -> Record:
        """Channel ``topic``'s block in the frame being recorded, as a record
        in place (what :meth:`drain`'s ``on_cycle`` reads)."""
        return Record(dtype, self.frame, FRAME.size + self.channels[topic].offset)

    # -- start / end --

    def start(self) -> None:
        """Start the writer process and send it the channels (before any cycle)."""
        rfd, wfd = os.pipe2(os.O_CLOEXEC)
        with contextlib.suppress(OSError):
            fcntl.fcntl(wfd, fcntl.F_SETPIPE_SZ, PIPE_BYTES)
        env = os.environ.copy()
        env.update(THREAD_ENV)
        ready_r, ready_w = os.pipe2(os.O_CLOEXEC)
        try:
            self.proc = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "redistro.process",
                    "logwriter",
                    "--fd",
                    str(rfd),
                    "--out",
                    self.path,
                    "--ready-fd",
                    str(ready_w),
                ],
                env=env,
                pass_fds=(rfd, ready_w),
                close_fds=True,
                stdin=subprocess.DEVNULL,
            )
        finally:
            os.close(rfd)
            os.close(ready_w)
        self.fd = wfd
        # the writer's imports take a while: the cycles start once it reads
        self._wait_ready(ready_r)
        rows = PROC_STATUS.fields
        assert rows is not None
        header = {
            "node": self.node,
            "session": self.spec.session_id,
            "rate_hz": self.spec.rate_hz,
            "processes": self.names,
            "roles": [w.role for w in self.spec.workers],
            "meta": self.meta,
            "frame": {"head": FRAME_HEAD.format, "cycle": 0, "due": 8, "tick": 16, "estop": 24},
            "channels": [
                {
                    "topic": c.topic,
                    "schema": schema.type_name(c.block),
                    "definition": schema.msg_definition(c.dtype),
                    "runs": schema.cdr_runs(c.dtype),
                    "ros2": _standard(c),
                    "offset": c.offset,
                    "size": c.size,
                    "digest": digest_runs(c.dtype),
                }
                for c in self.channels
            ],
            "timing": {
                "topic": f"/{self.node}/timing",
                "schema": schema.type_name(f"timing{len(self.names)}"),
                "definition": schema.msg_definition(self.timing_dtype),
                "format": schema.cdr_struct(self.timing_dtype),
                "rows_offset": self.layout.rows_offset,
                "row_size": PROC_STATUS.itemsize,
                "fields": {
                    name: [int(rows[name][1]), rows[name][0].str]
                    for name in (
                        "heartbeat_cycle",
                        "wake_ns",
                        "done_ns",
                        "overruns",
                        "skipped",
                        "state",
                    )
                },
                "on_cycle": [w.on_cycle for w in self.spec.workers],
            },
        }
        self._send_blocking(KIND_HEADER, json.dumps(header).encode())
        os.set_blocking(wfd, False)
        self.ring = LogRing.attach(self.spec.session_id, self.node, self.layout)

    def _wait_ready(self, fd: int) -> None:
        import select

        try:
            poller = select.poll()
            poller.register(fd, select.POLLIN)
            deadline = time.monotonic() + WRITER_WAIT_S
            while time.monotonic() < deadline:
                if poller.poll(100):
                    os.read(fd, 1)
                    return
                if self.proc is not None and self.proc.poll() is not None:
                    return  # it died: the frames will be dropped and counted
            log.warning("log writer of %s not ready in %s s", self.node, WRITER_WAIT_S)
        finally:
            os.close(fd)

    def close(self, on_cycle: Any = None) -> dict[str, Any]:
        """Record what is left in the ring (``on_cycle`` as in :meth:`drain`),
        send the counters and the node's fault, close the pipe, wait for the
        writer."""
        if self.fd < 0:
            return {}
        final = self.last_cycle
        with contextlib.suppress(Exception):
            # Cleanup is off real time: what is left in the ring may wait for
            # the writer (a drain on a full pipe would stop short: the
            # worker's own figures would miss the last cycles)
            os.set_blocking(self.fd, True)
            self.drain(on_cycle)  # what the manager captured since the last cycle we ran
            self.manager.read_into(self.mrec.bytes)
            final = max(final, int(self.mrec["cycle"]))
            self._messages(final)
            self._fault_event()
        stats = {
            "node": self.node,
            "cycles": final,
            "recorded": self.recorded,
            "dropped": max(0, final - self.recorded),
            "pipe_full": self.pipe_full,
            "overwritten": self.overwritten,
            "first_cycle": self.first_cycle,
            "last_cycle": self.last_cycle,
            "events": self.events,
            "events_dropped": self.events_dropped,
        }
        try:
            os.set_blocking(self.fd, True)
            self._send_blocking(KIND_END, json.dumps(stats).encode())
        except OSError:
            log.debug("log writer gone before the end record", exc_info=True)
        finally:
            os.close(self.fd)
            self.fd = -1
            if self.ring is not None:
                self.ring.close()
                self.ring = None
        if self.proc is not None:
            try:
                self.proc.wait(WRITER_WAIT_S)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
                stats["writer"] = "killed"
        return stats

    # -- every cycle --

    def drain(self, on_cycle: Any = None) -> int:
        """Record every cycle the manager has captured and this recorder has
        not: one frame each into the pipe (a full pipe drops and counts it).
        ``on_cycle(cycle)`` runs for each cycle recorded, its blocks then in
        the frame (see :meth:`view`). Returns how many cycles it took."""
        ring = self.ring
        if ring is None:
            return 0
        captured = ring.captured
        c = self.next
        if captured - c >= ring.slots:  # held off longer than the ring: those are gone
            self.overwritten += captured - ring.slots + 1 - c
            c = captured - ring.slots + 1
        taken = 0
        frame, payload = self.frame, self.payload
        while c <= captured:
            if ring.read(c, payload):
                due = FRAME_HEAD.unpack_from(payload, 0)[1]
                FRAME.pack_into(
                    frame, 0, self.layout.payload, KIND_CYCLE, due + self.realtime_offset_ns
                )
                try:
                    os.write(self.fd, frame)
                except BlockingIOError:
                    # the writer is behind: this cycle and the rest stay in
                    # the ring for the next drain (lost only if overwritten)
                    self.pipe_full += 1
                    break
                self.recorded += 1
                if not self.first_cycle:
                    self.first_cycle = c
                self.last_cycle = c
                if on_cycle is not None:
                    on_cycle(c)
                taken += 1
            else:
                self.overwritten += 1
            c += 1
        self.next = c
        ring.drained = c - 1
        if taken:
            self._messages(captured)
        return taken

    def _messages(self, cycle: int = 0) -> None:
        for name, box in zip(self.names, self.boxes, strict=True):
            for stamp_ns, level, text in box.drain():
                self.event(
                    "messages",
                    cycle,
                    process=name,
                    level=str(logging.getLevelName(level)),
                    text=text,
                    stamp_ns=stamp_ns,
                )

    def _fault_event(self) -> None:
        reason = self.mrec.array["fault_reason"].item().decode(errors="replace")
        if reason:
            text = self.mrec.array["fault_text"].item().decode(errors="replace")
            self.event("events", int(self.mrec["cycle"]), event="fault", reason=reason, text=text)

    def event(self, topic: str, cycle: int, **fields: Any) -> None:
        """A JSON event on ``/<node>/<topic>`` (dropped and counted if the pipe is full)."""
        body = json.dumps({"topic": f"/{self.node}/{topic}", "cycle": cycle, **fields}).encode()
        frame = FRAME.pack(len(body), KIND_EVENT, time.time_ns()) + body
        if len(frame) > PIPE_BUF:  # could be split by a non-blocking write: never sent
            self.events_dropped += 1
            return
        # (lockstep: an event waits for room in the pipe, up to EVENT_WAIT_S:
        # ticks as fast as the CPUs go may starve the writer, and nothing of
        # a lockstep run's log is dropped)
        waits = 1 if self.spec.clock == "lockstep" else 0
        while True:
            try:
                os.write(self.fd, frame)
                self.events += 1
                return
            except BlockingIOError:
                if not waits or not self._writable():
                    self.events_dropped += 1
                    return
                waits -= 1

    def _writable(self) -> bool:
        """The pipe has room again within ``EVENT_WAIT_S``."""
        import select

        poller = select.poll()
        poller.register(self.fd, select.POLLOUT)
        return bool(poller.poll(int(EVENT_WAIT_S * 1000)))

    def _send_blocking(self, kind: int, body: bytes) -> None:
        data = FRAME.pack(len(body), kind, time.time_ns()) + body
        view = memoryview(data)
        while view:
            n = os.write(self.fd, view)
            view = view[n:]


def _standard(c: Channel) -> dict[str, Any] | None:
    """What the writer needs to make a feedback channel's standard ROS 2
    messages (redistro.log.ros2) and its transforms (redistro.log.scene),
    or a plan's goal frame: the robot, its joints, where the fields are."""
    if c.block not in ("feedback", "plan"):
        return None
    from redistro.robotmodel import JOINT_NAMES

    fields = c.dtype.fields
    assert fields is not None
    plan = c.block == "plan"
    want = ("goal_xyz_m", "goal_rot_xyz") if plan else ("q_rad", "qd_rad_s", "tau_nm", "wrench")
    return {
        "kind": c.block,
        "robot": c.topic.strip("/").split("/")[0],
        "joints": list(JOINT_NAMES),
        "fields": {k: int(fields[k][1]) for k in want},
    }


def robots_meta(cfg: Any, robots: list[str]) -> dict[str, Any]:
    """What the inspection tools need to redo the kinematics: per robot its
    base and tool (peg or sensor plate), and the boards' sample rate."""
    from redistro.config.model import FIXTURE_FLOOR_M, TABLE_HALF_XY_M, table_top_m

    peg, hole = cfg.workcell.peg, cfg.workcell.hole
    return {
        "physics_hz": cfg.plant.physics_hz,
        "workcell": {  # as drawn: what the controller believes (the log's 3D scene)
            "table_top_m": table_top_m(hole),
            "table_half_xy_m": list(TABLE_HALF_XY_M),
            "table_x_m": hole.xyz_m[0],
            "hole": {
                "xyz_m": list(hole.xyz_m),
                "side_m": peg.side_m + hole.clearance_m,
                "wall_m": hole.wall_m,
                "depth_m": hole.depth_m,
                "floor_m": FIXTURE_FLOOR_M,
            },
            "objects": {
                name: {"size_xyz_m": list(o.size_xyz_m), "xy_m": list(o.xy_m), "yaw_deg": o.yaw_deg}
                for name, o in cfg.workcell.objects.items()
            },
        },
        "robots": {
            r: {
                "base_xyz_m": list(cfg.robots[r].base_xyz_m),
                "peg": [peg.side_m, peg.length_m, peg.mass_kg] if cfg.robots[r].peg else None,
            }
            for r in robots
        },
    }

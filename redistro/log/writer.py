"""The log writer process: drains a node's recording pipe into an MCAP file.

It runs at the default (non-real-time) priority, started by the node's
logging worker (:mod:`redistro.log.recorder`) with the read end of the pipe.
The first frame names the channels; cycle frames are cut into one message
per channel; event frames are JSON messages; the end frame carries the
recorder's counters. At end of file (the worker closed the pipe, or died)
the file is finished: summary, indexes, the counters as metadata, and a
``<node>.log.json`` sidecar for the session summary.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import struct
import time
from pathlib import Path
from typing import IO, Any

from redistro.log import ros2
from redistro.log.frames import (
    CDR_HEADER,
    FRAME,
    KIND_CYCLE,
    KIND_END,
    KIND_EVENT,
    KIND_HEADER,
    STRUCT_CODES,
)

CHUNK_BYTES = 256 * 1024
DIGEST_DEF = ros2.CYCLE_DIGEST_DEF.encode()
PACE_S = 0.01  # after a read that emptied the pipe, the next waits this long


class PacedPipe(io.RawIOBase):
    """The pipe's read end, read in batches. A reader asleep in ``read``
    makes every write into the pipe wake it: the recording worker (real
    time, every cycle) paid that wake-up, a cross-CPU one on a VM, inside
    its ``os.write``. After a read that took all there was, the next read
    waits ``PACE_S`` first: the frames of about ten 1 kHz cycles then wait
    in the pipe (its size is far more), the worker's writes find nobody to
    wake, and the writer wakes 100 times a second instead of once a cycle."""

    def __init__(self, fd: int) -> None:
        super().__init__()
        self.fd = fd
        self.emptied = False

    def readable(self) -> bool:
        return True

    def readinto(self, b: Any) -> int:
        if self.emptied:
            time.sleep(PACE_S)
        n = os.readv(self.fd, [b])
        self.emptied = n < len(b)
        return n

    def close(self) -> None:
        if not self.closed:
            os.close(self.fd)
        super().close()


def _read_exact(f: IO[bytes], n: int) -> bytes | None:
    data = f.read(n)
    if data is None or len(data) < n:
        return None  # end of file (a frame cut short by a dying recorder is dropped)
    return data


def run_writer(fd: int, out: str, ready_fd: int = -1) -> int:
    """Write the frames the pipe ``fd`` brings into the MCAP file ``out``."""
    import contextlib

    from redistro.process import hooks

    # a developer's profile (tools/profile.py TASK NODE/logwriter)
    profiled = hooks.profile(f"{Path(out).stem}/logwriter")
    with profiled if profiled is not None else contextlib.nullcontext():
        return _write(fd, out, ready_fd)


def _write(fd: int, out: str, ready_fd: int) -> int:
    from redistro import files

    if ready_fd >= 0:  # imported: the recorder may start the cycles
        os.write(ready_fd, b"R")
        os.close(ready_fd)
    src = io.BufferedReader(PacedPipe(fd), 1 << 16)
    tmp = files.temp_name(out)
    sink = _McapSink(os.fdopen(files.create(tmp), "wb", buffering=1 << 20))
    cpu0, wall0 = time.process_time(), time.monotonic()
    stats: dict[str, Any] = {}
    while True:
        head = _read_exact(src, FRAME.size)
        if head is None:
            break
        size, kind, log_ns = FRAME.unpack(head)
        body = _read_exact(src, size)
        if body is None:
            break
        if kind == KIND_CYCLE:
            sink.cycle(body, log_ns)
        elif kind == KIND_EVENT:
            doc = json.loads(body)
            sink.event(str(doc.pop("topic", "/events")), doc, log_ns)
        elif kind == KIND_HEADER:
            sink.header(json.loads(body))
        elif kind == KIND_END:
            stats = json.loads(body)
    stats.setdefault("node", sink.node)
    stats["frames_written"] = sink.frames
    stats["digest"] = sink.digest.hexdigest()
    stats["messages"] = sink.messages
    stats["complete"] = "recorded" in stats
    wall = time.monotonic() - wall0
    stats["writer_cpu_s"] = round(time.process_time() - cpu0, 3)
    stats["writer_cpu_percent"] = round(100 * stats["writer_cpu_s"] / wall, 2) if wall else 0.0
    sink.finish(stats)
    src.close()
    os.replace(tmp, out)
    side = out[: -len(".mcap")] + ".log.json" if out.endswith(".mcap") else out + ".json"
    files.replace(side, json.dumps(stats, indent=1))
    return 0


class _McapSink:
    """The MCAP file one node's frames go into: its channels from the
    header, each cycle's messages cut from the frame, the events (their
    JSON documents as ROS 2 strings)."""

    def __init__(self, out: Any) -> None:
        from mcap.writer import CompressionType, Writer

        self.out = out
        self.writer = Writer(out, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        self.writer.start(profile="ros2", library="redistro")
        # channel id, offset, size, the CDR body's runs (from, to, padding
        # before), a feedback channel's standard messages (or None), and
        # its part of the 3D scene (or None)
        self.cuts: list[tuple[int, int, int, list[tuple[int, int, bytes]], Any, Any]] = []
        self.scene: Any = None  # (redistro.log.scene.Online, once the header names robots)
        self.tf_channel = 0
        self.scene_channels: dict[str, int] = {}
        self.std_schemas: tuple[int, int] | None = None
        self.timing: Timing | None = None
        self.event_schema = self.writer.register_schema(
            ros2.EVENT, "ros2msg", ros2.EVENT_DEF.encode()
        )
        self.event_channels: dict[str, int] = {}
        self.message_schema: int | None = None
        self.node = ""
        self.frames = self.messages = 0
        # each cycle's digest (its logged data but the wall-clock stamps,
        # on /<node>/digest) and the run's, which chains them: two lockstep
        # runs of one task give the same
        self.digest = hashlib.blake2b(digest_size=16)
        self.digest_runs: list[list[tuple[int, int]]] = []
        self.digest_channel = 0

    def header(self, header: dict[str, Any]) -> None:
        """The node's channels (one per logged block, and its timing), and
        its metadata."""
        from redistro.log.frames import MESSAGE_ENCODING, SCHEMA_ENCODING

        w = self.writer
        self.node = header.get("node", "")
        meta = header.get("meta", {})
        drawn = bool(meta.get("robots"))  # (the robots known: the scene is drawn)
        for ch in [*header["channels"], header["timing"]]:
            sid = w.register_schema(ch["schema"], SCHEMA_ENCODING, ch["definition"].encode())
            cid = w.register_channel(ch["topic"], MESSAGE_ENCODING, sid, {"node": header["node"]})
            if ch is header["timing"]:
                self.timing = Timing(header, cid)
                sid = w.register_schema(ros2.CYCLE_DIGEST, SCHEMA_ENCODING, DIGEST_DEF)
                topic = ch["topic"].rsplit("/", 1)[0] + "/digest"
                self.digest_channel = w.register_channel(
                    topic, MESSAGE_ENCODING, sid, {"node": header["node"]}
                )
            else:
                runs = [(int(a), int(a) + int(n), bytes(int(p))) for a, n, p in ch["runs"]]
                spec = ch.get("ros2")
                std = self._standard(spec, header["node"])
                part = _scene_part(spec) if drawn else None
                self.cuts.append((cid, int(ch["offset"]), int(ch["size"]), runs, std, part))
                self.digest_runs.append([(int(a), int(b)) for a, b in ch.get("digest", [])])
        parts = [(c[5][0], c[5][1]) for c in self.cuts if c[5] is not None]
        if parts:
            from redistro.log import scene

            self.scene = scene.Online(meta, parts)
            sid = w.register_schema(scene.TF, SCHEMA_ENCODING, scene.TF_DEF.encode())
            self.tf_channel = w.register_channel("/tf", MESSAGE_ENCODING, sid, {})
        skip = ("channels", "meta", "timing", "frame")
        node = {k: v for k, v in header.items() if k not in skip}
        w.add_metadata("redistro.node", {k: json.dumps(v) for k, v in node.items()})
        w.add_metadata("redistro.meta", {k: json.dumps(v) for k, v in meta.items()})

    def _standard(self, spec: dict[str, Any] | None, node: str) -> Any:
        """A feedback channel's standard messages: JointState and WrenchStamped."""
        if spec is None or spec.get("kind", "feedback") != "feedback":
            return None
        w, robot = self.writer, str(spec["robot"])
        if not self.std_schemas:
            self.std_schemas = (
                w.register_schema(ros2.JOINT_STATE, "ros2msg", ros2.JOINT_STATE_DEF.encode()),
                w.register_schema(ros2.WRENCH_STAMPED, "ros2msg", ros2.WRENCH_STAMPED_DEF.encode()),
            )
        js, ws = self.std_schemas
        meta = {"node": node}
        return (
            ros2.Feedback(robot, list(spec["joints"]), spec["fields"]),
            w.register_channel(f"/{robot}/joint_states", "cdr", js, meta),
            w.register_channel(f"/{robot}/wrench", "cdr", ws, meta),
        )

    def cycle(self, body: bytes, log_ns: int) -> None:
        """One cycle's messages, its timing, its events."""
        timing = self.timing
        if timing is None:
            return
        w = self.writer
        cycle_bytes = body[0:8]
        seq = int.from_bytes(cycle_bytes, "little") & 0xFFFFFFFF
        poses: list[Any] = []  # (the cycle's transforms, in the scene's order)
        this = hashlib.blake2b(digest_size=16)
        digest = this.update
        for (cid, off, n, runs, std, part), keep in zip(self.cuts, self.digest_runs, strict=True):
            packed = cycle_bytes + body[off : off + n]
            for a, b in keep:
                digest(packed[a:b])
            w.add_message(cid, log_ns, cdr_message(packed, runs), log_ns, seq)
            if std is not None:  # (a robot's feedback: its JointState and WrenchStamped too)
                fb, js, ws = std
                w.add_message(js, log_ns, fb.joint_state(packed, log_ns), log_ns, seq)
                w.add_message(ws, log_ns, fb.wrench(packed, log_ns), log_ns, seq)
                self.messages += 2
            if part is not None:  # (its transforms: the joints', or the goal's)
                self._transforms(part, packed, log_ns, poses)
        if poses:  # one /tf message a cycle
            w.add_message(self.tf_channel, log_ns, self.scene.message(log_ns, poses), log_ns, seq)
            self.messages += 1
        w.add_message(timing.channel, log_ns, timing.message(body), log_ns, seq)
        cycle_digest = this.digest()
        self.digest.update(cycle_digest)
        w.add_message(
            self.digest_channel, log_ns, CDR_HEADER + cycle_bytes + cycle_digest, log_ns, seq
        )
        self.messages += len(self.cuts) + 2
        self.frames += 1
        for doc in timing.events(body):
            self.event(str(doc.pop("topic")), doc, log_ns)

    def _transforms(
        self, part: tuple[str, str, int, int], packed: bytes, log_ns: int, poses: list[Any]
    ) -> None:
        kind, robot, a, b = part
        if kind == "feedback":  # (a: the joint positions, b: the wrench)
            q, force = _Q.unpack_from(packed, a), _V3.unpack_from(packed, b)
            poses += self.scene.joints(robot, q, force, log_ns)
        else:  # a plan (a: the goal's position, b: its rotation vector)
            poses.append(self.scene.goal(_V3.unpack_from(packed, a), _V3.unpack_from(packed, b)))

    def _closing_scene(self) -> None:
        """The static scene and the wrench arrows, at the end of the file."""
        from redistro.log import scene

        schemas: dict[str, int] = {}
        for log_ns, topic, msgtype, data in self.scene.closing():
            if msgtype not in schemas:
                text = scene.definition(msgtype)
                schemas[msgtype] = self.writer.register_schema(msgtype, "ros2msg", text.encode())
            if topic not in self.scene_channels:
                cid = self.writer.register_channel(topic, "cdr", schemas[msgtype], {})
                self.scene_channels[topic] = cid
            self.writer.add_message(self.scene_channels[topic], log_ns, data, log_ns)
            self.messages += 1

    def event(self, topic: str, doc: dict[str, Any], log_ns: int) -> None:
        box = topic.endswith("/messages")  # (a message box's line: a message of its own)
        if topic not in self.event_channels:
            if box and self.message_schema is None:
                self.message_schema = self.writer.register_schema(
                    ros2.MESSAGE, "ros2msg", ros2.MESSAGE_DEF.encode()
                )
            schema = self.message_schema if box else self.event_schema
            channel = self.writer.register_channel(topic, "cdr", schema or 0)
            self.event_channels[topic] = channel
        # (an event: a ROS 2 string holding its JSON document)
        data = ros2.message(doc) if box else ros2.event(json.dumps(doc))
        self.writer.add_message(self.event_channels[topic], log_ns, data, log_ns)
        self.messages += 1

    def finish(self, stats: dict[str, Any]) -> None:
        if self.scene is not None:
            try:
                self._closing_scene()
            except Exception as exc:  # (a picture never costs the log its end)
                stats["scene_error"] = str(exc)[:200]
            stats["messages"] = self.messages
        self.writer.add_metadata("redistro.recording", {k: json.dumps(v) for k, v in stats.items()})
        self.writer.finish()  # type: ignore[no-untyped-call]
        self.out.close()


class Timing:
    """A cycle frame's timing message and events, from its tick and the
    processes' status rows (no numpy here: struct)."""

    def __init__(self, header: dict[str, Any], channel: int) -> None:
        t = header["timing"]
        self.channel = channel
        self.node = header["node"]
        self.names = list(header["processes"])
        n = self.n = len(self.names)
        self.on_cycle = [bool(v) for v in t["on_cycle"]]
        self.rows_at, self.row_size = int(t["rows_offset"]), int(t["row_size"])
        self.head = struct.Struct(header["frame"]["head"])
        self.fields = {name: (int(off), _code(code)) for name, (off, code) in t["fields"].items()}
        # log_cycle, tick_due_ns, tick_late_us, then per process: heartbeat
        # cycle, lateness, busy time, overruns, skipped, state
        # (in the CDR body's layout, its padding included)
        self.out = struct.Struct(t["format"])
        self.states = [-1] * n
        self.estop = False

    def _row(self, body: bytes, j: int, name: str) -> Any:
        off, st = self.fields[name]
        return st.unpack_from(body, self.rows_at + j * self.row_size + off)[0]

    def message(self, body: bytes) -> bytes:
        cycle, due, tick, _estop = self.head.unpack_from(body, 0)
        nan = math.nan
        hb, late, busy, over, skip, state = [], [], [], [], [], []
        for j in range(self.n):
            h = self._row(body, j, "heartbeat_cycle")
            wake, done = self._row(body, j, "wake_ns"), self._row(body, j, "done_ns")
            hb.append(h)
            late.append((wake - due) / 1e3 if self.on_cycle[j] and h == cycle else nan)
            busy.append((done - wake) / 1e3 if done >= wake > 0 else nan)
            over.append(self._row(body, j, "overruns") & 0xFFFFFFFF)
            skip.append(self._row(body, j, "skipped") & 0xFFFFFFFF)
            state.append(self._row(body, j, "state") & 0xFF)
        late_tick = (tick - due) / 1e3 if tick else nan
        return CDR_HEADER + self.out.pack(
            cycle, due, late_tick, *hb, *late, *busy, *over, *skip, *state
        )

    def events(self, body: bytes) -> list[dict[str, Any]]:
        """An e-stop raised, processes changing state: JSON events of this cycle."""
        cycle, _due, _tick, estop = self.head.unpack_from(body, 0)
        out: list[dict[str, Any]] = []
        if estop and not self.estop:
            self.estop = True
            out.append(
                {
                    "topic": f"/{self.node}/events",
                    "cycle": cycle,
                    "event": "estop",
                    "text": "e-stop raised in the node",
                }
            )
        for j in range(self.n):
            s = self._row(body, j, "state")
            if s != self.states[j]:
                self.states[j] = s
                out.append(
                    {
                        "topic": f"/{self.node}/events",
                        "cycle": cycle,
                        "event": "state",
                        "process": self.names[j],
                        "state": s,
                    }
                )
        return out


_Q = struct.Struct("<7d")  # an arm's joint positions
_V3 = struct.Struct("<3d")


def _scene_part(spec: dict[str, Any] | None) -> tuple[str, str, int, int] | None:
    """What a channel gives the scene: a feedback its joints and wrench, a
    plan its goal (kind, robot, two field offsets in the packed message)."""
    if spec is None:
        return None
    f = spec["fields"]
    if spec.get("kind", "feedback") == "feedback":
        return ("feedback", str(spec["robot"]), int(f["q_rad"]), int(f["wrench"]))
    return ("plan", str(spec["robot"]), int(f["goal_xyz_m"]), int(f["goal_rot_xyz"]))


def cdr_message(packed: bytes, runs: list[tuple[int, int, bytes]]) -> bytes:
    """A packed message as CDR: the header, then its runs of fields, each
    after its alignment's padding (``runs``: from
    :func:`redistro.log.schema.cdr_runs`, as (from, to, zero bytes))."""
    parts = [CDR_HEADER]
    for a, b, pad in runs:
        if pad:
            parts.append(pad)
        parts.append(packed[a:b])
    return b"".join(parts)


def _code(dtype_str: str) -> struct.Struct:
    """A struct for one numpy scalar dtype string (``<u8``, ``|u1`` ...)."""
    return struct.Struct("<" + STRUCT_CODES[(dtype_str[-2], int(dtype_str[-1]))])

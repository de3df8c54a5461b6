"""The recording side of the session log, inside a node's logging worker.

Each cycle the worker calls :meth:`CycleRecorder.record`: the blocks it logs
are snapshot (seqlocked reads straight into one frame buffer), the node's
timing is added, and the frame goes into a pipe with one non-blocking
write. A separate, non-real-time writer process (:mod:`redistro.log.writer`)
drains the pipe into ``<node>.mcap`` in the run folder. So recording never
waits on the file: when the writer falls behind and the pipe is full, the
frame is dropped and counted. The cycles the worker itself did not run
(a late wake-up coalesces syncs) are counted the same way: at the end,
``dropped = the manager's cycles - frames recorded``.

Events (segment changes, e-stop, message-box text, the node's fault) go
through the same pipe as JSON.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import struct
import subprocess
import sys
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from redistro.localdata import LocalData, MessageBox
from redistro.localdata.block import Block, Record
from redistro.localdata.layout import BLOCKS, MANAGER, PROC_STATUS
from redistro.log import schema
from redistro.log.frames import FRAME, KIND_CYCLE, KIND_END, KIND_EVENT, KIND_HEADER
from redistro.process.spawn import THREAD_ENV
from redistro.process.spec import NodeSpec

log = logging.getLogger(__name__)

PIPE_BUF = 4096  # a pipe write up to this size is all-or-nothing
PIPE_BYTES = 1 << 20  # asked for; the kernel may give less (fs.pipe-max-size)
WRITER_WAIT_S = 10.0


@dataclass
class Channel:
    topic: str
    block: Block | None  # None: the timing channel
    dtype: np.dtype[Any]
    offset: int  # of the message in the frame payload

    @property
    def size(self) -> int:
        return int(self.dtype.itemsize)


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
        self.channels: list[Channel] = []
        offset = 0
        for topic, name, index in topics:
            payload = BLOCKS[name][0]
            dt = schema.with_cycle(payload)
            self.channels.append(Channel(topic, ld.block(name, index), dt, offset))
            offset += dt.itemsize
        n = len(spec.workers)
        tdt = schema.timing_dtype(n)
        self.timing = Channel(f"/{spec.node}/timing", None, tdt, offset)
        self.channels.append(self.timing)
        offset += tdt.itemsize
        self.frame = bytearray(FRAME.size + offset)
        if len(self.frame) > PIPE_BUF:
            raise ValueError(
                f"a cycle frame of {len(self.frame)} bytes does not fit one pipe write"
            )
        FRAME.pack_into(self.frame, 0, offset, KIND_CYCLE, 0)
        self.mv = memoryview(self.frame)
        self.trec = np.zeros((), tdt)
        self.tbytes = memoryview(self.trec.reshape(1).view(np.uint8))  # type: ignore[arg-type]
        self.manager = ld.block("manager")
        self.mrec = Record(MANAGER)
        self.rows = [ld.block("proc", j) for j in range(n)]
        self.row_recs = [Record(PROC_STATUS) for _ in range(n)]
        self.on_cycle = [w.on_cycle for w in spec.workers]
        self.boxes: list[MessageBox] = [ld.msgbox(j) for j in range(n)]
        self.names = [w.name for w in spec.workers]
        self.states = [0] * n
        self.estop = 0
        self.realtime_offset_ns = time.time_ns() - time.monotonic_ns()
        self.recorded = 0
        self.dropped_full = 0
        self.repeated = 0
        self.seen_cycle = 0
        self.events = 0
        self.events_dropped = 0
        self.first_cycle = 0
        self.last_cycle = 0
        self.meta = meta
        self.fd = -1
        self.proc: subprocess.Popen[bytes] | None = None

    # -- start / end --

    def start(self) -> None:
        """Start the writer process and send it the channels (before any cycle)."""
        rfd, wfd = os.pipe2(os.O_CLOEXEC)
        with contextlib.suppress(OSError):
            fcntl.fcntl(wfd, fcntl.F_SETPIPE_SZ, PIPE_BYTES)
        env = os.environ.copy()
        env.update(THREAD_ENV)
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
                ],
                env=env,
                pass_fds=(rfd,),
                close_fds=True,
                stdin=subprocess.DEVNULL,
            )
        finally:
            os.close(rfd)
        self.fd = wfd
        header = {
            "node": self.node,
            "session": self.spec.session_id,
            "rate_hz": self.spec.rate_hz,
            "processes": self.names,
            "roles": [w.role for w in self.spec.workers],
            "meta": self.meta,
            "channels": [
                {
                    "topic": c.topic,
                    "schema": "redistro/" + c.topic.strip("/").replace("/", "_"),
                    "definition": schema.ros1_definition(c.dtype),
                    "offset": c.offset,
                    "size": c.size,
                }
                for c in self.channels
            ],
        }
        self._send_blocking(KIND_HEADER, json.dumps(header).encode())
        os.set_blocking(wfd, False)

    def close(self) -> dict[str, Any]:
        """Send the counters and the node's fault, close the pipe, wait for the writer."""
        if self.fd < 0:
            return {}
        final = self.last_cycle
        with contextlib.suppress(Exception):
            self.manager.read_into(self.mrec.bytes)
            final = max(final, int(self.mrec["cycle"]))
            self._messages(final)
            self._fault_event()
        stats = {
            "node": self.node,
            "cycles": final,
            "recorded": self.recorded,
            "dropped": max(0, final - self.recorded),
            "dropped_pipe_full": self.dropped_full,
            "repeated": self.repeated,
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
        if self.proc is not None:
            try:
                self.proc.wait(WRITER_WAIT_S)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
                stats["writer"] = "killed"
        return stats

    # -- every cycle --

    def record(self, cycle: int, due_ns: int = 0) -> None:
        """Snapshot this cycle's blocks and timing into one frame; send it or count it dropped.

        due_ns: when the cycle's tick was due (the worker's ``due_ns``); the
        manager block may already show a later cycle when this one runs late.
        """
        if cycle <= self.seen_cycle:
            # a late wake-up that read the manager's next cycle, then that
            # cycle's own sync: the step runs twice for one cycle, logged once
            self.repeated += 1
            return
        self.seen_cycle = cycle
        mv = self.mv
        base = FRAME.size
        self.manager.read_into(self.mrec.bytes)
        m = self.mrec
        current = int(m["cycle"]) == cycle
        due = due_ns or int(m["tick_due_ns"])
        struct.pack_into("<q", self.frame, 5, due + self.realtime_offset_ns)
        for c in self.channels:
            if c.block is None:
                continue
            o = base + c.offset
            struct.pack_into("<Q", self.frame, o, cycle)
            c.block.read_into(mv[o + 8 : o + c.size])
        self._timing(cycle, due, int(m["tick_ns"]) if current else 0)
        o = base + self.timing.offset
        mv[o : o + self.timing.size] = self.tbytes
        try:
            os.write(self.fd, self.frame)
        except BlockingIOError:
            self.dropped_full += 1
        else:
            self.recorded += 1
            if not self.first_cycle:
                self.first_cycle = cycle
            self.last_cycle = cycle
        if int(m["estop"]) and not self.estop:
            self.estop = 1
            self.event("events", cycle, event="estop", text="e-stop raised in the node")
        self._messages(cycle)

    def _timing(self, cycle: int, due: int, tick_ns: int) -> None:
        t = self.trec
        t["log_cycle"] = cycle
        t["tick_due_ns"] = due
        t["tick_late_us"] = (tick_ns - due) / 1e3 if tick_ns else np.nan
        hb, late, busy = t["heartbeat_cycle"], t["late_us"], t["busy_us"]
        over, skip, state = t["overruns"], t["skipped"], t["state"]
        for j, (row, rec) in enumerate(zip(self.rows, self.row_recs, strict=True)):
            try:
                row.read_into(rec.bytes)
            except Exception:
                continue  # a row held mid-write: last cycle's figures stay
            wake, done = int(rec["wake_ns"]), int(rec["done_ns"])
            hb[j] = rec["heartbeat_cycle"]
            late[j] = (
                (wake - due) / 1e3
                if self.on_cycle[j] and rec["heartbeat_cycle"] == cycle
                else np.nan
            )
            busy[j] = (done - wake) / 1e3 if done >= wake > 0 else np.nan
            over[j] = rec["overruns"]
            skip[j] = rec["skipped"]
            s = int(rec["state"])
            state[j] = s
            if s != self.states[j]:
                self.states[j] = s
                self.event("events", cycle, event="state", process=self.names[j], state=s)

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
        try:
            os.write(self.fd, frame)
            self.events += 1
        except BlockingIOError:
            self.events_dropped += 1

    def _send_blocking(self, kind: int, body: bytes) -> None:
        data = FRAME.pack(len(body), kind, time.time_ns()) + body
        view = memoryview(data)
        while view:
            n = os.write(self.fd, view)
            view = view[n:]


def robots_meta(cfg: Any, robots: list[str]) -> dict[str, Any]:
    """What the inspection tools need to redo the kinematics: per robot its
    base and tool (peg or sensor plate), and the boards' sample rate."""
    peg = cfg.plant.peg
    return {
        "physics_hz": cfg.plant.physics_hz,
        "robots": {
            r: {
                "base_xyz_m": list(cfg.robots[r].base_xyz_m),
                "peg": [peg.side_m, peg.length_m, peg.mass_kg] if cfg.robots[r].peg else None,
            }
            for r in robots
        },
    }

"""The operator's commands to a running session (``redistro ctl``, the live view's buttons).

A command is one datagram on the SSC manager's Unix socket, ``ctl.sock`` in
the session's 0700 runtime folder, signed with the session's key (HMAC-SHA256,
the ddm's link key, ``ddm.key`` beside it, mode 0600):

    magic "RDCT", version, command, robot, session id (32 bytes), nonce (8),
    stamp [ns, CLOCK_MONOTONIC], step (6 doubles) | tag (32 bytes)

The manager takes at most one datagram a cycle, in its Idle state. A command
whose tag, session, age (over ``MAX_AGE_NS``) or nonce (seen before) is wrong
is refused, counted and logged, and changes nothing. An accepted one goes into
the ``operator`` block of Local Data, which the SSC worker reads each cycle
(:mod:`redistro.ssc.operator`); the manager answers once the worker has acted
(pause, resume, jog) or at once (stop, e-stop), with a JSON line.
"""

from __future__ import annotations

import contextlib
import enum
import hashlib
import hmac
import json
import os
import secrets
import socket
import struct
import tempfile
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from redistro.errors import ConfigError

SOCKET = "ctl.sock"
MAGIC = b"RDCT"
VERSION = 1
BODY = struct.Struct("<4sHBB32sQq6d")
TAG = 32
SIZE = BODY.size + TAG
MAX_AGE_NS = 5_000_000_000  # older (or this far ahead): refused as a replay
NONCES = 256  # nonces remembered (a replay within MAX_AGE_NS is one of them)
JOG_MAX_M = 0.005  # a jog's largest translation [m] ...
JOG_MAX_RAD = 0.0349066  # ... and rotation (2 degrees) [rad]
REPLY_BYTES = 512


class Command(enum.IntEnum):
    NONE = 0
    PAUSE = 1
    RESUME = 2
    JOG = 3
    STOP = 4
    ESTOP = 5


class Status(enum.IntEnum):
    """How the worker ended a command (0: under way)."""

    UNDER_WAY = 0
    DONE = 1
    NOT_NOW = 2  # the task is not in a state for it (not started, ending, not paused)
    LIMITS = 3  # a jog would leave the joint limits (less the guard's margin)
    CLEARANCE = 4  # ... would bring links closer than the planned clearance
    UNREACHED = 5  # ... has no posture that reaches it
    BUSY = 6  # a jog is still moving


STATUS_TEXT = {
    Status.DONE: "done",
    Status.NOT_NOW: "not now",
    Status.LIMITS: "refused: the joint limits",
    Status.CLEARANCE: "refused: too close to the other arm or the work-cell",
    Status.UNREACHED: "refused: no posture reaches it",
    Status.BUSY: "refused: a jog is still moving",
}


@dataclass(frozen=True)
class Order:
    """One command, as signed."""

    command: Command
    robot: int = 0
    step: tuple[float, float, float, float, float, float] = (0.0,) * 6


def sign(key: bytes, session_id: str, order: Order, nonce: int, stamp_ns: int) -> bytes:
    body = BODY.pack(
        MAGIC, VERSION, int(order.command), order.robot, session_id.encode()[:32],
        nonce, stamp_ns, *order.step,
    )  # fmt: skip
    return body + hmac.digest(key, body, hashlib.sha256)


class Refused(Exception):
    """A datagram that is not a command of this session's operator."""


class Checker:
    """The manager's side: a datagram's checks, in order, before anything acts."""

    def __init__(self, key: bytes, session_id: str) -> None:
        self.key = key
        self.session = session_id.encode()[:32]
        self.seen: deque[int] = deque(maxlen=NONCES)

    def check(self, data: bytes, now_ns: int) -> Order:
        if len(data) != SIZE:
            raise Refused(f"{len(data)} bytes, not {SIZE}")
        body, tag = data[: BODY.size], data[BODY.size :]
        if not hmac.compare_digest(hmac.digest(self.key, body, hashlib.sha256), tag):
            raise Refused("not signed with the session's key")
        magic, version, cmd, robot, session, nonce, stamp, *step = BODY.unpack(body)
        if magic != MAGIC or version != VERSION:
            raise Refused(f"not a version {VERSION} command")
        if session.rstrip(b"\0") != self.session:
            raise Refused("another session's command")
        if abs(now_ns - stamp) > MAX_AGE_NS:
            raise Refused("stale (a replay?)")
        if nonce in self.seen:
            raise Refused("seen before (a replay)")
        try:
            command = Command(cmd)
        except ValueError:
            raise Refused(f"unknown command {cmd}") from None
        if command == Command.NONE:
            raise Refused("no command")
        if not all(v == v and abs(v) < 1.0 for v in step):
            raise Refused("a step out of range")
        self.seen.append(nonce)
        return Order(command, robot, (step[0], step[1], step[2], step[3], step[4], step[5]))


class Receiver:
    """The manager's socket: non-blocking, one datagram per :meth:`poll`."""

    def __init__(self, directory: Path, key: bytes, session_id: str) -> None:
        self.path = directory / SOCKET
        self.checker = Checker(key, session_id)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()  # (a dead session's, reaped with its folder)
        old = os.umask(0o177)
        try:
            self.sock.bind(str(self.path))
        finally:
            os.umask(old)

    def poll(self) -> tuple[bytes, Any] | None:
        """One datagram and its sender's address, or None (nothing waiting)."""
        try:
            data, addr = self.sock.recvfrom(SIZE + 1)
        except (BlockingIOError, InterruptedError):
            return None
        return data, addr

    def reply(self, addr: Any, doc: dict[str, Any]) -> None:
        if not addr:
            return  # (an unbound sender: nobody to answer)
        with contextlib.suppress(OSError):
            self.sock.sendto(json.dumps(doc).encode()[:REPLY_BYTES], addr)

    def close(self) -> None:
        self.sock.close()
        with contextlib.suppress(OSError):
            self.path.unlink()


def session_dir(session: str | None, what: str = "ctl") -> tuple[str, Path]:
    """The running session named (or the only one) and its runtime folder."""
    from redistro.errors import clipped
    from redistro.ipc import names
    from redistro.ipc.session import live_sessions

    live = live_sessions()
    if session is None:
        if len(live) != 1:
            names_ = ", ".join(live) or "none"
            raise ConfigError(f"{what}: {len(live)} sessions running; name one ({names_})")
        session = live[0]
    if session not in live:
        raise ConfigError(f"{what}: no running session {clipped(session)}")
    return session, names.runtime_dir() / session


class Client:
    """The operator's side: signs with the session's key and waits for the answer."""

    def __init__(self, session_id: str, directory: Path, key: bytes | None = None) -> None:
        from redistro.ddm import record as wire

        self.sid, self.dir = session_id, directory
        if key is None:
            try:
                key = wire.load_key(directory / wire.SESSION_KEY)
            except (OSError, ValueError) as exc:
                raise ConfigError(f"ctl: session {session_id} has no readable key: {exc}") from None
        self.key = key

    def send(self, order: Order, timeout_s: float = 10.0) -> dict[str, Any]:
        """The manager's answer, or ``{"ok": False, "text": ...}`` if none came."""
        data = sign(self.key, self.sid, order, secrets.randbits(63), time.monotonic_ns())
        return self.send_raw(data, timeout_s)

    def send_raw(self, data: bytes, timeout_s: float) -> dict[str, Any]:
        target = str(self.dir / SOCKET)
        with tempfile.TemporaryDirectory(prefix="redistro-ctl-") as tmp:
            me = os.path.join(tmp, "reply.sock")
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
                s.bind(me)
                try:
                    s.sendto(data, target)
                except OSError as exc:
                    return {"ok": False, "text": f"the session's SSC takes no commands: {exc}"}
                deadline = time.monotonic() + timeout_s
                while True:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        return {"ok": False, "text": f"no answer within {timeout_s:g} s"}
                    s.settimeout(left)
                    try:
                        reply = s.recv(REPLY_BYTES)
                    except TimeoutError:
                        continue
                    except InterruptedError:
                        continue
                    try:
                        doc = json.loads(reply)
                    except ValueError:
                        return {"ok": False, "text": "an answer that is not JSON"}
                    return doc if isinstance(doc, dict) else {"ok": False, "text": str(doc)}


class Desk:
    """The SSC manager's operator desk: the socket, the ``operator`` block,
    the answer owed. Per cycle: one ``recvfrom`` in Idle (nothing waiting:
    about a microsecond) and, while a command is under way, a look at the
    worker's answer in the plans the manager reads anyway."""

    def __init__(
        self, receiver: Receiver, block: Any, robots: list[str], say: Any, serial: bool
    ) -> None:
        from redistro.localdata.block import Record
        from redistro.localdata.layout import OPERATOR

        self.rx, self.block, self.robots, self.say = receiver, block, robots, say
        self.serial = serial  # (a parallel SSC's arms take no pause, resume or jog)
        self.rec = Record(OPERATOR)
        self.seq = 0
        self.refused = 0
        self.accepted = 0
        self.owed: tuple[int, Any, Order] | None = None  # (seq, address, order)
        self.act: Command = Command.NONE  # a stop or e-stop for the manager's next tick

    def idle(self, cycle: int) -> None:
        got = self.rx.poll()
        if got is None:
            return
        data, addr = got
        try:
            order = self.rx.checker.check(data, time.monotonic_ns())
            self._valid(order)
        except Refused as exc:
            self.refused += 1
            self.rec["refused"] = self.refused
            self.rec.array["refused_why"] = str(exc).encode()[:48]
            self.block.publish(self.rec.bytes)
            self.say(f"operator command refused ({self.refused} so far): {exc}", warning=True)
            self.rx.reply(addr, {"ok": False, "text": f"refused: {exc}"})
            return
        if self.owed is not None or self.act != Command.NONE:
            self.rx.reply(addr, {"ok": False, "text": "busy: the last command is under way"})
            return
        self.seq += 1
        self.accepted += 1
        rec = self.rec
        rec["seq"], rec["command"], rec["robot"], rec["cycle"] = (
            self.seq, int(order.command), order.robot, cycle,
        )  # fmt: skip
        rec.array["step"] = order.step
        self.block.publish(rec.bytes)
        what = order.command.name.lower()
        if order.command == Command.JOG:
            mm = ", ".join(f"{v * 1e3:.2f}" for v in order.step[:3])
            deg = ", ".join(f"{v * 57.29578:.2f}" for v in order.step[3:])
            what += f" {self.robots[order.robot]} by ({mm}) mm, ({deg})°"
        self.say(f"operator command {self.seq}: {what}")
        if order.command in (Command.STOP, Command.ESTOP):
            self.act = order.command
            self.rx.reply(addr, {"ok": True, "seq": self.seq, "text": f"{what}: under way"})
        else:
            self.owed = (self.seq, addr, order)

    def _valid(self, order: Order) -> None:
        if order.command in (Command.STOP, Command.ESTOP):
            return
        if not self.serial:
            raise Refused("pause, resume and jog need a serial SSC (ssc.parallel_arms: false)")
        if order.command != Command.JOG:
            return
        if order.robot >= len(self.robots):
            raise Refused(f"no robot {order.robot} in the group")
        p, r = order.step[:3], order.step[3:]
        if sum(v * v for v in p) ** 0.5 > JOG_MAX_M + 1e-9:
            raise Refused(f"a jog moves at most {JOG_MAX_M * 1e3:g} mm")
        if sum(v * v for v in r) ** 0.5 > JOG_MAX_RAD + 1e-9:
            raise Refused("a jog turns at most 2 degrees")

    def answer(self, plan: Any) -> None:
        """The worker's answer to the command owed, from a plan it wrote."""
        if self.owed is None:
            return
        seq, addr, order = self.owed
        if int(plan["op_seq"]) != seq or int(plan["op_status"]) == Status.UNDER_WAY:
            return
        self.owed = None
        status = Status(int(plan["op_status"]))
        text = f"{order.command.name.lower()}: {STATUS_TEXT.get(status, status.name)}"
        self.rx.reply(addr, {"ok": status == Status.DONE, "seq": seq, "text": text,
                             "paused": bool(plan["paused"])})  # fmt: skip

    def close(self) -> None:
        self.rx.close()

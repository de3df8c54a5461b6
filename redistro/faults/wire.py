"""DDM link and record faults, as a transport around the real one.

Armed for one node's ddm (see :mod:`redistro.faults.inject`); from the
trigger on it breaks what that ddm sends:

- ``ddm.link-close``: the link is cut (the real transport closed: the peer
  sees the socket close, or the memory card's updates stop) and every later
  call raises :class:`TransportError`;
- ``ddm.drop``: every record is silently dropped (reflective-memory updates
  lost on the network);
- ``ddm.delay``: every record leaves ``arg`` seconds late (in order);
- ``ddm.malformed``: for ``arg`` records, a copy with one byte flipped goes
  out before each genuine record (noise on the line);
- ``ddm.replay``: for ``arg`` records, the record sent 100 records earlier
  goes out again before each genuine one (a replay);
- ``ddm.forged``: for ``arg`` records, a forgery goes out before each
  genuine one: the same record with 150 N m on joint 1, its checksum right
  but signed with another key (someone on the network without the key);
- ``ddm.renamed``: for ``arg`` records, the record sent 100 records earlier
  under another source name, its checksum right (a replay under a new name);
- ``ddm.flood``: ``arg`` forgeries at once, then the genuine record (a
  peer streaming without pause);
- ``ddm.foreign``: a second connection to the peer's port sends ``arg``
  forgeries (another host taking over the link);
- ``ddm.own-source``: for ``arg`` records, a forgery goes out before each
  genuine one under the receiving node's own name (``esc.<robot>``);
- ``ddm.capture``: nothing is broken; every record sent for the robot is
  also appended to ``<trigger>.records`` (an eavesdropper's recording, for
  a later run to replay), at most ``CAPTURE_MAX``.

The genuine records of the last two still go out: the receiver must refuse
the bad ones, count them and carry on.
"""

from __future__ import annotations

import collections
import time
from collections.abc import Callable, Collection

from redistro.ddm.transport import Links, Transport
from redistro.errors import TransportError
from redistro.faults.inject import Injection

POINTS = (
    "ddm.link-close",
    "ddm.drop",
    "ddm.delay",
    "ddm.malformed",
    "ddm.replay",
    "ddm.forged",
    "ddm.renamed",
    "ddm.flood",
    "ddm.foreign",
    "ddm.own-source",
    "ddm.capture",
)
CAPTURE_MAX = 20_000
OTHER_KEY = b"not the link's key, 32 bytes...."


def _resealed(record: bytes, source: bytes | None = None, tau: float | None = None) -> bytes:
    """A record changed by someone without the link's key: its checksum made
    right again, its tag signed with another key."""
    import struct

    from redistro.ddm import record as wire

    b = bytearray(record)
    if source is not None:
        b[8:24] = source[:16].ljust(16, b"\0")
    if tau is not None:  # the command's joint 1 torque (the payload's tau_nm[0])
        from redistro.localdata.layout import COMMAND

        at = wire.PAYLOAD_AT + COMMAND.fields["tau_nm"][1]  # type: ignore[index]
        struct.pack_into("<d", b, at, tau)
    crc_at = wire.HEADER.fields["crc32"][1]  # type: ignore[index]
    struct.pack_into("<I", b, crc_at, wire._crc(b))
    b[wire.BODY : wire.SIZE] = wire._tag(OTHER_KEY, b)
    return bytes(b)


REPLAY_BACK = 100


class Relay(Transport):
    """A transport that forwards everything to ``inner``: what a fault
    wrapper is built on. It has no accelerator (the ddm's kernels then
    admit and seal record by record, as the wrapper hands them over: the
    compiled path, with the fault in the way)."""

    def __init__(self, inner: Transport) -> None:
        self.inner = inner
        self.closed = False
        self.links = _RelayLinks(self)

    def send(self, record: bytes, robot: int) -> None:
        if self.closed:
            raise TransportError("link closed (injected fault)")
        self.inner.send(record, robot)

    def receive(self, ready: Collection[int] | None = None) -> list[bytes]:
        if self.closed:
            raise TransportError("link closed (injected fault)")
        return self.inner.receive(ready)

    @property
    def replies(self) -> bool:  # type: ignore[override]
        return self.inner.replies

    def fds(self) -> list[int]:
        return [] if self.closed else self.inner.fds()

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.inner.close()


class _RelayLinks(Links):
    """The inner transport's links, as long as the relay is open."""

    def __init__(self, relay: Relay) -> None:
        self.relay = relay

    @property
    def inner(self) -> Links:
        return self.relay.inner.links

    def can_send(self, robot: int) -> bool:
        return self.inner.can_send(robot)

    def lost_links(self) -> dict[int, str]:
        return {} if self.relay.closed else self.inner.lost_links()

    def authenticated(self, robot: int | None = None) -> None:
        self.inner.authenticated(robot)

    def drop_unauthenticated(self) -> None:
        self.inner.drop_unauthenticated()

    def refused(self) -> int:
        return self.inner.refused()

    def verify_with(self, check: Callable[[bytes], bool]) -> bool:
        return self.inner.verify_with(check)

    def flush(self) -> None:
        if not self.relay.closed:
            self.inner.flush()


class InjectedTransport(Relay):
    def __init__(self, inner: Transport, inj: Injection, robot_ids: dict[int, str]) -> None:
        super().__init__(inner)
        self.inj = inj
        self.what = inj.point.split(".", 1)[1]
        self.robot_ids = robot_ids  # group-wide robot id -> name
        self.bad_left = int(inj.arg) or 50
        self.delayed: collections.deque[tuple[int, bytes, int]] = collections.deque()
        self.history: collections.deque[tuple[bytes, int]] = collections.deque(maxlen=REPLAY_BACK)
        self.captured = 0

    def _hits(self, robot: int) -> bool:
        return self.inj.concerns(self.robot_ids.get(robot, "")) and self.inj.live()

    def send(self, record: bytes, robot: int) -> None:
        if self.closed:
            raise TransportError("link closed (injected fault)")
        self._flush_delayed()
        if not self._hits(robot):
            self.history.append((record, robot))
            self.inner.send(record, robot)
            return
        if self.what == "capture":
            self._capture(record)
            self.inner.send(record, robot)
            return
        if self.what == "link-close":
            self.closed = True
            self.inner.close()
            raise TransportError("link closed (injected fault)")
        if self.what == "drop":
            return
        if self.what == "delay":
            self.delayed.append((time.monotonic_ns() + int(self.inj.arg * 1e9), record, robot))
            return
        if self.bad_left > 0:
            self.bad_left -= 1
            if self.what == "malformed":
                bad = bytearray(record)
                k = len(bad) // 2 + self.bad_left % 64
                bad[k] ^= 0x5A
                self.inner.send(bytes(bad), robot)
            elif self.what == "replay" and len(self.history) == self.history.maxlen:
                old, old_robot = self.history[0]
                if old_robot == robot:
                    self.inner.send(old, robot)
            elif self.what == "forged":
                self.inner.send(_resealed(record, tau=150.0), robot)
            elif self.what == "renamed" and len(self.history) == self.history.maxlen:
                old, old_robot = self.history[0]
                if old_robot == robot:
                    self.inner.send(_resealed(old, source=b"intruder"), robot)
            elif self.what == "flood":
                forged = _resealed(record, tau=150.0)
                for _ in range(self.bad_left + 1):
                    self.inner.send(forged, robot)
                self.bad_left = 0
            elif self.what == "own-source":
                own = f"esc.{self.robot_ids.get(robot, '')}".encode()
                self.inner.send(_resealed(record, source=own, tau=150.0), robot)
            elif self.what == "foreign":
                self._foreign(record, robot)
                self.bad_left = 0
        self.history.append((record, robot))
        self.inner.send(record, robot)

    def _capture(self, record: bytes) -> None:
        if self.captured < CAPTURE_MAX:
            self.captured += 1
            with open(f"{self.inj.trigger}.records", "ab") as f:
                f.write(record)

    def _foreign(self, record: bytes, robot: int) -> None:
        """Another connection to the peer's port, sending forgeries."""
        import contextlib
        import socket

        conns = getattr(self.inner, "conns", {})
        link = conns.get(robot)
        if link is None:
            return
        forged = _resealed(record, tau=150.0)
        with (
            contextlib.suppress(OSError),
            socket.create_connection(link.sock.getpeername()[:2], timeout=0.5) as sock,
        ):
            for _ in range(int(self.inj.arg) or 50):
                sock.send(forged)

    def _flush_delayed(self) -> None:
        now = time.monotonic_ns()
        sent = False
        while self.delayed and self.delayed[0][0] <= now:
            _, record, robot = self.delayed.popleft()
            self.inner.send(record, robot)
            sent = True
        if sent:
            self.inner.links.flush()  # (sent outside a step of the ddm's)

    def receive(self, ready: Collection[int] | None = None) -> list[bytes]:
        if self.closed:
            raise TransportError("link closed (injected fault)")
        self._flush_delayed()
        return self.inner.receive(ready)

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
  goes out again before each genuine one (a replay).

The genuine records of the last two still go out: the receiver must refuse
the bad ones, count them and carry on.
"""

from __future__ import annotations

import collections
import time

from redistro.ddm.transport import Transport
from redistro.errors import TransportError
from redistro.faults.inject import Injection

POINTS = ("ddm.link-close", "ddm.drop", "ddm.delay", "ddm.malformed", "ddm.replay")
REPLAY_BACK = 100


class InjectedTransport(Transport):
    def __init__(self, inner: Transport, inj: Injection, robot_ids: dict[int, str]) -> None:
        self.inner = inner
        self.inj = inj
        self.what = inj.point.split(".", 1)[1]
        self.robot_ids = robot_ids  # group-wide robot id -> name
        self.closed = False
        self.bad_left = int(inj.arg) or 50
        self.delayed: collections.deque[tuple[int, bytes, int]] = collections.deque()
        self.history: collections.deque[tuple[bytes, int]] = collections.deque(maxlen=REPLAY_BACK)

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
        self.history.append((record, robot))
        self.inner.send(record, robot)

    def _flush_delayed(self) -> None:
        now = time.monotonic_ns()
        while self.delayed and self.delayed[0][0] <= now:
            _, record, robot = self.delayed.popleft()
            self.inner.send(record, robot)

    def receive(self) -> list[bytes]:
        if self.closed:
            raise TransportError("link closed (injected fault)")
        self._flush_delayed()
        return self.inner.receive()

    def lost_links(self) -> dict[int, str]:
        return {} if self.closed else self.inner.lost_links()

    @property
    def replies(self) -> bool:  # type: ignore[override]
        return self.inner.replies

    def fds(self) -> list[int]:
        return [] if self.closed else self.inner.fds()

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.inner.close()

"""An in-process transport: every end of a robot group's links in one process.

The fake beside the real transports (as python-can's ``virtual`` bus): the
SSC's end and one end per ESC robot, records handed over in memory, each end
with a pipe that becomes readable when records arrive (what a ddm waits on),
a closed end seen by its peers as a lost link after the records it sent
before closing. It runs the same contract tests as the socket and
reflective transports (tests/unit/test_transports.py) and lets unit tests
run real ddms (:class:`redistro.ddm.worker.Ddm`) without processes. It is
not a ``ddm.transport`` choice: nodes are processes, and it spans one.
"""

from __future__ import annotations

import contextlib
import os
from collections import deque
from collections.abc import Collection

from redistro.ddm.transport import Links, Transport
from redistro.errors import TransportError


class Loopback(Transport):
    """One end. Make a group's ends with :meth:`group` (or :meth:`pair`)."""

    def __init__(self, name: str, replies: bool = False) -> None:
        self.name = name
        self.replies = replies
        self.inbox: deque[bytes] = deque()
        self._r, self._w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        self.peers: dict[int, Loopback] = {}  # robot -> the end that handles it
        self.lost: dict[int, str] = {}
        self.closed = False
        self.dropped = 0
        self.links = _Links(self)

    @classmethod
    def group(cls, robots: Collection[int]) -> tuple[Loopback, dict[int, Loopback]]:
        """The SSC's end and each robot's ESC end (which replies, as the
        socket transport's ESC side does)."""
        ssc = cls("ssc")
        escs = {r: cls(f"esc of robot {r}", replies=True) for r in robots}
        for r, esc in escs.items():
            ssc.peers[r] = esc
            esc.peers[r] = ssc
        return ssc, escs

    @classmethod
    def pair(cls) -> tuple[Loopback, Loopback]:
        """(SSC side, ESC side) for robot 0."""
        ssc, escs = cls.group([0])
        return ssc, escs[0]

    def send(self, record: bytes, robot: int) -> None:
        if self.closed:
            raise TransportError(f"{self.name}: closed")
        peer = self.peers.get(robot)
        if peer is None or robot in self.lost:
            self.dropped += 1  # no such link, or lost: as a socket with no peer
            return
        peer.inbox.append(bytes(record))
        with contextlib.suppress(BlockingIOError):
            os.write(peer._w, b"\0")

    def receive(self, ready: Collection[int] | None = None) -> list[bytes]:
        if self.closed:
            raise TransportError(f"{self.name}: closed")
        with contextlib.suppress(BlockingIOError):
            while os.read(self._r, 4096):
                pass
        out = list(self.inbox)
        self.inbox.clear()
        if not out and self.peers and len(self.lost) == len(self.peers):
            why = "; ".join(sorted(set(self.lost.values())))
            raise TransportError(f"link to {self.name}'s peer lost: {why}")
        return out

    def fds(self) -> list[int]:
        return [] if self.closed else [self._r]

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        for robot, peer in self.peers.items():
            if not peer.closed:
                peer.lost[robot] = "closed by the peer"
                with contextlib.suppress(BlockingIOError, OSError):
                    os.write(peer._w, b"\0")
        os.close(self._r)
        os.close(self._w)


class _Links(Links):
    """An end's links: a robot's is lost when its peer end closed."""

    def __init__(self, end: Loopback) -> None:
        self.end = end

    def lost_links(self) -> dict[int, str]:
        end = self.end
        return dict(end.lost) if len(end.lost) < len(end.peers) else {}

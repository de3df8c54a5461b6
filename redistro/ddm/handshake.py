"""The run's handshake: what makes a record of an earlier run useless.

Every record is signed, but a key outlives a run (nodes started alone share
``ddm.key_file``), so a signature alone proves who made a record, not when.
Each ddm therefore draws a nonce (16 random bytes) when it starts, and:

1. The SSC's ddm signs its commands (and checks the feedback) with the run
   key, :func:`redistro.ddm.record.run_key` of the link's key and its own
   nonce, from the start. Until a robot's feedback comes, it says *hello*
   to that robot's ESC every ``HELLO_EVERY_S``: a hello carries its nonce
   (``peer`` empty), signed with the link's key.
2. An ESC's ddm that has no run key yet answers a hello with a *challenge*:
   its own nonce, and the hello's as ``peer``.
3. The SSC's ddm answers a challenge that names its own nonce (so the ESC
   that sent it is running now, and holds the key) with a *proof*: its
   nonce, and the challenge's as ``peer``; from then on it sends that robot
   its records.
4. An ESC's ddm takes the run key from a proof that names its own nonce,
   and no other: only a ddm that holds the link's key and saw this ESC's
   challenge, in this run, can make one. It then pins its peer (a socket's
   connection), and accepts commands signed with the run key only.

A hello, a command or feedback recorded in an earlier run and sent again is
refused: the records fail the run key (``forged``), and a hello naming a
nonce that is not the receiver's is counted ``stale`` and changes nothing.
A replayed hello only earns its sender a challenge it cannot answer; it
never pins a peer, and the genuine SSC's hello, coming after it, is
answered in turn. Cost: three records per robot at start-up, one HMAC per
hello; nothing per cycle.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import numpy as np

from redistro.ddm import record as wire

HELLO_EVERY_S = 0.05  # the SSC's hello to a robot whose feedback has not come yet
EMPTY = bytes(wire.NONCE_BYTES)


@dataclass
class Reply:
    """What a hello asks of the ddm: ``send`` this record to robot ``gid``;
    ``run_key``: take this key (an ESC's, from a proof)."""

    gid: int
    send: bytes = b""
    run_key: bytes = b""


@dataclass
class Handshake:
    """One ddm's side (``esc`` or not) for its local robots ``gids``."""

    esc: bool
    link_key: bytes
    source: str
    gids: list[int]
    nonce: bytes = field(default_factory=lambda: os.urandom(wire.NONCE_BYTES))
    stale: int = 0  # hellos signed with the key but not of this run (or not to us)
    seq: int = 0

    def __post_init__(self) -> None:
        # the SSC's ddm: a proof sent to the robot; an ESC's: the run key taken
        self.proven = [False] * len(self.gids)
        self.sent_ns = [0] * len(self.gids)
        # the SSC knows its run key from the start
        self.run_key = b"" if self.esc else wire.run_key(self.link_key, self.nonce)

    @property
    def done(self) -> bool:
        return all(self.proven)

    def hello(self, gid: int, peer: bytes = EMPTY) -> bytes:
        """A hello (peer empty), challenge or proof to robot ``gid``."""
        body = np.zeros((), wire.HELLO)
        now = time.monotonic_ns()
        body["stamp_ns"] = now
        body["nonce"] = np.frombuffer(self.nonce, np.uint8)
        body["peer"] = np.frombuffer(peer, np.uint8)
        self.seq += 1
        return wire.encode(
            wire.KIND_HELLO, gid, self.source, self.seq, now, body, key=self.link_key
        )

    def due(self, i: int, now_ns: int) -> bool:
        """The SSC's side: a hello to local robot ``i`` is due now."""
        if now_ns - self.sent_ns[i] < HELLO_EVERY_S * 1e9:
            return False
        self.sent_ns[i] = now_ns
        return True

    def take(self, gid: int, payload: bytes | memoryview) -> Reply | None:
        """A hello from robot ``gid``'s side (signed with the link's key,
        checked by the caller): what to do about it (None: nothing)."""
        body = np.frombuffer(bytes(payload[: wire.HELLO.itemsize]), wire.HELLO)[0]
        theirs, peer = bytes(body["nonce"]), bytes(body["peer"])
        if gid not in self.gids:
            return None  # another robot's handshake, on a broadcast medium
        i = self.gids.index(gid)
        if theirs == EMPTY:
            self.stale += 1
            return None
        if self.esc:
            if self.proven[i]:
                return None  # (the SSC says hello until our feedback reaches it)
            if peer == EMPTY:  # a hello: challenge it with our nonce
                return Reply(gid, send=self.hello(gid, theirs))
            if peer == self.nonce:  # a proof of this run: the run key is theirs
                self.proven[i] = True
                self.run_key = wire.run_key(self.link_key, theirs)
                return Reply(gid, run_key=self.run_key)
            self.stale += 1  # a proof of another run, or to another ESC
            return None
        if peer != self.nonce:
            self.stale += 1  # a challenge of another run (or a hello: SSCs do not talk)
            return None
        self.proven[i] = True  # the ESC is running now and holds the key
        return Reply(gid, send=self.hello(gid, theirs))

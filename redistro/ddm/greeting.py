"""A ddm's side of the run's handshake (:mod:`redistro.ddm.handshake` keeps
its state): the SSC's hellos until every robot's feedback came, a hello's
answer, and an ESC taking the run's key from the SSC's proof."""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

from redistro.ddm import record as wire
from redistro.errors import WireError

if TYPE_CHECKING:
    from redistro.ddm.worker import Ddm


class Greeting:
    """One ddm's greeting (see the module's text)."""

    def __init__(self, ddm: Ddm) -> None:
        self.d = ddm
        self.stale_seen = 0

    def greet(self) -> None:
        """The SSC's side: a hello to each robot whose feedback has not come
        yet (every ``HELLO_EVERY_S``), until every robot's has."""
        d = self.d
        now = time.monotonic_ns()
        waiting = False
        for i, g in enumerate(d.gid[r] for r in d.robots):
            if d.ex[i]["updates"]:
                d.links.authenticated(g)  # (its link brought this run's records)
                continue
            waiting = True
            if d.handshake.due(i, now) and d.links.can_send(g):
                d.transport.send(d.handshake.hello(g), g)
        d.links.flush()
        d.greeted = not waiting

    def hello(self, raw: bytes, robot: int) -> None:
        """A hello of the handshake, signed with the link's key (checked)."""
        d = self.d
        reply = d.handshake.take(robot, memoryview(raw)[wire.PAYLOAD_AT :])
        if reply is None:
            stale = d.handshake.stale
            if stale != self.stale_seen:
                for ex in d.ex:
                    ex["stale"] += stale - self.stale_seen
                    ex["dropped"] += stale - self.stale_seen
                self.stale_seen = stale
                d.dirty = True
                if d.kind == "esc":
                    d.links.drop_unauthenticated()  # not our SSC of this run
            return
        if reply.send:
            d.transport.send(reply.send, reply.gid)
            d.links.flush()
        if reply.run_key:
            self.take_run_key(reply.run_key)
        d.shaken = d.handshake.done
        for ex, proven in zip(d.ex, d.handshake.proven, strict=True):
            if proven and not ex["linked"]:
                ex["linked"] = 1
                d.dirty = d.urgent = True

    def authentic(self, raw: bytes) -> bool:
        """Whether a record is sound and signed (a hello with the link's key,
        the rest with this run's)."""
        d = self.d
        hello = len(raw) == wire.SIZE and raw[6] == wire.KIND_HELLO
        try:
            wire.check(raw, d.link_key if hello else d.key)
        except WireError:
            return False
        return True

    def take_run_key(self, key: bytes) -> None:
        """An ESC's side: the SSC's proof came; its records, and ours, are
        signed with this run's key from now on, and the link is pinned."""
        d = self.d
        d.key = key
        if d.encrypt:
            d.cipher = wire.cipher_key(key)
        for enc in d.encoders:
            enc.rekey(key)
        if d.kernel_path is not None:
            d.kernel_path.rekey(key)
        d.links.authenticated()
        d.post("handshake done: this run's key taken from the SSC's proof", logging.DEBUG)
        d.urgent = d.dirty = True

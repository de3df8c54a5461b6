"""A ddm's admission of one record, in Python: every case.

The ``ddm_admit`` kernel takes the common case (ddm/step_kernel.c); what it
leaves comes here, and here is everything when the kernels are off: the
record checked (size, magic, version, kind, checksum, tag: hellos with the
link's key, the rest with the run's), a hello handed to the handshake,
another node's traffic left alone, a refusal counted (duplicate, out of
order, stale), and an admitted record's effects: the payload into Local
Data, the exchange counted, an incoming e-stop raised, an ESC's starving
index paid back, the command latency taken.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any

from redistro.ddm import record as wire
from redistro.errors import WireError

if TYPE_CHECKING:
    from redistro.ddm.worker import Ddm


def _stamp_of(payload: Any) -> int:
    """The producer's stamp [ns] at the start of a (decrypted) payload."""
    return int.from_bytes(bytes(payload[:8]), "little", signed=True)


class PythonAdmission:
    """One ddm's admission of the records the kernel left (see the module's text)."""

    def __init__(self, ddm: Ddm) -> None:
        self.d = ddm

    def take(self, raw: bytes) -> int:
        """1 when ``raw`` was admitted as a fresh record, else 0."""
        d = self.d
        if (
            not d.handshake.run_key  # an ESC before the SSC's proof
            and len(raw) == wire.SIZE
            and raw[6] != wire.KIND_HELLO
            and (raw[6] != d.in_kind or raw[7] not in d.local)
        ):
            return 0  # another robot's traffic: without the run key, not ours to judge
        checked = self._check(raw)
        if checked is None:
            return 0
        kind, robot, source, seq, stamp, estop = checked
        if kind == wire.KIND_HELLO:
            d.greeting.hello(raw, robot)
            return 0
        i = d.local.get(robot)
        if kind != d.in_kind or i is None:
            return 0  # another node's traffic on a broadcast medium (authentic)
        ex = d.ex[i]
        if d.kernel_path is not None:
            why = d.kernel_path.refuse(d.admission, i, source, kind, robot, seq, stamp)
        else:
            why = d.admission.refuse(source, kind, robot, seq, stamp)
        if why:
            ex[why] += 1
            ex["dropped"] += 1
            return 0
        d.links.authenticated()
        if estop and not ex["estop_in"]:
            self._estop_in(ex, source)
        self._admitted(i, raw, kind, robot, seq)
        return 1

    def _check(self, raw: bytes) -> tuple[int, int, bytes, int, int, int] | None:
        """The record's header when it is sound and authentic (every record
        is checked, another node's traffic on a broadcast medium too: a
        forgery is counted whoever it claims to be); else counted, None."""
        d = self.d
        hello = len(raw) == wire.SIZE and raw[6] == wire.KIND_HELLO
        try:
            return wire.check(raw, d.link_key if hello else d.key)
        except WireError as exc:
            field = "forged" if exc.reason == "auth" else "malformed"
            for ex in d.ex:
                ex[field] += 1
                ex["dropped"] += 1
            if field == "forged" and d.kind == "esc":
                # not the SSC: whoever holds the link goes (a new
                # connection may take it: the SSC reconnecting)
                d.links.drop_unauthenticated()
            return None

    def _estop_in(self, ex: Any, source: bytes) -> None:
        d = self.d
        d.urgent = True
        name = source.rstrip(b"\0")
        ex["estop_in"] = 1
        ex.array["estop_source"] = name[:16]
        d.post(f"e-stop from {name.decode(errors='replace')}", logging.ERROR)
        d.estop_request = True

    def _admitted(self, i: int, raw: bytes, kind: int, robot: int, seq: int) -> None:
        """An admitted record's effects (see the module's text)."""
        d = self.d
        ex = d.ex[i]
        now = time.monotonic_ns()
        payload: Any = memoryview(raw)[wire.PAYLOAD_AT : wire.PAYLOAD_AT + d.in_size]
        if d.cipher:
            payload = memoryview(wire.crypt(d.cipher, kind, robot, seq, payload))
        if d.hooks is not None:
            payload = d.hooks.command(payload)
        d.in_blocks[i].publish(payload)
        if not ex["fresh"]:
            d.urgent = True
        if not d.commanded:
            d.commanded = True
            d.answers.open_state()
            if d.replying:  # ... feedback goes out as the replies to commands
                ex["feedback_wanted"] = 0
        ex["updates"] += 1
        ex["last_update_ns"] = now
        ex["fresh"] = 1
        if d.kind != "esc":
            return
        # a fresh command pays back every command the sender sent on the
        # strength of the old one
        d.sent_block.read_into(d.sent_rec.bytes)
        d.delivered_rec["count"] = d.sent_rec["count"]
        d.delivered_rec["stamp_ns"] = now
        d.delivered_block.publish(d.delivered_rec.bytes)
        stamp = wire.payload_stamp(raw) if not d.cipher else _stamp_of(payload)
        if 0 < stamp <= now:
            if d.kernel_path is not None:
                d.kernel_path.add_latency(now - stamp)
            else:
                d.latency.add(now - stamp)

"""The ddm's common case in compiled code: a record admitted, a record emitted.

A ddm's step is a few system calls and, around them, the same small work
on every record: check its checksum and tag, admit it (a newer seq and
stamp from its source), publish its payload into Local Data, count it,
pay back the starving index, take the command latency; on the way out,
read the node's block, encode, checksum and sign. Done in Python that is
two dozen interpreter-level calls per record, which a process woken cold
pays several times over. :class:`KernelPath` plans the kernels
``ddm_admit`` and ``ddm_emit`` once, in Initialization, over the ddm's own
records and Local Data; each takes the common case in one call and leaves
everything else (a record to refuse and count, an e-stop, the first record
of a link, a torn read) untouched for the ddm's Python path, which handles
every case. The two paths share one state: the exchange and out records,
the wire seq and last-sent counters, the latency ring, and each robot's
admission state for the source that claimed it (:meth:`refuse`).

Cost per record: one kernel call (about 1 µs hot) where the Python path
made two dozen. Used when the kernels are built and nothing wraps the
ddm's transport (the fault harness's hooks take the Python path).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from redistro.ddm import record as wire
from redistro.ddm import wire_layout
from redistro.kernels import KERNELS, plan, table
from redistro.localdata.block import Record
from redistro.localdata.layout import EXCHANGE
from redistro.localdata.segment import LocalData
from redistro.process.stats import Samples

_U64 = (1 << 64) - 1


def _signed(seq: int) -> int:
    """A u8 seq stored in an int64 row (the kernel reads it back unsigned)."""
    return seq - (1 << 64) if seq >= 1 << 63 else seq


def _field(dtype: np.dtype[Any], name: str) -> int:
    fields = dtype.fields
    assert fields is not None
    return int(fields[name][1])


class KernelPath:
    """The compiled common case of one ddm (see the module's text).

    ld: the node's Local Data; gids: each local robot's group-wide id;
    in_blocks, out_blocks: (name, index) of the blocks records come into
    and go out from; in_kind, out_kind: the record kinds; source: this
    node's name; key: the link's key; starving: an ESC pays back its
    starving index; latency: the ring command latencies go into.
    """

    def __init__(
        self,
        ld: LocalData,
        gids: list[int],
        in_blocks: list[tuple[str, int]],
        out_blocks: list[tuple[str, int]],
        in_kind: int,
        out_kind: int,
        source: str,
        key: bytes,
        starving: bool,
        latency: Samples,
    ) -> None:
        assert KERNELS is not None
        n = len(gids)
        out_dtype = wire.PAYLOADS[out_kind]
        # the plans hold this buffer: rekey() changes the key of every kernel
        self.codec = wire.codec_record(key)
        ld_raw = ld.raw
        # the records both paths share: exchange and out records in arenas
        self.ex_arena = np.zeros(n * EXCHANGE.itemsize, dtype=np.uint8)
        self.ex = [Record(EXCHANGE, self.ex_arena, i * EXCHANGE.itemsize) for i in range(n)]
        self.out_arena = np.zeros(n * out_dtype.itemsize, dtype=np.uint8)
        self.out = [Record(out_dtype, self.out_arena, i * out_dtype.itemsize) for i in range(n)]

        self._plan_admission(ld, gids, in_blocks, in_kind, starving, latency)
        self._plan_emission(ld, gids, out_blocks, out_kind, source)
        # sending on stream sockets (a transport that has them): each robot's
        # socket, refreshed when the transport's peers change; per robot the
        # bytes sent or -errno; ddm_reply's outcome (the emit's mask, the
        # send's trouble bits)
        self.send_fds = np.full(n, -1, dtype=np.int64)
        self.send_status = np.zeros(n, dtype=np.int64)
        self.reply = np.zeros((), wire_layout.REPLY)
        self.send_plan = plan(
            "ddm_send", wire=self.wire, fds=self.send_fds, status=self.send_status, reply=self.reply
        )
        self.admit_call = KERNELS.ddm_admit
        self.emit_call = KERNELS.ddm_emit
        self.recv_call = KERNELS.ddm_recv
        self.send_call = KERNELS.ddm_send
        self.reply_call = KERNELS.ddm_reply
        # the exchange records published into Local Data in one call
        rows = []
        for i in range(n):
            seq_off, pay_off, size = ld.block_offsets("exchange", i)
            rows.append((seq_off, pay_off, size, i * EXCHANGE.itemsize))
        self.publish_plan = plan(
            "seq_write", dst=ld_raw, src=self.ex_arena, table=table("seq_write", "table", rows)
        )
        self.publish_call = KERNELS.seq_write
        # the Python path's counters, in the kernels' rows
        self.seq = self.emit_rows["seq"]
        self.last_out = self.emit_rows["last_out"]
        self.mask = self.state["mask"]  # the last ddm_recv's admitted records
        self.taken = self.state["taken"]  # records the kernels admitted

    def _plan_admission(
        self,
        ld: LocalData,
        gids: list[int],
        in_blocks: list[tuple[str, int]],
        in_kind: int,
        starving: bool,
        latency: Samples,
    ) -> None:
        """ddm_admit's plan: where a record's fields lie, each robot's in
        block and claiming source, the state both paths share."""
        n, codec, ld_raw = len(gids), self.codec, ld.raw
        in_dtype = wire.PAYLOADS[in_kind]
        head = wire.HEADER
        # one row per local robot: its gid, its in block, its claiming source's state
        self.admit_rows = np.zeros(n, wire_layout.ADMIT_ROW)
        for i, (g, (name, index)) in enumerate(zip(gids, in_blocks, strict=True)):
            row = self.admit_rows[i]
            row["gid"] = g
            row["seq_off"], row["pay_off"], _ = ld.block_offsets(name, index)
        self.src = np.zeros(n * 16, dtype=np.uint8)
        sent = ld.block_offsets("starving_sent") if starving else (-1, -1, 0)
        delivered = ld.block_offsets("starving_delivered") if starving else (-1, -1, 0)
        self.state = np.zeros((), wire_layout.ADMIT_STATE)
        self.latency = latency
        p = np.zeros((), wire_layout.ADMIT_PARAMS)
        p["magic"], p["version"], p["kind"] = wire.MAGIC, wire.VERSION, in_kind
        p["payload_at"], p["size"] = wire.PAYLOAD_AT, in_dtype.itemsize
        for f in ("magic", "version", "kind", "robot", "source", "seq", "estop"):
            p[f"h_{f}"] = _field(head, f)
        p["h_stamp"] = _field(head, "stamp_ns")
        p["ex_size"], p["ex_updates"] = EXCHANGE.itemsize, _field(EXCHANGE, "updates")
        p["ex_last"], p["ex_fresh"] = _field(EXCHANGE, "last_update_ns"), _field(EXCHANGE, "fresh")
        p["sent_seq"], p["sent_pay"], p["deliv_seq"], p["deliv_pay"] = (*sent[:2], *delivered[:2])
        self.admit_plan = plan(
            "ddm_admit",
            ld=ld_raw,
            codec=codec,
            params=p,
            rows=self.admit_rows,
            src=self.src,
            ex=self.ex_arena,
            lat=latency._buf,
            state=self.state,
        )

    def _plan_emission(
        self,
        ld: LocalData,
        gids: list[int],
        out_blocks: list[tuple[str, int]],
        out_kind: int,
        source: str,
    ) -> None:
        """ddm_emit's plan: each robot's out block, its wire record (the
        header's constant part written once), the fields the kernel sets."""
        n, codec, ld_raw = len(gids), self.codec, ld.raw
        out_dtype, head = wire.PAYLOADS[out_kind], wire.HEADER
        self.emit_rows = np.zeros(n, wire_layout.EMIT_ROW)
        for i, (name, index) in enumerate(out_blocks):
            row = self.emit_rows[i]
            row["seq_off"], row["pay_off"], _ = ld.block_offsets(name, index)
        self.wire = np.zeros(n * wire.SIZE, dtype=np.uint8)
        mem = memoryview(self.wire)  # type: ignore[arg-type]
        for i, g in enumerate(gids):  # the header's constant part, once
            wire.HEAD.pack_into(
                mem, i * wire.SIZE, wire.MAGIC, wire.VERSION, out_kind, g, source.encode()[:16],
                0, 0, 0, 0,
            )  # fmt: skip
        self.wire_views = [mem[i * wire.SIZE : (i + 1) * wire.SIZE] for i in range(n)]
        e = np.zeros((), wire_layout.EMIT_PARAMS)
        e["payload_at"], e["size"] = wire.PAYLOAD_AT, out_dtype.itemsize
        e["seqsrc_at"] = _field(out_dtype, "seq_src")
        e["h_seq"], e["h_stamp"] = _field(head, "seq"), _field(head, "stamp_ns")
        e["h_estop"] = _field(head, "estop")
        e["ex_size"], e["ex_sent"] = EXCHANGE.itemsize, _field(EXCHANGE, "sent")
        self.emit_plan = plan(
            "ddm_emit",
            ld=ld_raw,
            codec=codec,
            params=e,
            rows=self.emit_rows,
            out=self.out_arena,
            wire=self.wire,
            ex=self.ex_arena,
        )

    def rekey(self, key: bytes) -> None:
        """Verify and sign with ``key`` from now on (every plan's codec, in place)."""
        self.codec[...] = wire.codec_record(key)

    def admit(self, raw: bytes) -> int:
        """The local robot whose block took ``raw``, or -1: the Python path's."""
        i: int = self.admit_call(self.admit_plan, raw)
        return i

    def emit(self) -> int:
        """A bit mask of the robots whose ``wire_views[i]`` is to be sent, or -1."""
        mask: int = self.emit_call(self.emit_plan)
        return mask

    # -- the Python path, on the same state --

    def claimed(self, i: int, source: bytes) -> bool:
        row = self.admit_rows[i]
        return bool(row["claimed"]) and bytes(self.src[16 * i : 16 * i + 16]) == source

    def refuse(
        self,
        admission: wire.Admission,
        i: int,
        source: bytes,
        kind: int,
        robot: int,
        seq: int,
        stamp: int,
    ) -> str:
        """Admission of an in-kind record for local robot i on the Python path:
        the claiming source's state is the row's; the first source admitted
        claims the row (its state moves there)."""
        row = self.admit_rows[i]
        if self.claimed(i, source):
            last_seq = int(row["last_seq"]) & _U64  # the kernel compares seqs unsigned
            why = ""
            if seq == last_seq:
                why = "duplicate"
            elif seq < last_seq:
                why = "out_of_order"
            elif stamp <= row["last_stamp"]:
                why = "stale"
            if why:
                admission.dropped[why] += 1
                return why
            row["last_seq"], row["last_stamp"] = _signed(seq), stamp
            admission.accepted += 1
            return ""
        why = admission.refuse(source, kind, robot, seq, stamp)
        if not why and not row["claimed"]:
            admission.last.pop((source, kind, robot), None)
            self.src[16 * i : 16 * i + 16] = np.frombuffer(source.ljust(16, b"\0")[:16], np.uint8)
            row["last_seq"], row["last_stamp"], row["claimed"] = _signed(seq), stamp, 1
        return why

    def add_latency(self, value_ns: int) -> None:
        lat = self.latency._buf
        count = int(self.state["latency_count"])
        lat[count % lat.shape[0]] = value_ns
        self.state["latency_count"] = count + 1

    def latency_count(self) -> int:
        return int(self.state["latency_count"])

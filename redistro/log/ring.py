"""The log ring: a node's last cycles, captured by its manager, drained by its logging worker.

The session log records every cycle of a node. Its logging worker runs at
the lowest real-time priority, last in the cycle, so a busy or stalled host
holds it off now and then; what it would have read is gone by the time it
runs. So the logged blocks do not wait for it: at every tick, before it
dispatches the next cycle, the manager (the highest priority of the node)
copies the blocks of the cycle that just ended, and every process's status
row, into one slot of a ring in shared memory (a kernel call for the
blocks, one for the slot). The logging worker drains every slot it has not
recorded yet, whenever it runs: up to ``slots`` cycles late, nothing is
lost; later than that, the overwritten cycles are counted as dropped.

A slot is seqlocked; its payload is the cycle's frame as the log writer
takes it (:mod:`redistro.log.writer`): the cycle, its tick's due and taken
times, the node's e-stop, the logged blocks' payloads back to back, the
status rows. ``/redistro.<sid>.<node>.logring`` belongs to the manager (it
creates and unlinks it); the logging worker attaches.
"""

from __future__ import annotations

import contextlib
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from redistro import kernels
from redistro.errors import IPCError, LayoutError
from redistro.ipc import names
from redistro.ipc.session import Manifest
from redistro.ipc.shm import SharedMemory
from redistro.localdata.layout import BLOCKS, PROC_STATUS

OBJECT = "logring"
MAGIC = b"RDSTRING"
# ring header: magic, slots, slot size, payload size, layout hash, captured (last cycle)
HEADER = struct.Struct("<8sIIIQQ")
CAPTURED_AT = 8 + 4 + 4 + 4 + 8
# after the header: the last cycle the logging worker has taken (sent, or
# counted lost); in lockstep the plant holds its tick while the worker is
# more than half the ring behind (redistro.plant.lockstep)
DRAINED_AT = 40
HEADER_BYTES = 64
# a payload starts with: cycle, tick due, tick taken, e-stop (then padding)
FRAME_HEAD = struct.Struct("<QqqB7x")
SLOTS = 1024  # 5 s at 200 Hz, 1 s at 1 kHz


@dataclass(frozen=True)
class RingLayout:
    """Where each logged block and the status rows lie in a payload."""

    blocks: tuple[tuple[str, int | None, int, int], ...]  # name, index, offset, size
    rows_offset: int
    n_procs: int
    payload: int

    @classmethod
    def of(cls, topics: list[tuple[str, str, int | None]], n_procs: int) -> RingLayout:
        """topics: (topic, block name, robot index) of the node's log channels."""
        at = FRAME_HEAD.size
        blocks = []
        for _topic, name, index in topics:
            size = BLOCKS[name][0].itemsize
            blocks.append((name, index, at, size))
            at += size
        rows = at
        at += n_procs * PROC_STATUS.itemsize
        return cls(tuple(blocks), rows, n_procs, at)

    @property
    def slot(self) -> int:
        """A slot: its sequence counter, then the payload, padded to 64 bytes."""
        return (8 + self.payload + 63) // 64 * 64

    def hash(self) -> int:
        """The same in every process (Python's own hash of a str is salted)."""
        import zlib

        return zlib.crc32(repr((self.blocks, self.rows_offset, self.n_procs)).encode())


class LogRing:
    def __init__(self, shm: SharedMemory, layout: RingLayout, slots: int) -> None:
        self.shm = shm
        self.layout = layout
        self.slots = slots
        self.raw = np.frombuffer(shm.buffer, dtype=np.uint8)
        self._mem = memoryview(self.raw)  # type: ignore[arg-type]
        self._captured = self._mem[CAPTURED_AT : CAPTURED_AT + 8].cast("Q")
        self._drained = self._mem[DRAINED_AT : DRAINED_AT + 8].cast("Q")
        # each slot's counter and payload as views made once (a reader takes
        # one slot per cycle; making and releasing two views cost more than
        # the copy)
        self._seqs: list[Any] = []
        self._srcs: list[memoryview] = []
        for k in range(slots):
            at = HEADER_BYTES + k * layout.slot
            self._seqs.append(self._mem[at : at + 8].cast("Q"))
            self._srcs.append(self._mem[at + 8 : at + 8 + layout.payload])

    @staticmethod
    def _size(layout: RingLayout, slots: int) -> int:
        return HEADER_BYTES + slots * layout.slot

    @classmethod
    def create(
        cls,
        session_id: str,
        node: str,
        layout: RingLayout,
        slots: int = SLOTS,
        manifest: Manifest | None = None,
    ) -> LogRing:
        name = names.object_name(session_id, node, OBJECT)
        shm = SharedMemory.create(name, cls._size(layout, slots), manifest)
        ring = cls(shm, layout, slots)
        HEADER.pack_into(ring._mem, 0, MAGIC, slots, layout.slot, layout.payload, layout.hash(), 0)
        return ring

    @classmethod
    def attach(cls, session_id: str, node: str, layout: RingLayout) -> LogRing:
        name = names.object_name(session_id, node, OBJECT)
        shm = SharedMemory.attach(name)
        try:
            magic, slots, slot, payload, h, _ = HEADER.unpack_from(shm.buffer, 0)
            if magic != MAGIC or slot != layout.slot or payload != layout.payload:
                raise LayoutError(f"{name}: not a log ring of this layout")
            if h != layout.hash():
                raise LayoutError(f"{name}: layout hash differs")
            return cls(shm, layout, int(slots))
        except Exception:
            shm.close()
            raise

    @property
    def captured(self) -> int:
        """The last cycle captured (0: none yet)."""
        return int(self._captured[0])

    @property
    def drained(self) -> int:
        """The last cycle the logging worker has taken (0: none yet)."""
        return int(self._drained[0])

    @drained.setter
    def drained(self, cycle: int) -> None:
        self._drained[0] = cycle

    def slot_offset(self, cycle: int) -> int:
        return HEADER_BYTES + (cycle % self.slots) * self.layout.slot

    def read(self, cycle: int, dst: memoryview) -> bool:
        """Cycle ``cycle``'s payload into ``dst``; False when its slot holds
        another cycle by now (overwritten) or is mid-write past a few tries."""
        k = cycle % self.slots
        seq, src = self._seqs[k], self._srcs[k]
        for _ in range(4):
            s1 = seq[0]
            if s1 & 1:
                continue
            dst[:] = src
            if seq[0] == s1:
                return bool(FRAME_HEAD.unpack_from(dst, 0)[0] == cycle)
        return False

    def close(self) -> None:
        for view in (*self._seqs, *self._srcs):
            view.release()
        self._seqs, self._srcs = [], []
        self._captured.release()
        self._drained.release()
        self._mem.release()
        self.raw = np.empty(0, dtype=np.uint8)
        with contextlib.suppress(IPCError):
            self.shm.close()

    def unlink(self) -> None:
        self.shm.unlink()


class Capture:
    """The manager's side: each tick, the cycle that just ended into its slot."""

    def __init__(self, ring: LogRing, ld: Any) -> None:
        self.ring = ring
        lay = ring.layout
        self.staging = np.zeros(lay.payload, dtype=np.uint8)
        self._head = memoryview(self.staging)  # type: ignore[arg-type]
        rows = [(*ld.block_offsets(name, index), at) for name, index, at, _size in lay.blocks]
        rows += [
            (*ld.block_offsets("proc", j), lay.rows_offset + j * PROC_STATUS.itemsize)
            for j in range(lay.n_procs)
        ]
        self._read_table = kernels.table("seq_read", "table", rows)
        # the slot's seq and payload (set per cycle), the size, from the staging's start
        self._write_table = kernels.table("seq_write", "table", [(0, 0, lay.payload, 0)])
        self._slot_seq, self._slot_payload = self._write_table["seq"], self._write_table["payload"]
        self.torn = np.zeros(len(rows), dtype=np.int64)  # blocks held mid-write (kept as were)
        self._kernels = kernels.AVAILABLE
        if self._kernels:
            self._read = kernels.plan(
                "seq_read", src=ld.raw, dst=self.staging, table=self._read_table, torn=self.torn
            )
            self._write = kernels.plan(
                "seq_write", dst=ring.raw, src=self.staging, table=self._write_table
            )
        else:
            self._blocks = [ld.block(name, index) for name, index, _a, _s in lay.blocks]
            self._blocks += [ld.block("proc", j) for j in range(lay.n_procs)]

    def __call__(self, cycle: int, due_ns: int, tick_ns: int, estop: bool) -> None:
        ring = self.ring
        FRAME_HEAD.pack_into(self._head, 0, cycle, due_ns, tick_ns, 1 if estop else 0)
        at = ring.slot_offset(cycle)
        if self._kernels:
            kernels.KERNELS.seq_read(self._read)
            self._slot_seq[0] = at
            self._slot_payload[0] = at + 8
            kernels.KERNELS.seq_write(self._write)
        else:
            self._capture_python(at)
        ring._captured[0] = cycle

    def _capture_python(self, at: int) -> None:
        from redistro.errors import TornReadTimeout

        rows = zip(self._read_table["size"].tolist(), self._read_table["dst"].tolist(), strict=True)
        for block, (size, dst) in zip(self._blocks, rows, strict=True):
            with contextlib.suppress(TornReadTimeout):
                block.read_into(self._head[dst : dst + size], budget_s=0.0005)
        mem = self.ring._mem
        seq = mem[at : at + 8].cast("Q")
        s = seq[0]
        s += s & 1
        seq[0] = s + 1
        mem[at + 8 : at + 8 + self.ring.layout.payload] = self._head
        seq[0] = s + 2
        seq.release()


class Progress:
    """How far a node's logging worker lags its manager, read from outside
    (the lockstep plant): the ring's header alone."""

    def __init__(self, shm: SharedMemory) -> None:
        self.shm = shm
        mem = memoryview(shm.buffer)
        self._captured = mem[CAPTURED_AT : CAPTURED_AT + 8].cast("Q")
        self._drained = mem[DRAINED_AT : DRAINED_AT + 8].cast("Q")
        self.slots = int(HEADER.unpack_from(shm.buffer, 0)[1])
        mem.release()

    @classmethod
    def attach(cls, session_id: str, node: str) -> Progress | None:
        """The node's ring, or None: it has none (no logging worker)."""
        try:
            shm = SharedMemory.attach(names.object_name(session_id, node, OBJECT))
        except IPCError:
            return None
        if bytes(shm.buffer[:8]) != MAGIC:
            shm.close()
            return None
        return cls(shm)

    def lag(self) -> int:
        """Cycles captured that the logging worker has not taken yet."""
        return int(self._captured[0]) - int(self._drained[0])

    def close(self) -> None:
        self._captured.release()
        self._drained.release()
        with contextlib.suppress(IPCError):
            self.shm.close()

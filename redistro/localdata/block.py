"""Seqlocked blocks: one writer, many readers, never a torn snapshot.

Protocol (the writer is the only process that writes the block):

- write: ``seq += 1`` (now odd), write the payload, ``seq += 1`` (even again);
- read: load ``seq``; if odd, retry; copy the payload; load ``seq`` again; if
  it changed, the copy may be torn: count it and retry, until a time budget
  runs out (then :class:`~redistro.errors.TornReadTimeout`).

Stores and loads are each a separate C call on x86-64 (TSO: stores are not
reordered with stores, loads not with loads), which is what the protocol needs.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any, cast

import numpy as np

from redistro.errors import TornReadTimeout
from redistro.localdata.layout import MSG_TEXT, MSGBOX_SLOTS

DEFAULT_READ_BUDGET_S = 0.005
_BACKOFF_S = 20e-6


_WORD_FORMATS = {"u8": "Q", "i8": "q", "f8": "d", "u4": "I", "i4": "i", "u2": "H", "i2": "h"}
_WORD_FORMATS.update({"u1": "B", "i1": "b", "f4": "f"})


class Record:
    """A process-local record of a block's payload dtype, with fast scalar access.

    The hot paths of a cycle work on a Record: a reader takes a snapshot into
    it (``block.read_into(rec.bytes)``) and reads scalars (``rec["cycle"]``);
    a writer keeps its block's record locally, sets scalars and publishes it
    whole (``block.publish(rec.bytes)``). Scalar access goes through cached
    memoryview words, ten times cheaper than indexing a numpy record; arrays
    and nested fields are reached through ``rec.array``.
    """

    def __init__(self, dtype: np.dtype[Any], buffer: Any = None, offset: int = 0) -> None:
        """buffer, offset: where the record lies (default: its own memory)."""
        self.array: np.ndarray[Any, Any] = (
            np.zeros((), dtype)
            if buffer is None
            else np.ndarray((), dtype=dtype, buffer=buffer, offset=offset)
        )
        self.bytes = _bytes_of(self.array)
        fields = dtype.fields
        assert fields is not None
        self._words: dict[str, Any] = {}  # name -> one-element memoryview
        for name, spec in fields.items():
            ftype, off = spec[0], spec[1]
            code = f"{ftype.kind}{ftype.itemsize}"
            if ftype.shape or ftype.fields is not None or code not in _WORD_FORMATS:
                continue
            word: Any = self.bytes[off : off + ftype.itemsize]
            self._words[name] = word.cast(_WORD_FORMATS[code])

    def __getitem__(self, name: str) -> Any:
        return self._words[name][0]

    def __setitem__(self, name: str, value: int | float) -> None:
        self._words[name][0] = value

    def word(self, name: str) -> Any:
        """The one-element memoryview of a scalar field (``word[0]``), for a
        loop that sets the field without the lookup."""
        return self._words[name]

    def release(self) -> None:
        """Drop the memoryviews (before the record is discarded with a mapping)."""
        for word in self._words.values():
            word.release()
        self._words.clear()
        self.bytes.release()


def _bytes_of(array: np.ndarray[Any, Any]) -> memoryview:
    """A byte memoryview of an array's memory (uint8 arrays as they are)."""
    if array.dtype != np.uint8:
        array = array.reshape(-1).view(np.uint8)
    return memoryview(array)  # type: ignore[arg-type]


class Block:
    """A view onto one seqlocked block of a mapped segment.

    Reads copy the payload as raw bytes (one memcpy) and view the copy with
    the payload dtype: a field-by-field structured copy costs ten times more.
    """

    def __init__(self, name: str, view: np.ndarray[Any, Any]) -> None:
        self.name = name
        fields = view.dtype.fields
        assert fields is not None
        seq_off = fields["seq"][1]
        payload, data_off = fields["data"][0], fields["data"][1]
        raw = view.reshape(1).view(np.uint8)
        # The hot path works on memoryviews: a load, a store or a slice copy
        # through a memoryview costs a third of the same numpy call.
        self._mem = memoryview(raw)  # type: ignore[arg-type]
        self._seq = self._mem[seq_off : seq_off + 8].cast("Q")  # one aligned 8-byte word
        self._raw = self._mem[data_off : data_off + payload.itemsize]
        self._payload = payload
        self.data = view["data"]  # 0-d structured view; write only inside write()
        self.torn = 0  # retries this handle needed (read side)
        self._words: list[Any] = []  # handed out by word(), released with the mapping

    @property
    def seq(self) -> int:
        return self._seq[0]

    def word(self, name: str) -> Any:
        """A one-element memoryview onto one byte-sized field of the payload,
        in place: a flag that is read alone needs no snapshot (one byte is
        never torn)."""
        fields = self._payload.fields
        assert fields is not None
        ftype, off = fields[name][0], int(fields[name][1])
        if ftype.itemsize != 1 or ftype.shape:
            raise ValueError(f"{self.name}.{name}: not a one-byte field")
        view: Any = self._raw[off : off + 1]
        word = view.cast(_WORD_FORMATS[f"{ftype.kind}1"])
        self._words.append(word)
        return word

    def counter(self, name: str) -> Any:
        """A one-element memoryview onto an 8-byte unsigned field of the
        payload, in place, for a watcher that reads that one counter alone
        (a cycle, a step, a sequence number: a value only the field's
        writer moves forward). None when the field straddles a cache line:
        a load could then be torn, and the watcher takes a snapshot."""
        fields = self._payload.fields
        assert fields is not None
        ftype, off = fields[name][0], int(fields[name][1])
        if ftype.itemsize != 8 or ftype.shape or ftype.kind != "u":
            raise ValueError(f"{self.name}.{name}: not an 8-byte counter")
        view: Any = self._raw[off : off + 8]
        address = np.frombuffer(view, dtype=np.uint8).ctypes.data
        if address % 64 > 56:
            return None
        word = view.cast("Q")
        self._words.append(word)
        return word

    def load(self, word: Any) -> int | None:
        """One word of the payload (from :meth:`counter`) under the block's
        seqlock: its value, or None while a write is in progress."""
        seq = self._seq[0]
        if seq & 1:
            return None
        value = int(word[0])
        return value if self._seq[0] == seq else None

    def spin_until_changed(self, last: int, deadline_ns: int) -> int:
        """Busy-wait until the sequence counter differs from ``last`` and is
        even (a finished write); return it, or ``last`` when the monotonic
        deadline passes. For a reader that owns a CPU and wants the lowest
        latency; a cyclic process reads once per cycle instead."""
        seq = self._seq
        n = 0
        while True:
            s = seq[0]
            if s != last and not s & 1:
                return s
            n += 1
            if not n & 255 and time.monotonic_ns() > deadline_ns:
                return last

    @contextmanager
    def write(self) -> Iterator[np.ndarray[Any, Any]]:
        """``with block.write() as d: d["q_rad"] = q`` -- the one writer only."""
        s = self._seq[0]
        if s & 1:  # a writer died mid-write earlier: resume from an even count
            s += 1
        self._seq[0] = s + 1
        try:
            yield self.data
        finally:
            self._seq[0] = s + 2

    def publish(self, record: np.ndarray[Any, Any] | memoryview) -> None:
        """Write a whole prepared record in one copy: the fast path for a writer
        that builds its record locally, then publishes it.

        record: an array of the payload dtype (one element), its raw bytes
        (uint8), or a byte memoryview of those (the fastest).
        """
        if type(record) is not memoryview:
            record = _bytes_of(record)
        seq = self._seq
        s = seq[0]
        s += s & 1
        seq[0] = s + 1
        self._raw[:] = record
        seq[0] = s + 2

    def read(self, budget_s: float = DEFAULT_READ_BUDGET_S) -> np.void:
        """A consistent copy of the payload (a numpy record).

        A failed attempt means the writer is inside its write. If it was
        preempted there by this (higher-priority) reader on the same CPU,
        spinning would keep it from finishing: so retry at once a few times,
        then yield the CPU, then sleep a little between attempts.
        """
        out = np.empty((), self._payload)
        self.read_into(out, budget_s)
        return cast(np.void, out[()])

    def read_into(
        self, out: np.ndarray[Any, Any] | memoryview, budget_s: float = DEFAULT_READ_BUDGET_S
    ) -> None:
        """Like :meth:`read`, into a preallocated 0-d array of the payload dtype,
        its raw bytes (uint8), or a byte memoryview of it (the fastest): no
        allocation, for polling readers."""
        dst = out if type(out) is memoryview else _bytes_of(out)
        deadline = 0
        seq = self._seq
        raw = self._raw
        attempts = 0
        while True:
            s1 = seq[0]
            if not s1 & 1:
                dst[:] = raw
                if seq[0] == s1:
                    return
            self.torn += 1
            attempts += 1
            now = time.monotonic_ns()
            if deadline == 0:
                deadline = now + int(budget_s * 1e9)
            elif now > deadline:
                raise TornReadTimeout(f"block {self.name}: no consistent snapshot in {budget_s} s")
            if attempts > 8:
                time.sleep(_BACKOFF_S)
            elif attempts > 2:
                os.sched_yield()

    def detach(self) -> None:
        """Drop the views onto the mapping (the segment is being unmapped)."""
        for mv in (*self._words, self._seq, self._raw, self._mem):
            mv.release()
        self._words.clear()
        empty = memoryview(bytearray(max(8, self._payload.itemsize)))
        self._mem = empty
        self._seq = empty[:8].cast("Q")
        self._raw = empty[: self._payload.itemsize]
        self.data = np.zeros((), self._payload)

    def raw_read(self) -> np.void:
        """A copy taken without the protocol (tests use it as a negative control)."""
        return np.frombuffer(bytes(self._raw), self._payload)[0]  # type: ignore[no-any-return]


_NONE: list[tuple[int, int, str]] = []  # never appended to: drain's "nothing new"


def _word(field: np.ndarray[Any, Any]) -> Any:
    """A one-element memoryview onto a 0-d u8 field (in place)."""
    return memoryview(field.reshape(1).view(np.uint8)).cast("Q")  # type: ignore[arg-type]


class MessageBox:
    """A process's ring of short text messages; the process writes, the manager reads.

    Each slot is seqlocked on its own; ``head`` counts messages ever written.
    A reader that falls more than a ring behind counts the lost messages.
    """

    def __init__(self, view: np.ndarray[Any, Any]) -> None:
        self._view = view
        self._head = view["head"]
        self._slots = view["slots"]
        # the head as one memoryview word: a reader polls it every cycle, and
        # a numpy field read costs ten times more
        self._head_word = _word(self._head)
        self._read = int(self._head)  # reader's position
        self.lost = 0

    def detach(self) -> None:
        """Drop the views onto the mapping (the segment is being unmapped)."""
        view = np.zeros((), self._view.dtype)
        self._head_word.release()
        self._view, self._head, self._slots = view, view["head"], view["slots"]
        self._head_word = _word(self._head)

    def post(self, text: str, level: int = 20) -> None:
        head = int(self._head)
        i = head % MSGBOX_SLOTS
        slot = self._slots[i : i + 1]
        s = int(slot["seq"][0])
        s += s & 1
        slot["seq"] = s + 1
        slot["number"] = head
        slot["stamp_ns"] = time.monotonic_ns()
        slot["level"] = level
        slot["text"] = text.encode("utf-8", "replace")[:MSG_TEXT]
        slot["seq"] = s + 2
        self._head[...] = head + 1

    def drain(self) -> list[tuple[int, int, str]]:
        """New messages since the last drain: (stamp_ns, level, text)."""
        head = self._head_word[0]
        if head == self._read:
            return _NONE
        out: list[tuple[int, int, str]] = []
        if head - self._read > MSGBOX_SLOTS:
            self.lost += head - self._read - MSGBOX_SLOTS
            self._read = head - MSGBOX_SLOTS
        while self._read < head:
            i = self._read % MSGBOX_SLOTS
            slot = self._slots[i : i + 1]
            s1 = int(slot["seq"][0])
            copy = slot.copy()[0]
            if s1 & 1 or int(slot["seq"][0]) != s1 or int(copy["number"]) != self._read:
                self.lost += 1  # overwritten while, or before, we read it
            else:
                text = bytes(copy["text"]).decode("utf-8", "replace")
                out.append((int(copy["stamp_ns"]), int(copy["level"]), text))
            self._read += 1
        return out

"""A set of boards' register banks in one byte buffer, the image.

Per board type one structured array (a row per board, by address), for
``in`` and ``out`` banks alike, all in one buffer: vectorized code reaches a
field of every board of a type at once (``image.inp[BoardType.DAC]["code"]``),
and a compiled kernel reaches any register by its byte offset
(:meth:`RegisterImage.offset`). The simulated chassis keeps its boards'
registers in one; a robot-level driver keeps its snapshot of its boards, and
the outputs it stages, in another.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from redistro.config.hardware import Channel
from redistro.drivers.io import registers as R
from redistro.drivers.io.registers import BANKS, BoardType


class RegisterImage:
    """``rec_in[a]`` and ``rec_out[a]`` are 0-d views of board ``a``'s banks,
    ``bytes_in[a]`` and ``bytes_out[a]`` their raw bytes (uint8 views)."""

    def __init__(self, boards: dict[int, BoardType]) -> None:
        self.types = dict(boards)
        self.row: dict[int, int] = {}
        by_type = {
            t: sorted(a for a, bt in boards.items() if bt == t)
            for t in BoardType
            if t != BoardType.NONE
        }
        size = sum(
            len(a) * (BANKS[t][0].itemsize + BANKS[t][1].itemsize) + 16 for t, a in by_type.items()
        )
        self.image = np.zeros(size, dtype=np.uint8)
        self.base: dict[tuple[BoardType, str], int] = {}
        self.inp: dict[BoardType, np.ndarray[Any, Any]] = {}
        self.out: dict[BoardType, np.ndarray[Any, Any]] = {}
        at = 0
        for t, addrs in by_type.items():
            for side, dt, arrays in (("in", BANKS[t][0], self.inp), ("out", BANKS[t][1], self.out)):
                at = (at + 7) // 8 * 8
                self.base[(t, side)] = at
                arrays[t] = np.ndarray((len(addrs),), dtype=dt, buffer=self.image, offset=at)
                at += len(addrs) * dt.itemsize
            self.inp[t]["board_type"] = int(t)
            self.inp[t]["channels"] = R.CHANNELS[t]
            self.inp[t]["status"] = R.STATUS_OK
            for i, a in enumerate(addrs):
                self.row[a] = i
        rows = {a: slice(self.row[a], self.row[a] + 1) for a in boards}
        self.rec_in = {a: self.inp[t][rows[a]].reshape(()) for a, t in boards.items()}
        self.rec_out = {a: self.out[t][rows[a]].reshape(()) for a, t in boards.items()}
        self.bytes_in = {a: self.inp[t][rows[a]].view(np.uint8) for a, t in boards.items()}
        self.bytes_out = {a: self.out[t][rows[a]].view(np.uint8) for a, t in boards.items()}

    def offset(self, t: BoardType, side: str, row: int, name: str) -> int:
        """Byte offset in the image of field ``name`` of board ``row`` of type ``t``."""
        dt = BANKS[t][0 if side == "in" else 1]
        fields = dt.fields
        assert fields is not None
        return self.base[(t, side)] + row * dt.itemsize + int(fields[name][1])

    def offsets(
        self, t: BoardType, side: str, name: str, rows: Any, ch: Any = None, width: int = 0
    ) -> np.ndarray[Any, Any]:
        """Byte offsets of field ``name`` of boards ``rows`` (each + its channel
        ``ch`` x ``width`` bytes: one register of a register array)."""
        chs = [0] * len(rows) if ch is None else [int(c) for c in ch]
        return np.array(
            [
                self.offset(t, side, int(r), name) + width * c
                for r, c in zip(rows, chs, strict=True)
            ],
            dtype=np.int64,
        )

    def wires(self, channels: list[Channel | None], first_joint: int) -> list[tuple[int, ...]]:
        """(joint, row, channel) of the fitted ones among ``channels`` (one per
        joint of a robot whose first joint is ``first_joint`` in a joint vector)."""
        return [
            (first_joint + j, self.row[c.address], c.index)
            for j, c in enumerate(channels)
            if c is not None
        ]

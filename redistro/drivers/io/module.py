"""Base of the I/O module drivers: one board, its address, its output bank."""

from __future__ import annotations

from typing import Any

import numpy as np

from redistro.drivers.io.backplane import Backplane
from redistro.drivers.io.registers import BANKS, BoardType


class ModuleDriver:
    """An I/O module driver keeps the board's ``out`` bank locally and writes it
    whole (``flush``); it decodes the board's ``in`` bank from a snapshot."""

    TYPE: BoardType = BoardType.NONE

    def __init__(
        self, backplane: Backplane, address: int, out: np.ndarray[Any, Any] | None = None
    ) -> None:
        """out: where to keep the ``out`` bank (a 0-d record of the board
        type's out dtype, e.g. a row of a register image); default its own."""
        self.backplane = backplane
        self.address = address
        self.out: np.ndarray[Any, Any] = np.zeros((), BANKS[self.TYPE][1]) if out is None else out

    def flush(self) -> None:
        self.backplane.write(self.address, self.out)

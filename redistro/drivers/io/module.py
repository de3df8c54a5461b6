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

    def __init__(self, backplane: Backplane, address: int) -> None:
        self.backplane = backplane
        self.address = address
        self.out: np.ndarray[Any, Any] = np.zeros((), BANKS[self.TYPE][1])

    def flush(self) -> None:
        self.backplane.write(self.address, self.out)

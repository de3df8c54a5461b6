"""Driver of the 24-bit digital I/O board (home switches in, brakes out)."""

from __future__ import annotations

from typing import Any

import numpy as np

from redistro.drivers.io.module import ModuleDriver
from redistro.drivers.io.registers import DIO_MASK, BoardType


class DioDriver(ModuleDriver):
    TYPE = BoardType.DIO

    @staticmethod
    def bits(rec: np.ndarray[Any, Any], which: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        """Input levels of bits ``which`` (bool array)."""
        return np.asarray((int(rec["inputs"]) >> which) & 1 == 1)

    def set_bits(self, which: np.ndarray[Any, Any], on: bool | np.ndarray[Any, Any]) -> None:
        """Stage output bits; ``flush`` sends."""
        word = int(self.out["outputs"])
        levels = np.broadcast_to(np.asarray(on, dtype=bool), which.shape)
        for bit, level in zip(which.tolist(), levels.tolist(), strict=True):
            word = word | (1 << bit) if level else word & ~(1 << bit)
        self.out["outputs"] = word & DIO_MASK

    @staticmethod
    def output_bits(rec: np.ndarray[Any, Any], which: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        """The outputs as the board reports driving them (readback)."""
        return np.asarray((int(rec["outputs_readback"]) >> which) & 1 == 1)

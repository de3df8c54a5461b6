"""Driver of the 4-axis 24-bit quadrature encoder board."""

from __future__ import annotations

from typing import Any

import numpy as np

from redistro.drivers.io.module import ModuleDriver
from redistro.drivers.io.registers import ENC_MODULO, BoardType


class EncoderDriver(ModuleDriver):
    TYPE = BoardType.ENCODER

    def preset(self, axis: int, value: int) -> int:
        """Ask the board to load ``value`` into ``axis``; returns the request
        number the board echoes in ``preset_ack`` once done."""
        self.out["preset_value"][axis] = value % ENC_MODULO
        self.out["preset_req"][axis] += 1
        return int(self.out["preset_req"][axis])

    def set_latch_mode(self, axis: int, mode: int) -> None:
        self.out["latch_mode"][axis] = mode

    def latch(self, axis: int) -> int:
        """Software latch request; returns its number."""
        self.out["latch_req"][axis] += 1
        return int(self.out["latch_req"][axis])

    @staticmethod
    def preset_done(rec: np.ndarray[Any, Any], axis: int, req: int) -> bool:
        return int(rec["preset_ack"][axis]) == req

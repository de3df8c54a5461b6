"""Driver of the 16-channel 12-bit bipolar +-10 V DAC board."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from redistro.drivers.io.module import ModuleDriver
from redistro.drivers.io.registers import BoardType, dac_volts


class DacDriver(ModuleDriver):
    TYPE = BoardType.DAC

    def set_codes(self, channels: np.ndarray[Any, Any], codes: np.ndarray[Any, Any]) -> None:
        """Stage output codes (within the converter's range); ``flush`` sends."""
        self.out["code"][channels] = codes

    def flush(self) -> None:
        # a new watchdog value on every write (never 0, which disables it)
        self.out["watchdog"] = (time.monotonic_ns() >> 10) & 0xFFFFFFFF or 1
        super().flush()

    def zero(self) -> None:
        self.out["code"][:] = 0

    @staticmethod
    def readback_volts(rec: np.ndarray[Any, Any], channels: np.ndarray[Any, Any]) -> Any:
        return dac_volts(rec["readback"][channels])

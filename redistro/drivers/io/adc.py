"""Driver of the 16-channel 16-bit ADC board (torque sensors, tachometers)."""

from __future__ import annotations

from typing import Any

import numpy as np

from redistro.drivers.io.module import ModuleDriver
from redistro.drivers.io.registers import BoardType, adc_volts


class AdcDriver(ModuleDriver):
    TYPE = BoardType.ADC

    @staticmethod
    def volts(rec: np.ndarray[Any, Any], channels: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        return adc_volts(rec["code"][channels])

"""Driver of the 6-axis force/torque sensor receiver."""

from __future__ import annotations

from typing import Any

import numpy as np

from redistro.drivers.io.module import ModuleDriver
from redistro.drivers.io.registers import BoardType


class ForceDriver(ModuleDriver):
    TYPE = BoardType.FORCE

    @staticmethod
    def wrench(rec: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        """[Fx, Fy, Fz, Mx, My, Mz] (N, N m) in the sensor frame: the board's
        calibration matrix applied to its raw gauge counts."""
        c = np.asarray(rec["calibration"], dtype=np.float64)
        return np.asarray(c @ rec["strain"].astype(np.float64))

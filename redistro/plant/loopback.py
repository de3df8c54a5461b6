"""A controller's backplane straight onto a chassis in the same process: the
kernels benchmark and the tests drive a real :class:`RobotDriver` against a
real chassis without a plant process between them."""

from __future__ import annotations

from typing import Any

import numpy as np

from redistro.drivers.io.backplane import Backplane
from redistro.drivers.io.registers import BoardType


class ChassisLoopback(Backplane):
    """``read`` copies a board's ``in`` bank, ``write`` sets its ``out`` bank."""

    timeout_s = 0.5

    def __init__(self, chassis: Any) -> None:
        self.chassis = chassis

    def inventory(self) -> dict[int, BoardType]:
        return dict(self.chassis.boards)

    def read(self, addresses: list[int]) -> dict[int, np.ndarray[Any, Any]]:
        return {a: self.chassis.inp[a].copy() for a in addresses}

    def write(self, address: int, record: np.ndarray[Any, Any]) -> None:
        self.chassis.banks.rec_out[address][...] = record

    def close(self) -> None:
        pass

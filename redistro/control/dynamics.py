"""Rigid-body terms of one arm from Pinocchio, built from the plant's own URDF."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from redistro.robotmodel import JOINT_NAMES, Peg, write_arm_urdf

F64 = np.ndarray[Any, np.dtype[np.float64]]


class ArmModel:
    """Gravity torques of one arm (its tool included).

    The URDF is the plant's (:mod:`redistro.robotmodel`): same links, same
    inertias, same tool. The base is not rotated; gravity is -z.
    """

    def __init__(self, peg: Peg | None) -> None:
        import pinocchio as pin

        self._pin = pin
        with tempfile.TemporaryDirectory(prefix="redistro-pin-") as tmp:
            path = write_arm_urdf(Path(tmp), "arm", peg)
            self.model = pin.buildModelFromUrdf(str(path))
        names = [self.model.names[i] for i in range(1, self.model.njoints)]
        if names != JOINT_NAMES:
            raise ValueError(f"unexpected joints in the arm model: {names}")
        self.data = self.model.createData()

    def gravity(self, q: F64) -> F64:
        """g(q): joint torques [N m] that hold the arm still against gravity."""
        out: F64 = self._pin.computeGeneralizedGravity(self.model, self.data, q).copy()
        return out

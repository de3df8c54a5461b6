"""What every ESC process opens: the config, its robot's hardware, a driver."""

from __future__ import annotations

from dataclasses import dataclass

from redistro.config import Config
from redistro.config.hardware import RobotHardware
from redistro.drivers.io.backplane import open_backplane
from redistro.drivers.robot import RobotDriver
from redistro.process.spec import NodeSpec


@dataclass
class EscContext:
    cfg: Config
    robot: str
    hw: RobotHardware

    @classmethod
    def load(cls, spec: NodeSpec) -> EscContext:
        """The node's config and its robot's hardware (read and checked once by
        the session owner, handed down resolved in its spec)."""
        return cls(spec.cfg(), spec.robots[0], spec.hardware())

    def driver(self, session_id: str) -> RobotDriver:
        """A robot-level driver over its own backplane connection (not yet opened)
        to the plant of ``session_id``."""
        bp = open_backplane(self.cfg.plant, session_id)
        return RobotDriver(self.hw, bp, self.cfg.plant.physics_hz)


def plant_session(spec: NodeSpec) -> str:
    """The session whose plant the node drives: its own, or the one named in
    the params (a node started alone beside a plant of another session)."""
    return spec.plant_session

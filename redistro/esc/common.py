"""What every ESC process opens: the config, its robot's hardware, a driver."""

from __future__ import annotations

from dataclasses import dataclass, replace

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
        plant = replace(self.cfg.plant, io_timeout_ms=1e3 * io_timeout_s(self.cfg))
        bp = open_backplane(plant, session_id)
        return RobotDriver(self.hw, bp, plant.physics_hz)


def io_timeout_s(cfg: Config) -> float:
    """How long a board may go unpublished before the driver calls it an I/O
    fault: ``plant.io_timeout_ms``; in lockstep at least the start-up
    timeout. There the plant is the clock: one held off the CPUs is slow,
    not gone (serving the boards before the first tick, a lockstep plant
    was once starved 565 ms on a loaded host); a dead one sends no tick
    (the manager's tick timeout) and its owner sees it end."""
    t = cfg.plant.io_timeout_ms / 1e3
    return max(t, cfg.session.startup_timeout_s) if cfg.session.clock == "lockstep" else t


def plant_session(spec: NodeSpec) -> str:
    """The session whose plant the node drives: its own, or the one named in
    the params (a node started alone beside a plant of another session)."""
    return spec.plant_session

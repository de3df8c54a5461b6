"""A plant process with both robots' drivers, for integration tests."""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from redistro.config.hardware import load_hardware
from redistro.config.loader import load_config
from redistro.config.model import Config
from redistro.drivers.io.backplane import open_backplane
from redistro.drivers.robot import RobotDriver
from redistro.ipc.session import Session
from redistro.localdata.block import Block
from redistro.plant.launch import PlantProcess


@dataclass
class Rig:
    cfg: Config
    session: Session
    plant: PlantProcess
    drivers: dict[str, RobotDriver]
    truths: dict[str, Block]

    def truth(self, robot: str) -> np.void:
        return self.truths[robot].read()

    def wait_released(self, robot: str, joints: list[int], timeout_s: float = 2.0) -> None:
        """Until the plant's truth shows the joints' brakes released (the
        driver's one write taken), with a deadline: a release that never
        arrives is named as such, not found later as an arm that did not move."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if not self.truth(robot)["braked"][joints].any():
                return
            time.sleep(0.001)  # polling the plant's truth with a deadline
        held = [j + 1 for j in joints if self.truth(robot)["braked"][j]]
        raise AssertionError(f"{robot}: the plant never took the release of joints {held}")

    def sim_time_s(self) -> float:
        t = self.plant.clock_s()  # the clock a session's time budget counts on
        assert t is not None
        return t

    def run_for(self, sim_seconds: float, body: Any = None, timeout_s: float = 60.0) -> None:
        """Call ``body()`` once a plant step (as a driver's loop writes once
        a cycle: as fast as Python can, its writes flooded the CAN bus past
        the chassis' socket buffer, a brake's write lost among them) until
        the plant's clock advanced by ``sim_seconds``."""
        now = self.sim_time_s()
        end, last = now + sim_seconds, -1.0
        deadline = time.monotonic() + timeout_s
        while now < end:
            if time.monotonic() > deadline:
                raise AssertionError(f"plant did not advance {sim_seconds} s in {timeout_s} s")
            if body is not None and now != last:
                last = now
                body()
            else:
                time.sleep(0.0002 if body is not None else 0.005)  # the plant's clock, polled
            now = self.sim_time_s()

    def synced(self, robot: str) -> tuple[Any, np.void]:
        """Feedback and ground truth from the same plant step (retries until they match)."""
        for _ in range(200):
            before = self.truth(robot)
            fb = self.drivers[robot].read_feedback()
            after = self.truth(robot)
            for tr in (before, after):
                if fb.coherent and int(tr["step"]) == fb.step:
                    return fb, tr
        raise AssertionError("could not catch feedback and truth in the same step")


@contextlib.contextmanager
def above_the_load() -> Iterator[None]:
    """This process at real-time priority (10: below the nodes of a session
    beside it, above everything else) while it drives or watches the plant
    step by step; as it was where that is refused. A test process stalled
    by the load beside it (another worker's lockstep sessions, at normal
    priority) wrote its torques late, or saw a stop late."""
    try:
        policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
    except OSError:
        yield
        return
    try:
        yield
    finally:
        os.sched_setscheduler(0, policy, param)


@contextlib.contextmanager
def plant_rig(backplane: str, tmp: Path, overrides: list[str] | None = None) -> Iterator[Rig]:
    sets = [f"plant.backplane={backplane}", *(overrides or [])]
    cfg = load_config(None, sets)
    hardware = load_hardware(cfg)
    with Session.create() as session:
        plant = PlantProcess.start(session, tmp / "run", cfg)
        drivers: dict[str, RobotDriver] = {}
        try:
            assert plant.bank is not None
            for name, hw in hardware.items():
                bp = open_backplane(cfg.plant, session.id)
                drivers[name] = RobotDriver(hw, bp, cfg.plant.physics_hz)
                drivers[name].open()
            names = plant.bank.robot_names
            truths = {n: plant.bank.truth(names.index(n)) for n in hardware}
            rig = Rig(cfg, session, plant, drivers, truths)
            rig.run_for(0.2)  # the brakes take up the load; the arms settle
            for name, d in drivers.items():  # encoders read the true angles from here on
                d.preset_encoders(rig.truth(name)["q_rad"])
            yield rig
        finally:
            for d in drivers.values():
                with contextlib.suppress(Exception):
                    d.freeze()
                d.close()
            plant.stop()


class Model:
    """Test-side dynamics (a second PyBullet world of the same config): gravity
    torques and the tool-tip Jacobian, to drive the arms from the test."""

    def __init__(self, cfg: Config) -> None:
        from redistro.plant.world import World

        self.world = World(cfg)
        self.pb = self.world.pb

    def gravity(self, robot: str, q: np.ndarray) -> np.ndarray:
        arm = self.world.arms[robot]
        z = [0.0] * 7
        return np.asarray(
            self.pb.calculateInverseDynamics(
                arm.body, list(map(float, q)), z, z, physicsClientId=self.world.client
            )
        )

    def jacobian(self, robot: str, q: np.ndarray, tip: list[float]) -> np.ndarray:
        arm = self.world.arms[robot]
        z = [0.0] * 7
        jl, _ja = self.pb.calculateJacobian(
            arm.body,
            arm.tool_link,
            tip,
            list(map(float, q)),
            z,
            z,
            physicsClientId=self.world.client,
        )
        return np.asarray(jl)

    def ik(self, robot: str, xyz: list[float], rpy: list[float]) -> np.ndarray:
        arm = self.world.arms[robot]
        quat = self.pb.getQuaternionFromEuler(rpy)
        q = self.pb.calculateInverseKinematics(
            arm.body,
            arm.tool_link,
            xyz,
            quat,
            maxNumIterations=500,
            residualThreshold=1e-6,
            physicsClientId=self.world.client,
        )
        return np.asarray(q[:7])

    def close(self) -> None:
        self.world.close()

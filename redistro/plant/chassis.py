"""The simulated I/O chassis: boards wired to the arms' devices.

Each step: take the controller's ``out`` banks (DAC codes, brake bits,
encoder presets and latch requests), drive the motors and brakes, step the
world, then convert the new joint states into the ``in`` banks (counters,
home bits and latches, ADC codes, wrist gauges). Wiring comes from the I/O
interface configs; device constants from the sensor/actuator configs.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from redistro.config.hardware import RobotHardware, by_board
from redistro.config.model import Config
from redistro.drivers.io import registers as R
from redistro.drivers.io.registers import BANKS, BOARD_NAMES, BoardType
from redistro.plant.devices import Encoders, HomeSwitches, Motors, WristSensor
from redistro.plant.world import Arm, World


@dataclass(frozen=True)
class Group:
    """Joints of one robot wired to one board: joint indices and channel indices."""

    address: int
    joints: np.ndarray
    idx: np.ndarray


def _groups(channels: list[Any]) -> list[Group]:
    return [Group(a, js, ks) for a, (js, ks) in by_board(channels).items()]


@dataclass
class RobotRig:
    """One robot's devices and where its joints are wired."""

    name: str
    arm: Arm
    hw: RobotHardware
    motors: Motors
    encoders: Encoders
    homes: HomeSwitches
    wrist: WristSensor | None
    brake_torque_nm: np.ndarray
    tach_v: np.ndarray
    torque_v: np.ndarray
    enc: list[Group]
    dac: list[Group]
    home: list[Group]
    brake: list[Group]
    torque: list[Group]
    tach: list[Group]
    q: np.ndarray = field(default_factory=lambda: np.zeros(7))
    qd: np.ndarray = field(default_factory=lambda: np.zeros(7))
    tau: np.ndarray = field(default_factory=lambda: np.zeros(7))
    wrench: np.ndarray = field(default_factory=lambda: np.zeros(6))
    tool_xyz: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tool_rot: np.ndarray = field(default_factory=lambda: np.eye(3))


class Chassis:
    def __init__(self, cfg: Config, world: World, hardware: dict[str, RobotHardware]) -> None:
        self.world = world
        self.boards: dict[int, BoardType] = {}
        for hw in hardware.values():
            for b in hw.io.boards.values():
                self.boards[b.address] = BOARD_NAMES[b.type]
        self.inp = {a: np.zeros((), BANKS[t][0]) for a, t in self.boards.items()}
        for a, t in self.boards.items():
            self.inp[a]["board_type"] = int(t)
            self.inp[a]["channels"] = R.CHANNELS[t]
            self.inp[a]["status"] = R.STATUS_OK
        self.rigs: list[RobotRig] = []
        for name, hw in hardware.items():
            s = hw.sensors
            arm = world.arms[name]
            q0 = np.asarray(cfg.robots[name].initial_q_rad, dtype=np.float64)
            disturbance = np.asarray(cfg.plant.encoder_disturbance_rad.get(name, [0.0] * 7))
            wrist = None
            if hw.wrist is not None:
                wrist = WristSensor(
                    np.asarray(s.ft_calibration),
                    np.asarray(cfg.plant.ft_bias.get(name, [0.0] * 6)),
                    cfg.plant.ft_noise_n,
                    cfg.plant.ft_noise_nm,
                    cfg.plant.seed + len(self.rigs),
                )
                self.inp[hw.wrist.address]["calibration"] = np.asarray(s.ft_calibration)
            js = hw.joints
            self.rigs.append(
                RobotRig(
                    name=name,
                    arm=arm,
                    hw=hw,
                    motors=Motors(s),
                    encoders=Encoders(s, q0, disturbance),
                    homes=HomeSwitches(s),
                    wrist=wrist,
                    brake_torque_nm=np.asarray(s.brake_torque_nm, dtype=np.float64),
                    tach_v=np.asarray(s.tach_volts_per_rad_s, dtype=np.float64),
                    torque_v=np.asarray(s.torque_volts_per_nm, dtype=np.float64),
                    enc=_groups([w.encoder for w in js]),
                    dac=_groups([w.dac for w in js]),
                    home=_groups([w.home for w in js]),
                    brake=_groups([w.brake for w in js]),
                    torque=_groups([w.torque for w in js]),
                    tach=_groups([w.tach for w in js]),
                )
            )
        self.step_count = 0
        self._sw_latches: dict[tuple[int, int], int] = {}  # last software latch request seen
        self._home_latch: dict[int, np.ndarray] = {  # encoder address -> axes latching on home
            a: np.zeros(R.ENC_AXES, dtype=bool)
            for a, t in self.boards.items()
            if t == BoardType.ENCODER
        }
        for rig in self.rigs:  # brakes on at power-up: the arms hold until released
            world.set_brakes(rig.arm, np.ones(7, dtype=bool), rig.brake_torque_nm)
        self._sample()

    # -- controller -> boards --

    def apply_outputs(self, outputs: dict[int, np.ndarray[Any, Any]]) -> None:
        """Take each board's ``out`` bank and act on it."""
        for a, modes in self._home_latch.items():
            modes[:] = outputs[a]["latch_mode"] == R.LATCH_HOME_EDGES
        for rig in self.rigs:
            volts = np.zeros(7)
            for g in rig.dac:
                code = outputs[g.address]["code"]
                volts[g.joints] = R.dac_volts(code[g.idx])
                self.inp[g.address]["readback"] = code
            # fail-safe brakes: engaged unless their release output is on
            brake = np.ones(7, dtype=bool)
            for g in rig.brake:
                word = int(outputs[g.address]["outputs"])
                brake[g.joints] = (word >> g.idx) & 1 == 0
                self.inp[g.address]["outputs_readback"] = word & R.DIO_MASK
            for g in rig.enc:
                out, inp = outputs[g.address], self.inp[g.address]
                for j, k in zip(g.joints.tolist(), g.idx.tolist(), strict=True):
                    req = int(out["preset_req"][k])
                    if req != int(inp["preset_ack"][k]):
                        rig.encoders.preset(j, float(rig.q[j]), int(out["preset_value"][k]))
                        inp["preset_ack"][k] = req
                        inp["counter"][k] = int(rig.encoders.counts(rig.q)[j])
                    req = int(out["latch_req"][k])
                    if req != self._sw_latches.get((g.address, k), 0):
                        self._sw_latches[(g.address, k)] = req
                        if int(out["latch_mode"][k]) == R.LATCH_SOFTWARE:
                            inp["latch"][k] = inp["counter"][k]
                            inp["latch_count"][k] += 1
            self.world.set_brakes(rig.arm, brake, rig.brake_torque_nm)
            # the amplifier is inhibited while its joint's brake is on (interlock)
            self.world.set_torques(rig.arm, rig.motors.joint_torque_nm(volts, ~brake))

    # -- physics --

    def step(self) -> None:
        self.world.step()
        self.step_count += 1
        self._sample()

    def _sample(self) -> None:
        """Joint states -> every board's ``in`` bank."""
        for rig in self.rigs:
            rig.q, rig.qd, rig.tau = self.world.joint_states(rig.arm)
            self.world.settle_brakes(rig.arm, rig.q, rig.qd)
            counts = rig.encoders.counts(rig.q)
            before = rig.homes.state
            home = rig.homes.update(rig.q)
            edges = home != before
            for g in rig.enc:
                enc = self.inp[g.address]
                enc["counter"][g.idx] = counts[g.joints]
                enc["home"][g.idx] = home[g.joints]
                hit = edges[g.joints] & self._home_latch[g.address][g.idx]
                if hit.any():
                    axes, js = g.idx[hit], g.joints[hit]
                    enc["latch"][axes] = counts[js]
                    enc["latch_count"][axes] += 1
                    enc["latch_edge"][axes] = np.where(home[js], R.EDGE_RISING, R.EDGE_FALLING)
            for g in rig.home:
                dio = self.inp[g.address]
                weights = 1 << g.idx  # distinct bits (checked by the config)
                bits = int(home[g.joints] @ weights)
                dio["inputs"] = (int(dio["inputs"]) & ~int(weights.sum())) | bits
            for g in rig.torque:
                self.inp[g.address]["code"][g.idx] = R.adc_code(
                    rig.tau[g.joints] * rig.torque_v[g.joints]
                )
            for g in rig.tach:
                self.inp[g.address]["code"][g.idx] = R.adc_code(
                    rig.qd[g.joints] * rig.tach_v[g.joints]
                )
            if rig.wrist is not None and rig.hw.wrist is not None:
                rig.tool_xyz, rig.tool_rot = self.world.sensor_frame(rig.arm)
                rig.wrench = self.world.wrist_wrench(rig.arm, rig.tool_rot)
                ft = self.inp[rig.hw.wrist.address]
                ft["strain"] = rig.wrist.gauges(rig.wrench)
                ft["sample"] += 1
        for rec in self.inp.values():
            rec["step"] = self.step_count

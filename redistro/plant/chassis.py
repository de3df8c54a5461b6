"""The simulated I/O chassis: boards wired to the arms' devices.

Each step: take the controller's ``out`` banks (DAC codes, brake bits,
encoder presets and latch requests), drive the motors and brakes, step the
world, then convert the new joint states into the ``in`` banks (counters,
home bits and latches, ADC codes, wrist gauges). Wiring comes from the I/O
interface configs; device constants from the sensor/actuator configs.
"""

from __future__ import annotations

import time
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
        self.physics_ns = 0  # CPU time of the last PyBullet step
        # the amplifiers' watchdog: per DAC board, (last value, when it moved)
        self.watchdog_ns = round(cfg.plant.output_watchdog_ms * 1e6)
        self._wd: dict[int, tuple[int, int]] = {}
        self.watchdog_tripped = [False] * len(self.rigs)
        self.watchdog_trips: list[dict[str, Any]] = []  # robot, monotonic_ns, step
        self._sw_latches: dict[tuple[int, int], int] = {}  # last software latch request seen
        self._home_latch: dict[int, np.ndarray] = {  # encoder address -> axes latching on home
            a: np.zeros(R.ENC_AXES, dtype=bool)
            for a, t in self.boards.items()
            if t == BoardType.ENCODER
        }
        # the fault harness's point in the boards and devices (None normally)
        from redistro.faults import inject

        self.injection = inject.injection("plant.")
        if self.injection is not None:
            self.injection.defer_record = True  # the loop records it once on the boards
        self._inj_rig = next(
            (
                i
                for i, r in enumerate(self.rigs)
                if self.injection and self.injection.concerns(r.name)
            ),
            0,
        )
        self._inj_done = False
        self._last_home = [np.zeros(7, dtype=bool) for _ in self.rigs]
        for rig in self.rigs:  # brakes on at power-up: the arms hold until released
            world.set_brakes(rig.arm, np.ones(7, dtype=bool), rig.brake_torque_nm)
        self._sample()

    # -- controller -> boards --

    def _watchdog(self, i: int, rig: RobotRig, outputs: dict[int, Any], now_ns: int) -> bool:
        """True while robot ``i``'s amplifiers are cut: its DAC boards' watchdog
        registers (when armed, non-zero) have not moved for the watchdog time."""
        if self.watchdog_ns <= 0:
            return False
        stale = armed = False
        for g in rig.dac:
            value = int(outputs[g.address]["watchdog"])
            last = self._wd.get(g.address)
            if last is None or last[0] != value:
                self._wd[g.address] = last = (value, now_ns)
            if value:
                armed = True
                stale = stale or now_ns - last[1] > self.watchdog_ns
        tripped = armed and stale
        if tripped and not self.watchdog_tripped[i] and len(self.watchdog_trips) < 1000:
            self.watchdog_trips.append(
                {"robot": rig.name, "step": self.step_count + 1, "monotonic_ns": now_ns}
            )
        self.watchdog_tripped[i] = tripped
        return tripped

    def apply_outputs(self, outputs: dict[int, np.ndarray[Any, Any]], now_ns: int = 0) -> None:
        """Take each board's ``out`` bank and act on it (``now_ns``: CLOCK_MONOTONIC,
        for the amplifiers' watchdog; 0 reads the clock)."""
        now_ns = now_ns or time.monotonic_ns()
        for a, modes in self._home_latch.items():
            modes[:] = outputs[a]["latch_mode"] == R.LATCH_HOME_EDGES
        for i, rig in enumerate(self.rigs):
            cut = self._watchdog(i, rig, outputs, now_ns)
            volts = np.zeros(7)
            for g in rig.dac:
                code = outputs[g.address]["code"]
                if not cut:
                    volts[g.joints] = R.dac_volts(code[g.idx])
                self.inp[g.address]["readback"] = code
            # fail-safe brakes: engaged unless their release output is on
            brake = np.ones(7, dtype=bool)
            for g in rig.brake:
                word = int(outputs[g.address]["outputs"])
                if not cut:  # the watchdog's relay also drops the brakes' release
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

    def _injected(self) -> str:
        """The live injected fault ('' when none)."""
        inj = self.injection
        if inj is None or not inj.live():
            return ""
        return inj.point.split(".", 1)[1]

    def step(self) -> None:
        what = self._injected()
        if what == "wrist-push":  # pressed down hard on the peg, every step
            rig = self.rigs[self._inj_rig]
            assert self.injection is not None
            self.world.push(rig.arm, np.array([0.0, 0.0, -(self.injection.arg or 300.0)]))
        elif what == "encoder-jump" and not self._inj_done:  # one counter glitch
            self._inj_done = True
            assert self.injection is not None
            self.rigs[self._inj_rig].encoders.offset[1] += int(self.injection.arg or 5000)
        t0 = time.thread_time_ns()
        self.world.step()
        self.physics_ns = time.thread_time_ns() - t0
        self.step_count += 1
        self._sample()

    def _sample(self) -> None:
        """Joint states -> every board's ``in`` bank."""
        for rig in self.rigs:
            rig.q, rig.qd, rig.tau = self.world.joint_states(rig.arm)
            self.world.settle_brakes(rig.arm, rig.q, rig.qd)
            counts = rig.encoders.counts(rig.q)
            home = rig.homes.update(rig.q).copy()
            if self.injection is not None and rig is self.rigs[self._inj_rig]:
                what = self._injected()
                if what in ("home-stuck-on", "home-stuck-off"):  # every switch of the robot
                    home[:] = what == "home-stuck-on"
            before = self._last_home[self.rigs.index(rig)]
            edges = home != before
            before[:] = home
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
                if (
                    self.injection is not None
                    and rig is self.rigs[self._inj_rig]
                    and self._injected() == "sensor-nan"
                ):  # the receiver's calibration memory corrupted
                    ft["calibration"][0, 0] = np.nan
        for rec in self.inp.values():
            rec["step"] = self.step_count

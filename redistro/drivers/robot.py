"""The robot-level driver: robot units in and out, whatever the boards.

Built from a robot's hardware configs (I/O interface and sensor/actuator) over
a backplane. ``read_feedback`` gives q [rad], qd [rad/s] (tachometer where
fitted, else differentiated over the boards' sample times), joint torque
[N m] (torque sensor where fitted, else the motor model applied to the DAC
output), wrist wrench [N, N m] in the sensor frame, home switch levels.
``send_torques`` converts joint torques to DAC volts through the motor model;
``freeze`` engages every brake and zeroes every DAC channel.

Past the house's ~400 lines: one robot's every unit conversion, in both
directions and for each board, is the driver's one job.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from redistro import kernels
from redistro.config.hardware import RobotHardware, by_board
from redistro.drivers import driver_layout
from redistro.drivers.driver_plans import driver_plans
from redistro.drivers.driver_reference import decode_numpy
from redistro.drivers.io import registers as R
from redistro.drivers.io.adc import AdcDriver
from redistro.drivers.io.backplane import Backplane
from redistro.drivers.io.dac import DacDriver
from redistro.drivers.io.dio import DioDriver
from redistro.drivers.io.encoder import EncoderDriver
from redistro.drivers.io.force import ForceDriver
from redistro.drivers.io.image import RegisterImage
from redistro.drivers.io.module import ModuleDriver
from redistro.drivers.io.registers import BOARD_NAMES, ENC_MODULO, LATCH_HOME_EDGES, BoardType
from redistro.errors import ConfigError, IOFault

DOF = 7
DRIVERS: dict[str, type[ModuleDriver]] = {
    "encoder": EncoderDriver,
    "dac": DacDriver,
    "adc": AdcDriver,
    "dio": DioDriver,
    "force": ForceDriver,
}


@dataclass
class Feedback:
    q_rad: np.ndarray
    qd_rad_s: np.ndarray
    tau_nm: np.ndarray
    wrench: np.ndarray  # sensor frame [Fx, Fy, Fz, Mx, My, Mz]
    home: np.ndarray  # bool (7,)
    brakes: np.ndarray  # bool (7,): brakes engaged, as the board drives its outputs
    step: int  # the plant step of the encoder sample (the oldest, if boards differ)
    stamp_ns: int  # CLOCK_MONOTONIC when read
    coherent: bool = True  # every encoder board sampled in the same plant step
    latch_count: np.ndarray | None = None  # (7,) home-edge latches so far, per joint
    latch_edge: np.ndarray | None = None  # (7,) EDGE_RISING / EDGE_FALLING of the last one
    latch_q_rad: np.ndarray | None = None  # (7,) joint position at the last latch [rad]


class RobotDriver:
    """The robot-level driver. Its boards' registers live in one register
    image (:mod:`redistro.drivers.io.image`): the last snapshot of their
    ``in`` banks and the ``out`` banks it stages; its decoded feedback and
    state in one arena. The per-cycle arithmetic (:meth:`sample`,
    :meth:`send_torques`) is a compiled kernel call each
    (:mod:`redistro.kernels`), with the same arithmetic kept in numpy
    (``use_kernels=False``), the reference the kernels are tested against."""

    def __init__(
        self,
        hw: RobotHardware,
        backplane: Backplane,
        physics_hz: float,
        *,
        use_kernels: bool | None = None,
    ) -> None:
        self.hw = hw
        self.name = hw.name
        self.bp = backplane
        self.physics_hz = physics_hz
        self.kernels = kernels.AVAILABLE if use_kernels is None else use_kernels
        s = hw.sensors
        self.counts_per_rad = (
            np.asarray(s.counts_per_rev, dtype=np.float64) * np.asarray(s.gear_ratio) / (2 * np.pi)
        )
        self.nm_per_volt = (
            np.asarray(s.amps_per_volt)
            * np.asarray(s.torque_constant_nm_a)
            * np.asarray(s.gear_ratio, dtype=np.float64)
        )
        self.tach_v = np.asarray(s.tach_volts_per_rad_s, dtype=np.float64)
        self.torque_v = np.asarray(s.torque_volts_per_nm, dtype=np.float64)
        # register codes -> robot units
        self.tach_scale = R.ADC_FULL_SCALE_V / 32768 / self.tach_v  # [rad/s per code]
        self.torque_scale = R.ADC_FULL_SCALE_V / 32768 / self.torque_v  # [N m per code]
        self.dac_scale = R.DAC_FULL_SCALE_V / 2048 * self.nm_per_volt  # [N m per code]
        self.volts_per_nm = 1.0 / self.nm_per_volt
        boards: dict[int, BoardType] = {
            b.address: BOARD_NAMES[b.type] for b in hw.io.boards.values()
        }
        self.regs = regs = RegisterImage(boards)
        self.modules: dict[int, ModuleDriver] = {
            b.address: DRIVERS[b.type](backplane, b.address, regs.rec_out[b.address])
            for b in hw.io.boards.values()
        }
        self.addresses = sorted(self.modules)
        js = hw.joints
        self.enc = by_board([w.encoder for w in js])
        self.dac = by_board([w.dac for w in js])
        self.home = by_board([w.home for w in js])
        self.brake = by_board([w.brake for w in js])
        self.torque = by_board([w.torque for w in js])
        self.tach = by_board([w.tach for w in js])
        self.has_tach = all(w.tach is not None for w in js)
        self.has_torque = all(w.torque is not None for w in js)
        # wires in joint order: (joint, board row, channel)
        wire = {
            kind: np.array(regs.wires([getattr(w, kind) for w in js], 0), dtype=np.int64)
            for kind in ("encoder", "dac", "home", "brake", "torque", "tach")
        }
        self._wire = wire
        self._arena(physics_hz)
        self.tau_cmd = self.arena.take("tau_cmd", np.float64, DOF)  # the torques send() writes
        # each joint's rounding error [DAC codes], carried into its next code
        # where the joint's carry is 1 (sensors.dac_error_feedback)
        self.dac_residual = self.arena.take("dac_residual", np.float64, DOF)
        self.dac_carry = self.arena.take("dac_carry", np.float64, DOF)
        self.dac_carry[...] = np.asarray(s.dac_error_feedback, dtype=np.float64)
        self._read: Any = None  # the batch reader and writer: made by open()
        self._write_dac: Any = None
        self._dac_watchdog = regs.out[BoardType.DAC]["watchdog"]
        self._enc_steps = regs.inp[BoardType.ENCODER]["step"]
        self._decode: Any = lambda: decode_numpy(self)
        if self.kernels:
            self._decode_plan, self._dac_plan = driver_plans(self)
            run, plan = kernels.KERNELS.driver_decode, self._decode_plan
            self._decode = lambda: run(plan)

    def _arena(self, physics_hz: float) -> None:
        """State and outputs in one arena (the acquisition copies out of it
        in one call): the figures, the encoders' unwrapping, what decoding
        keeps between samples and its parameters (driver_layout.py)."""
        a = self.arena = kernels.Arena(1024)
        self.q = a.take("q", np.float64, DOF)
        self.qd = a.take("qd", np.float64, DOF)
        self.tau = a.take("tau", np.float64, DOF)
        self.wrench = a.take("wrench", np.float64, 6)
        self.home_levels = a.take("home", np.bool_, DOF)
        self.brakes = a.take("brakes", np.bool_, DOF)
        self.latch_count = a.take("latch_count", np.uint32, DOF)
        self.latch_edge = a.take("latch_edge", np.uint8, DOF)
        self.latch_q = a.take("latch_q", np.float64, DOF)
        self.stamp_ns = a.take("stamp_ns", np.int64, 1)
        # encoder unwrapping: q = q_ref + (accumulated counts since the reference) / scale
        self._raw = a.take("raw", np.int64, DOF)
        self._acc = a.take("acc", np.int64, DOF)
        self._q_ref = a.take("q_ref", np.float64, DOF)
        self._prev_q = a.take("prev_q", np.float64, DOF)
        # what decoding keeps between samples, and its parameters (driver_layout.py)
        st = self._state = a.take("state", driver_layout.STATE, ())
        st["prev_step"] = -1
        self.step_now = st["step"]  # the boards' sample number of the last sample
        a.alias("step", self.step_now)
        pa = self._params = a.take("params", driver_layout.PARAMS, ())
        pa["physics_hz"], pa["retry"] = physics_hz, 1.0
        pa["has_tach"], pa["has_torque"] = float(self.has_tach), float(self.has_torque)
        self._retry = pa["retry"]  # 0 while an incoherent snapshot is decoded as it is
        self._jump = a.take("jump", driver_layout.JUMP, ())  # a refused counter change

    @property
    def jump_limit_rad_s(self) -> float:
        """Speed above which a counter change is a glitch (0: not checked)."""
        return float(self._params["jump_limit_rad_s"])

    @jump_limit_rad_s.setter
    def jump_limit_rad_s(self, value: float) -> None:
        self._params["jump_limit_rad_s"] = value

    # -- set-up --

    def open(self, owner: bool = True) -> None:
        """Check the chassis against the I/O config; as the owner, set the
        encoders' latch sources and freeze.

        A board's output registers are written whole from the driver's own
        copy, so each must have one writer at a time: the owner (the ESC
        manager) writes the encoder boards (latch sources, presets); a
        non-owner (an ESC worker) never writes them, and leaves the brakes
        and DAC outputs as they are.
        """
        chassis = self.bp.inventory()
        for name, b in self.hw.io.boards.items():
            if b.address not in chassis:
                found = ", ".join(f"{a}:{t.name.lower()}" for a, t in sorted(chassis.items()))
                raise ConfigError(
                    f"{self.hw.io_path}: boards.{name}.address: no board at address "
                    f"{b.address} in the chassis (it has {found or 'none'})"
                )
            if chassis[b.address] != BOARD_NAMES[b.type]:
                raise ConfigError(
                    f"{self.hw.io_path}: boards.{name}.type: the chassis has a "
                    f"{chassis[b.address].name.lower()} board at address {b.address}, not {b.type}"
                )
        regs = self.regs
        self._read = self.bp.reader({a: regs.bytes_in[a] for a in self.addresses}, regs.image)
        dacs = sorted(a for a, t in regs.types.items() if t == BoardType.DAC)
        self._write_dac = self.bp.writer({a: regs.rec_out[a] for a in dacs}, regs.image)
        if owner:
            for a, (_js, axes) in self.enc.items():
                enc = self.modules[a]
                assert isinstance(enc, EncoderDriver)
                for k in axes.tolist():
                    enc.set_latch_mode(k, LATCH_HOME_EDGES)
                enc.flush()
            self.freeze()
        self.read_feedback()

    def close(self) -> None:
        # the batch reader and writer hold views of the backplane's mapping
        self._read = self._write_dac = None
        self.bp.close()

    # -- feedback --

    def read_raw(self) -> dict[int, np.ndarray[Any, Any]]:
        return self.bp.read(self.addresses)

    def sample(self) -> None:
        """Read the boards and decode them into robot units, in place: ``q``
        [rad], ``qd`` [rad/s] (tachometer where fitted, else differentiated
        over the boards' sample times), ``tau`` [N m] (torque sensor where
        fitted, else the motor model applied to the DAC output), ``wrench``
        [N, N m] (sensor frame), ``home_levels``, ``brakes``, the latches
        (``latch_count``, ``latch_edge``, ``latch_q``), ``step_now``,
        ``stamp_ns``. The hot path: no allocation."""
        # Boards are sampled one after another; a snapshot that straddles a
        # plant step is taken again once (the figures are then coherent).
        self._read()
        self.stamp_ns[0] = time.monotonic_ns()
        decode = self._decode
        bad = decode()
        if bad < 0:
            self._read()
            self.stamp_ns[0] = time.monotonic_ns()
            self._retry[...] = 0.0
            bad = decode()
            self._retry[...] = 1.0
        if bad:
            j = bad - 1
            jump = self._jump
            delta, limit, n = float(jump["delta"]), float(jump["limit"]), float(jump["steps"])
            raise IOFault(
                f"{self.name} joint {j + 1}: encoder jump of {int(delta)} counts in "
                f"{int(n)} sample(s) (any real motion: at most {limit:.0f})"
            )

    def read_feedback(self) -> Feedback:
        """:meth:`sample`, returned as a :class:`Feedback` of copies."""
        self.sample()
        return Feedback(
            self.q.copy(),
            self.qd.copy(),
            self.tau.copy(),
            self.wrench.copy(),
            self.home_levels.copy(),
            self.brakes.copy(),
            int(self._state["step"]),
            int(self.stamp_ns[0]),
            bool(self._state["coherent"]),
            self.latch_count.astype(np.int64),
            self.latch_edge.copy(),
            self.latch_q.copy(),
        )

    def shift_zero(self, offset_rad: np.ndarray[Any, Any]) -> None:
        """Take ``offset_rad`` out of every joint position from now on.

        The counters are left alone: q_new = q_old - offset, exactly, even
        while the arm moves (a counter preset would race the motion).
        """
        offset = np.asarray(offset_rad, dtype=np.float64)
        self._q_ref -= offset
        self._prev_q -= offset

    # -- commands --

    def send_torques(self, tau_nm: np.ndarray[Any, Any]) -> None:
        """Joint torques [N m], through the motor model to DAC volts (saturated)."""
        tau = np.asarray(tau_nm, dtype=np.float64)
        if tau.shape != (DOF,):
            raise ValueError(f"{self.name}: joint torques must be 7 finite numbers, got {tau}")
        self.tau_cmd[...] = tau
        self.send()

    def send(self) -> None:
        """Send the joint torques staged in ``tau_cmd`` [N m] (the hot path:
        write them there, then call this)."""
        bad = kernels.KERNELS.driver_dac(self._dac_plan) if self.kernels else self._dac_numpy()
        if bad:
            raise ValueError(
                f"{self.name}: joint torques must be 7 finite numbers, got {self.tau_cmd}"
            )
        # a new watchdog value on every write (never 0, which disables it)
        self._dac_watchdog[...] = (time.monotonic_ns() >> 10) & 0xFFFFFFFF or 1
        self._write_dac()

    def _dac_numpy(self) -> int:
        """The arithmetic of the ``driver_dac`` kernel."""
        tau = self.tau_cmd
        bad = np.flatnonzero(~np.isfinite(tau))
        if bad.size:
            return int(bad[0]) + 1
        # (as the kernel computes: bit for bit)
        x = tau * self.volts_per_nm * (2048 / R.DAC_FULL_SCALE_V) + self.dac_residual
        code = np.rint(x)
        clipped = np.clip(code, R.DAC_CODE_MIN, R.DAC_CODE_MAX)
        self.dac_residual[...] = np.where(clipped == code, self.dac_carry * (x - code), 0.0)
        for a, (js, ch) in self.dac.items():
            dac = self.modules[a]
            assert isinstance(dac, DacDriver)
            dac.set_codes(ch, clipped[js])
        return 0

    def freeze(self) -> None:
        """Brakes on, then every DAC channel to zero (nothing carried)."""
        self._set_brakes(True)
        self.dac_residual[...] = 0.0
        for a in self.dac:
            dac = self.modules[a]
            assert isinstance(dac, DacDriver)
            dac.zero()
            dac.flush()

    def set_gripper(self, closed: bool) -> None:
        """Close (or open) the flange's gripper: its DIO output (none fitted:
        nothing). A freeze leaves it as it is: an object held stays held."""
        ch = self.hw.gripper
        if ch is None:
            return
        dio = self.modules[ch.address]
        assert isinstance(dio, DioDriver)
        dio.set_bits(np.array([ch.index]), closed)
        dio.flush()

    def release_brakes(self, joints: list[int] | None = None) -> None:
        """Release the brakes of ``joints`` (default: all); the others keep theirs."""
        self._set_brakes(False, joints)

    def engage_brakes(self, joints: list[int] | None = None) -> None:
        self._set_brakes(True, joints)

    def _set_brakes(self, on: bool, joints: list[int] | None = None) -> None:
        # fail-safe brakes: the output bit *releases* its brake; off (the
        # board's power-on state) means engaged
        for a, (js, bits) in self.brake.items():
            pick = np.ones(len(js), dtype=bool) if joints is None else np.isin(js, joints)
            if not pick.any():
                continue
            dio = self.modules[a]
            assert isinstance(dio, DioDriver)
            dio.set_bits(bits[pick], not on)
            dio.flush()

    def preset_encoders(
        self, q_rad: np.ndarray[Any, Any], counts: np.ndarray[Any, Any] | None = None
    ) -> None:
        """Load the counters so that they read ``q_rad`` from now on.

        counts: the raw counter value to load per joint (default: q x scale,
        modulo 2**24); the driver maps that count to ``q_rad``.
        """
        q = np.asarray(q_rad, dtype=np.float64)
        values = (
            np.mod(np.rint(q * self.counts_per_rad).astype(np.int64), ENC_MODULO)
            if counts is None
            else np.asarray(counts, dtype=np.int64) % ENC_MODULO
        )
        reqs: dict[int, list[tuple[int, int]]] = {}
        for a, (js, axes) in self.enc.items():
            enc = self.modules[a]
            assert isinstance(enc, EncoderDriver)
            for j, k in zip(js.tolist(), axes.tolist(), strict=True):
                reqs.setdefault(a, []).append((k, enc.preset(k, int(values[j]))))
            enc.flush()
        deadline = time.monotonic() + max(0.2, 10 * min(self.bp.timeout_s, 1.0))
        while True:
            recs = self.bp.read(list(reqs))
            if all(
                EncoderDriver.preset_done(recs[a], k, r) for a, lst in reqs.items() for k, r in lst
            ):
                break
            if time.monotonic() > deadline:
                raise IOFault(f"{self.name}: encoder preset not acknowledged in time")
            time.sleep(0.0005)  # (the plant answers: leave it the CPU)
        self._raw[...] = values
        self._acc[:] = 0
        self._q_ref[...] = q
        self._state["have_ref"] = 1  # a reference
        self._state["prev_step"] = -1  # no previous sample

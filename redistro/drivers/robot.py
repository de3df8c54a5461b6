"""The robot-level driver: robot units in and out, whatever the boards.

Built from a robot's hardware configs (I/O interface and sensor/actuator) over
a backplane. ``read_feedback`` gives q [rad], qd [rad/s] (tachometer where
fitted, else differentiated over the boards' sample times), joint torque
[N m] (torque sensor where fitted, else the motor model applied to the DAC
output), wrist wrench [N, N m] in the sensor frame, home switch levels.
``send_torques`` converts joint torques to DAC volts through the motor model;
``freeze`` engages every brake and zeroes every DAC channel.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from redistro.config.hardware import RobotHardware, by_board
from redistro.drivers.io.adc import AdcDriver
from redistro.drivers.io.backplane import Backplane
from redistro.drivers.io.dac import DacDriver
from redistro.drivers.io.dio import DioDriver
from redistro.drivers.io.encoder import EncoderDriver
from redistro.drivers.io.force import ForceDriver
from redistro.drivers.io.module import ModuleDriver
from redistro.drivers.io.registers import BOARD_NAMES, ENC_MODULO, LATCH_HOME_EDGES
from redistro.errors import ConfigError, IOFault

DOF = 7
DRIVERS: dict[str, type[ModuleDriver]] = {
    "encoder": EncoderDriver,
    "dac": DacDriver,
    "adc": AdcDriver,
    "dio": DioDriver,
    "force": ForceDriver,
}


_HALF = ENC_MODULO // 2
_MASK = ENC_MODULO - 1


def _wrap(delta: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Signed changes between 24-bit counter readings (|change| < 2**23), per element."""
    out: np.ndarray[Any, Any] = ((delta + _HALF) & _MASK) - _HALF
    return out


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
    def __init__(self, hw: RobotHardware, backplane: Backplane, physics_hz: float) -> None:
        self.hw = hw
        self.name = hw.name
        self.bp = backplane
        self.physics_hz = physics_hz
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
        self.modules: dict[int, ModuleDriver] = {
            b.address: DRIVERS[b.type](backplane, b.address) for b in hw.io.boards.values()
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
        # encoder unwrapping: q = q_ref + (accumulated counts since the reference) / scale
        self._raw = np.zeros(DOF, dtype=np.int64)
        self._acc = np.zeros(DOF, dtype=np.int64)
        self._q_ref = np.zeros(DOF)
        self._have_ref = False
        self._prev: tuple[int, np.ndarray] | None = None
        # speed above which a counter change is a glitch (0: not checked)
        self.jump_limit_rad_s = 0.0
        self._qd = np.zeros(DOF)

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
        self.bp.close()

    # -- feedback --

    def read_raw(self) -> dict[int, np.ndarray[Any, Any]]:
        return self.bp.read(self.addresses)

    def read_feedback(self) -> Feedback:
        # Boards are sampled one after another; a snapshot that straddles a
        # plant step is taken again once (the figures are then coherent).
        for _attempt in range(2):
            recs = self.read_raw()
            steps = [int(recs[a]["step"]) for a in self.enc]
            if min(steps) == max(steps):
                break
        now = time.monotonic_ns()
        raw = np.zeros(DOF, dtype=np.int64)
        latch_raw = np.zeros(DOF, dtype=np.int64)
        latch_count = np.zeros(DOF, dtype=np.int64)
        latch_edge = np.zeros(DOF, dtype=np.uint8)
        step = min(steps)
        for a, (js, axes) in self.enc.items():
            rec = recs[a]
            raw[js] = rec["counter"][axes]
            latch_raw[js] = rec["latch"][axes]
            latch_count[js] = rec["latch_count"][axes]
            latch_edge[js] = rec["latch_edge"][axes]
        if not self._have_ref:
            signed = np.where(raw >= ENC_MODULO // 2, raw - ENC_MODULO, raw)
            self._q_ref = signed / self.counts_per_rad
            self._acc[:] = 0
            self._have_ref = True
        else:
            delta = _wrap(raw - self._raw)
            if self.jump_limit_rad_s > 0 and self._prev is not None:
                self._check_jump(delta, step - self._prev[0])
            self._acc += delta
        self._raw = raw
        q = self._q_ref + self._acc / self.counts_per_rad
        # a latched count is within half the counter's range of the present one
        back = _wrap(latch_raw - raw)
        latch_q = q + back / self.counts_per_rad
        if self.has_tach:
            qd = np.zeros(DOF)
            for a, (js, ch) in self.tach.items():
                qd[js] = AdcDriver.volts(recs[a], ch) / self.tach_v[js]
        else:
            qd = self._qd
            if self._prev is not None and step > self._prev[0]:
                dt = (step - self._prev[0]) / self.physics_hz
                qd = (q - self._prev[1]) / dt
            self._qd = qd
        self._prev = (step, q)
        if self.has_torque:
            tau = np.zeros(DOF)
            for a, (js, ch) in self.torque.items():
                tau[js] = AdcDriver.volts(recs[a], ch) / self.torque_v[js]
        else:
            tau = np.zeros(DOF)
            for a, (js, ch) in self.dac.items():
                tau[js] = DacDriver.readback_volts(recs[a], ch) * self.nm_per_volt[js]
        home = np.zeros(DOF, dtype=bool)
        for a, (js, bits) in self.home.items():
            home[js] = DioDriver.bits(recs[a], bits)
        brakes = np.ones(DOF, dtype=bool)
        for a, (js, bits) in self.brake.items():
            brakes[js] = ~DioDriver.output_bits(recs[a], bits)
        wrench = np.zeros(6)
        if self.hw.wrist is not None:
            wrench = ForceDriver.wrench(recs[self.hw.wrist.address])
        return Feedback(
            q,
            qd,
            tau,
            wrench,
            home,
            brakes,
            step,
            now,
            min(steps) == max(steps),
            latch_count,
            latch_edge,
            latch_q,
        )

    def _check_jump(self, delta: np.ndarray[Any, Any], steps: int) -> None:
        """A counter change no motion could make in ``steps`` samples is a glitch."""
        steps = max(1, steps)
        limit = np.broadcast_to(
            self.jump_limit_rad_s * self.counts_per_rad * steps / self.physics_hz + 2, delta.shape
        )
        bad = np.flatnonzero(np.abs(delta) > limit)
        if bad.size:
            j = int(bad[0])
            raise IOFault(
                f"{self.name} joint {j + 1}: encoder jump of {int(delta[j])} counts in "
                f"{steps} sample(s) (any real motion: at most {float(limit[j]):.0f})"
            )

    def shift_zero(self, offset_rad: np.ndarray[Any, Any]) -> None:
        """Take ``offset_rad`` out of every joint position from now on.

        The counters are left alone: q_new = q_old - offset, exactly, even
        while the arm moves (a counter preset would race the motion).
        """
        self._q_ref = self._q_ref - np.asarray(offset_rad, dtype=np.float64)
        if self._prev is not None:
            self._prev = (self._prev[0], self._prev[1] - offset_rad)

    # -- commands --

    def send_torques(self, tau_nm: np.ndarray[Any, Any]) -> None:
        """Joint torques [N m], through the motor model to DAC volts (saturated)."""
        tau = np.asarray(tau_nm, dtype=np.float64)
        if tau.shape != (DOF,) or not np.all(np.isfinite(tau)):
            raise ValueError(f"{self.name}: joint torques must be 7 finite numbers, got {tau}")
        volts = tau / self.nm_per_volt
        for a, (js, ch) in self.dac.items():
            dac = self.modules[a]
            assert isinstance(dac, DacDriver)
            dac.set_volts(ch, volts[js])
            dac.flush()

    def freeze(self) -> None:
        """Brakes on, then every DAC channel to zero."""
        self._set_brakes(True)
        for a in self.dac:
            dac = self.modules[a]
            assert isinstance(dac, DacDriver)
            dac.zero()
            dac.flush()

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
        deadline = time.monotonic() + max(0.2, 10 * self.bp.timeout_s)
        while True:
            recs = self.bp.read(list(reqs))
            if all(
                EncoderDriver.preset_done(recs[a], k, r) for a, lst in reqs.items() for k, r in lst
            ):
                break
            if time.monotonic() > deadline:
                raise IOFault(f"{self.name}: encoder preset not acknowledged in time")
        self._raw = values.copy()
        self._acc[:] = 0
        self._q_ref = q.copy()
        self._have_ref = True
        self._prev = None

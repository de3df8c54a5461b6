"""Models of the devices between the boards and the joints (pure numpy).

Per robot, vectorized over its 7 joints. Units in names; angles are joint
side unless named ``motor``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from redistro.config.hardware import SensorsConfig
from redistro.drivers.io.registers import ENC_MODULO

F64 = np.ndarray[Any, np.dtype[np.float64]]


class Motors:
    """DAC volts -> amplifier current (saturated) -> motor torque -> joint torque."""

    def __init__(self, s: SensorsConfig) -> None:
        self.amps_per_volt = np.asarray(s.amps_per_volt, dtype=np.float64)
        self.max_current_a = np.asarray(s.max_current_a, dtype=np.float64)
        self.kt = np.asarray(s.torque_constant_nm_a, dtype=np.float64)
        self.gear = np.asarray(s.gear_ratio, dtype=np.float64)

    def joint_torque_nm(self, volts: F64, enabled: np.ndarray[Any, Any] | bool = True) -> F64:
        current = np.clip(volts * self.amps_per_volt, -self.max_current_a, self.max_current_a)
        return np.where(enabled, current * self.kt * self.gear, 0.0)


class Encoders:
    """Quadrature counters on the motor shafts: counts = motor angle x counts/rev,
    24-bit, wrapping. The counter's zero is wherever it was at power-on or at
    the last preset."""

    def __init__(self, s: SensorsConfig, q0_rad: F64, disturbance_rad: F64) -> None:
        self.counts_per_rad = (
            np.asarray(s.counts_per_rev, dtype=np.float64) * np.asarray(s.gear_ratio) / (2 * np.pi)
        )
        # At power-on the counters read as if the joints stood at q0 + disturbance
        # (the arm was moved while powered off): offset such that counter(q0) does.
        self.offset = np.rint(np.asarray(disturbance_rad) * self.counts_per_rad).astype(np.int64)

    def counts(self, q_rad: F64) -> np.ndarray[Any, np.dtype[np.int64]]:
        raw = np.floor(q_rad * self.counts_per_rad).astype(np.int64) + self.offset
        out: np.ndarray[Any, np.dtype[np.int64]] = np.mod(raw, ENC_MODULO)
        return out

    def preset(self, axis: int, q_rad: float, value: int) -> None:
        """Load ``value`` into the counter of ``axis`` now (the joint at ``q_rad``)."""
        here = int(np.floor(q_rad * self.counts_per_rad[axis]))
        self.offset[axis] = value - here


class HomeSwitches:
    """Hall-effect switches: on inside a window around the zero mark, with
    hysteresis (turns on a little inside the edges, off a little outside)."""

    def __init__(self, s: SensorsConfig) -> None:
        self.center = np.asarray(s.home_angle_rad, dtype=np.float64)
        self.half = np.asarray(s.home_window_rad, dtype=np.float64) / 2
        self.hyst = np.asarray(s.home_hysteresis_rad, dtype=np.float64) / 2
        self.state = np.zeros(self.center.shape, dtype=bool)

    def update(self, q_rad: F64) -> np.ndarray[Any, np.dtype[np.bool_]]:
        d = np.abs(q_rad - self.center)
        turn_on = d < self.half - self.hyst
        turn_off = d > self.half + self.hyst
        self.state = np.where(self.state, ~turn_off, turn_on)
        return self.state


class WristSensor:
    """6-axis strain-gauge sensor: gauge counts = C^-1 (wrench + bias + noise)."""

    def __init__(self, calibration: F64, bias: F64, noise_n: float, noise_nm: float, seed: int):
        self.calibration = np.asarray(calibration, dtype=np.float64)
        self.inverse = np.linalg.inv(self.calibration)
        self.bias = np.asarray(bias, dtype=np.float64)
        self.sigma = np.array([noise_n] * 3 + [noise_nm] * 3)
        self.rng = np.random.default_rng(seed)

    def gauges(self, wrench: F64) -> np.ndarray[Any, np.dtype[np.int32]]:
        w = wrench + self.bias + self.rng.normal(0.0, 1.0, 6) * self.sigma
        counts = np.rint(self.inverse @ w)
        out: np.ndarray[Any, np.dtype[np.int32]] = np.clip(
            counts, -(1 << 23), (1 << 23) - 1
        ).astype(np.int32)
        return out

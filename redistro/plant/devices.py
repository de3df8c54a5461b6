"""Models of the devices between the boards and the joints (pure numpy).

Vectorized over joints: built from one robot's sensor/actuator config, or
from several robots' stacked (the chassis models every joint of every robot
in one array, so each step is one operation per quantity, not per robot or
per joint). Units in names; angles are joint side unless named ``motor``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from redistro.config.hardware import SensorsConfig
from redistro.drivers.io.registers import ENC_MODULO
from redistro.plant import chassis_layout

F64 = np.ndarray[Any, np.dtype[np.float64]]


def _stack(sensors: SensorsConfig | Sequence[SensorsConfig], name: str) -> F64:
    """The per-joint list ``name`` of one config, or of several end to end."""
    configs = [sensors] if isinstance(sensors, SensorsConfig) else list(sensors)
    return np.concatenate([np.asarray(getattr(s, name), dtype=np.float64) for s in configs])


class Motors:
    """DAC volts -> amplifier current (saturated) -> motor torque -> joint torque."""

    def __init__(self, s: SensorsConfig | Sequence[SensorsConfig]) -> None:
        self.amps_per_volt = _stack(s, "amps_per_volt")
        self.max_current_a = _stack(s, "max_current_a")
        self.kt = _stack(s, "torque_constant_nm_a")
        self.gear = _stack(s, "gear_ratio")
        self.nm_per_amp = self.kt * self.gear
        self.min_current_a = -self.max_current_a

    def joint_torque_nm(self, volts: F64, enabled: np.ndarray[Any, Any] | bool = True) -> F64:
        current = np.clip(volts * self.amps_per_volt, -self.max_current_a, self.max_current_a)
        return np.where(enabled, current * self.nm_per_amp, 0.0)


class Encoders:
    """Quadrature counters on the motor shafts: counts = motor angle x counts/rev,
    24-bit, wrapping. The counter's zero is wherever it was at power-on or at
    the last preset."""

    def __init__(
        self, s: SensorsConfig | Sequence[SensorsConfig], q0_rad: F64, disturbance_rad: F64
    ) -> None:
        self.counts_per_rad = _stack(s, "counts_per_rev") * _stack(s, "gear_ratio") / (2 * np.pi)
        # At power-on the counters read as if the joints stood at q0 + disturbance
        # (the arm was moved while powered off): offset such that counter(q0) does.
        self.offset = np.rint(np.asarray(disturbance_rad) * self.counts_per_rad).astype(np.int64)
        self._f = np.zeros(self.counts_per_rad.shape)
        self._raw = np.zeros(self.counts_per_rad.shape, dtype=np.int64)

    def counts(self, q_rad: F64) -> np.ndarray[Any, np.dtype[np.int64]]:
        """The counters' readings at ``q_rad`` (a buffer reused by the next call)."""
        f, raw = self._f, self._raw
        np.multiply(q_rad, self.counts_per_rad, out=f)
        np.floor(f, out=f)
        np.copyto(raw, f, casting="unsafe")
        raw += self.offset
        raw &= ENC_MODULO - 1  # modulo 2**24, negative counts included (two's complement)
        return raw

    def preset(self, axis: int, q_rad: float, value: int) -> None:
        """Load ``value`` into the counter of ``axis`` now (the joint at ``q_rad``)."""
        here = int(np.floor(q_rad * self.counts_per_rad[axis]))
        self.offset[axis] = value - here


class HomeSwitches:
    """Hall-effect switches: on inside a window around the zero mark, with
    hysteresis (turns on a little inside the edges, off a little outside)."""

    def __init__(self, s: SensorsConfig | Sequence[SensorsConfig]) -> None:
        self.center = _stack(s, "home_angle_rad")
        half = _stack(s, "home_window_rad") / 2
        hyst = _stack(s, "home_hysteresis_rad") / 2
        self.on_within = half - hyst
        self.off_beyond = half + hyst
        self.state = np.zeros(self.center.shape, dtype=bool)
        self._d = np.zeros(self.center.shape)
        self._on = np.zeros(self.center.shape, dtype=bool)
        self._off = np.zeros(self.center.shape, dtype=bool)

    def update(self, q_rad: F64) -> np.ndarray[Any, np.dtype[np.bool_]]:
        """The switches' levels at ``q_rad`` (``self.state``, updated in place)."""
        d = self._d
        np.subtract(q_rad, self.center, out=d)
        np.abs(d, out=d)
        np.less(d, self.on_within, out=self._on)
        np.less_equal(d, self.off_beyond, out=self._off)  # True: not turned off
        # on stays on unless beyond the window; off turns on well inside it
        # (inside implies not beyond: on = (on and not beyond) or inside)
        np.logical_and(self.state, self._off, out=self.state)
        np.logical_or(self.state, self._on, out=self.state)
        return self.state


class WristSensors:
    """6-axis strain-gauge sensors, one row each: gauge counts = C^-1 (wrench +
    bias + noise). ``calibration`` (k, 6, 6), ``bias`` (k, 6).

    The noise is drawn ahead in blocks (one draw of many samples costs about
    what one draw of six does), already in gauge counts: ``noise`` (block, k,
    6) and the next row to use, ``noise_at["row"]`` (NOISE_AT,
    plant/chassis_layout.py; both filled in place: a compiled kernel may
    hold them)."""

    NOISE_BLOCK = 1024

    def __init__(
        self, calibration: F64, bias: F64, noise_n: float, noise_nm: float, seed: int
    ) -> None:
        self.calibration = np.asarray(calibration, dtype=np.float64).reshape(-1, 6, 6)
        self.k = self.calibration.shape[0]
        self.inverse = np.ascontiguousarray(np.linalg.inv(self.calibration))
        self.bias = np.asarray(bias, dtype=np.float64).reshape(self.k, 6)
        self.sigma = np.array([noise_n] * 3 + [noise_nm] * 3)
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.noise = np.zeros((self.NOISE_BLOCK, self.k, 6))
        self.noise_at = np.zeros((), chassis_layout.NOISE_AT)
        self._row = self.noise_at["row"]
        self.refill()
        self._counts = np.zeros((self.k, 6, 1))

    def reseed(self, offset: int) -> None:
        """The noise drawn afresh from ``seed + offset`` (a lockstep group's
        first tick: the same noise whatever the plant served before it)."""
        self.rng = np.random.default_rng(self.seed + offset)
        self.refill()

    def refill(self) -> None:
        """The next block of noise (in gauge counts); start at its first row."""
        w = self.rng.normal(0.0, 1.0, (self.NOISE_BLOCK, self.k, 6)) * self.sigma + self.bias
        self.noise[...] = np.matmul(self.inverse, w[..., None])[..., 0]
        self._row[...] = 0

    def _draw(self) -> F64:
        if self._row >= self.NOISE_BLOCK:
            self.refill()
        row: F64 = self.noise[int(self._row)]
        self._row += 1
        return row

    def gauges_into(self, wrenches: F64, out: np.ndarray[Any, Any]) -> None:
        """The gauge counts of ``wrenches`` (k, 6; sensor frames) into ``out``
        (k, 6; int32 registers)."""
        c = self._counts
        np.matmul(self.inverse, wrenches[..., None], out=c)
        c[..., 0] += self._draw()
        np.rint(c, out=c)
        np.minimum(c, (1 << 23) - 1, out=c)
        np.maximum(c, -(1 << 23), out=c)
        out[...] = c[..., 0]


class WristSensor(WristSensors):
    """One wrist sensor: ``calibration`` (6, 6), ``bias`` (6,)."""

    def gauges(self, wrench: F64) -> np.ndarray[Any, np.dtype[np.int32]]:
        out = np.zeros((1, 6), dtype=np.int32)
        self.gauges_into(np.asarray(wrench, dtype=np.float64).reshape(1, 6), out)
        one: np.ndarray[Any, np.dtype[np.int32]] = out[0]
        return one

"""Fifth-order polynomial trajectories (zero velocity and acceleration at both ends).

For a move from ``q0`` to ``q1`` in ``T`` seconds with s = t / T::

    q(t)   = q0 + (q1 - q0) (10 s^3 - 15 s^4 + 6 s^5)
    qd(t)  = (q1 - q0) / T   (30 s^2 - 60 s^3 + 30 s^4)
    qdd(t) = (q1 - q0) / T^2 (60 s - 180 s^2 + 120 s^3)

Peak speed is 15/8 (q1 - q0) / T at s = 1/2. Before t = 0 the trajectory
rests at ``q0``, after ``T`` at ``q1``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from redistro.control import joint_layout

F64 = np.ndarray[Any, np.dtype[np.float64]]
PEAK_SPEED = 15.0 / 8.0  # peak |qd| x T / |q1 - q0|


@dataclass(frozen=True)
class Quintic:
    """q0, q1: start and goal [rad], shape (n,); duration_s > 0."""

    q0: F64
    q1: F64
    duration_s: float

    def __post_init__(self) -> None:
        if not self.duration_s > 0:
            raise ValueError(f"duration_s must be > 0, got {self.duration_s}")

    def sample(self, t_s: float) -> tuple[F64, F64, F64]:
        """(q [rad], qd [rad/s], qdd [rad/s^2]) at ``t_s`` seconds from the start."""
        return quintic(self.q0, self.q1, self.duration_s, t_s)

    def peak_speed(self) -> F64:
        return np.abs(self.q1 - self.q0) * PEAK_SPEED / self.duration_s


def quintic(q0: F64, q1: F64, duration_s: float, t_s: float) -> tuple[F64, F64, F64]:
    """The quintic from q0 to q1 over duration_s, sampled at t_s (clamped to the ends)."""
    T = float(duration_s)
    s = min(max(t_s / T, 0.0), 1.0)
    d = np.asarray(q1, dtype=np.float64) - np.asarray(q0, dtype=np.float64)
    s2 = s * s
    s3 = s2 * s
    pos = 10 * s3 - 15 * s3 * s + 6 * s3 * s2
    vel = (30 * s2 - 60 * s3 + 30 * s2 * s2) / T
    acc = (60 * s - 180 * s2 + 120 * s3) / (T * T)
    return q0 + d * pos, d * vel, d * acc


def quintic_into(
    q0: F64,
    d: F64,
    duration_s: float,
    t_s: float,
    q: F64,
    qd: F64,
    qdd: F64,
) -> None:
    """:func:`quintic` into preallocated arrays (``d`` = q1 - q0): six
    in-place operations, no temporaries (a control cycle's hot path)."""
    T = float(duration_s)
    s = min(max(t_s / T, 0.0), 1.0)
    s2 = s * s
    s3 = s2 * s
    np.multiply(d, 10 * s3 - 15 * s3 * s + 6 * s3 * s2, out=q)
    q += q0
    np.multiply(d, (30 * s2 - 60 * s3 + 30 * s2 * s2) / T, out=qd)
    np.multiply(d, (60 * s - 180 * s2 + 120 * s3) / (T * T), out=qdd)


class QuinticRef:
    """A quintic's reference written into bound arrays (views into a record),
    one compiled kernel call per cycle; :func:`quintic_into` is its
    reference. ``start(q0, q1, T)`` a new move; ``at(t)`` the reference."""

    def __init__(
        self, q: F64, qd: F64, qdd: F64, n: int = 7, *, use_kernel: bool | None = None
    ) -> None:
        from redistro import kernels

        self.q, self.qd, self.qdd = q, qd, qdd
        self.q0 = np.zeros(n)
        self.d = np.zeros(n)
        self.time = np.zeros((), joint_layout.QUINTIC_TIME)
        self.duration, self.t = self.time["duration"], self.time["t"]
        self.duration[...] = 1.0
        self.use_kernel = kernels.AVAILABLE if use_kernel is None else use_kernel
        if self.use_kernel:
            self._plan = kernels.plan(
                "quintic", q0=self.q0, d=self.d, q=q, qd=qd, qdd=qdd, time=self.time
            )
            self._run = kernels.KERNELS.quintic

    def start(self, q0: F64, q1: F64, duration_s: float) -> None:
        if not duration_s > 0:
            raise ValueError(f"duration_s must be > 0, got {duration_s}")
        self.q0[...] = q0
        np.subtract(q1, q0, out=self.d)
        self.duration[...] = duration_s

    def at(self, t_s: float) -> None:
        if self.use_kernel:
            self.t[...] = t_s
            self._run(self._plan)
        else:
            quintic_into(self.q0, self.d, float(self.duration), t_s, self.q, self.qd, self.qdd)

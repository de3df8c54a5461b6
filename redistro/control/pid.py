"""Joint PID with gravity compensation, as a pure update function.

    tau = g(q) + Kp (q_ref - q) + Kd (qd_ref - qd) + Ki * integral(q_ref - q)

The integral is clamped per joint (``i_max_nm`` bounds Ki x integral), and it
only integrates on joints that are on. Joints that are off get no torque at
all (their brakes hold them). The state is a small dataclass the caller keeps.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from redistro.control import joint_layout

F64 = np.ndarray[Any, np.dtype[np.float64]]


@dataclass(frozen=True)
class PidGains:
    """Per joint, shape (n,): kp [N m/rad], ki [N m/(rad s)], kd [N m s/rad], i_max_nm [N m]."""

    kp: F64
    ki: F64
    kd: F64
    i_max_nm: F64
    i_lim: F64 = field(init=False, repr=False)  # bound on the integral itself [rad s]

    def __post_init__(self) -> None:
        ki = np.asarray(self.ki, dtype=np.float64)
        lim = np.zeros_like(ki)
        np.divide(self.i_max_nm, ki, out=lim, where=ki > 0)
        object.__setattr__(self, "i_lim", lim)


@dataclass
class PidState:
    integral: F64 = field(default_factory=lambda: np.zeros(7))  # [rad s]

    def reset(self) -> None:
        self.integral[:] = 0.0


def pid_update(
    gains: PidGains,
    state: PidState,
    q: F64,
    qd: F64,
    q_ref: F64,
    qd_ref: F64,
    gravity_nm: F64,
    on: np.ndarray[Any, Any],
    dt_s: float,
) -> F64:
    """Joint torques [N m] for one cycle; updates ``state.integral`` in place.

    q, qd: measured positions [rad] and speeds [rad/s]; q_ref, qd_ref: the
    reference; gravity_nm: g(q) [N m]; on: bool mask of joints under control;
    dt_s: time since the previous update [s].
    """
    e = q_ref - q
    integral = state.integral + e * dt_s
    np.minimum(integral, gains.i_lim, out=integral)
    np.maximum(integral, -gains.i_lim, out=integral)
    mask = on.astype(np.float64)
    integral *= mask
    state.integral = integral
    tau: F64 = gravity_nm + gains.kp * e + gains.kd * (qd_ref - qd) + gains.ki * integral
    tau *= mask
    return tau


class PidWork:
    """Scratch buffers of :func:`pid_update_into` (made once per controller)."""

    def __init__(self, n: int = 7) -> None:
        self.e = np.zeros(n)
        self.d = np.zeros(n)
        self.mask = np.zeros(n)


def pid_update_into(
    gains: PidGains,
    state: PidState,
    work: PidWork,
    q: F64,
    qd: F64,
    q_ref: F64,
    qd_ref: F64,
    gravity_nm: F64,
    on: np.ndarray[Any, Any],
    dt_s: float,
    tau: F64,
) -> None:
    """:func:`pid_update` into ``tau``, in place and without temporaries (the
    same arithmetic; the hot path of a control cycle)."""
    e, d, mask, integral = work.e, work.d, work.mask, state.integral
    np.subtract(q_ref, q, out=e)
    np.multiply(e, dt_s, out=d)
    integral += d
    np.minimum(integral, gains.i_lim, out=integral)
    np.maximum(integral, -gains.i_lim, out=integral)
    np.copyto(mask, on)
    integral *= mask
    np.multiply(gains.kp, e, out=tau)
    np.subtract(qd_ref, qd, out=d)
    d *= gains.kd
    tau += d
    np.multiply(gains.ki, integral, out=d)
    tau += d
    tau += gravity_nm
    tau *= mask


class PidLoop:
    """A joint PID bound once to its arrays (views into the records a worker
    reads and writes), run each cycle in one compiled kernel call; the numpy
    :func:`pid_update_into` is its reference. q, qd, q_ref, qd_ref, g: inputs
    (float64, aligned); on: joints under control (bool or uint8); tau: output."""

    def __init__(
        self,
        gains: PidGains,
        state: PidState,
        q: F64,
        qd: F64,
        q_ref: F64,
        qd_ref: F64,
        g: F64,
        on: np.ndarray[Any, Any],
        tau: F64,
        *,
        use_kernel: bool | None = None,
    ) -> None:
        from redistro import kernels

        self.gains, self.state = gains, state
        self.args = (q, qd, q_ref, qd_ref, g, on)
        self.tau = tau
        self._dt = np.zeros((), joint_layout.PID_DT)
        self.dt = self._dt["dt"]  # the cycle, set per call
        self.work = PidWork(len(tau))
        self.use_kernel = kernels.AVAILABLE if use_kernel is None else use_kernel
        if self.use_kernel:
            table = np.zeros((), joint_layout.PID_GAINS)
            table["kp"], table["ki"], table["kd"], table["i_max"] = (
                gains.kp,
                gains.ki,
                gains.kd,
                gains.i_lim,
            )
            self._plan = kernels.plan(
                "joint_pid",
                q=q,
                qd=qd,
                q_ref=q_ref,
                qd_ref=qd_ref,
                g=g,
                on=on.view(np.uint8),
                tau=tau,
                integral=state.integral,
                gains=table,
                dt=self._dt,
            )
            self._run = kernels.KERNELS.joint_pid

    def update(self, dt_s: float) -> None:
        """One cycle: ``tau`` from the bound arrays' present values."""
        if self.use_kernel:
            self.dt[...] = dt_s
            self._run(self._plan)
        else:
            q, qd, q_ref, qd_ref, g, on = self.args
            pid_update_into(
                self.gains, self.state, self.work, q, qd, q_ref, qd_ref, g, on, dt_s, self.tau
            )

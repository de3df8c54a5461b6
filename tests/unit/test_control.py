"""Pure control functions: trajectories and the joint PID."""

from __future__ import annotations

import numpy as np
import pytest

from redistro.control.pid import PidGains, PidState, PidWork, pid_update, pid_update_into
from redistro.control.trajectory import PEAK_SPEED, Quintic, quintic, quintic_into


def test_quintic_rests_at_both_ends() -> None:
    q0, q1 = np.array([0.0, 1.0]), np.array([0.5, -1.0])
    for t, want in ((0.0, q0), (2.0, q1), (-1.0, q0), (5.0, q1)):
        q, qd, qdd = quintic(q0, q1, 2.0, t)
        assert np.allclose(q, want)
        assert np.allclose(qd, 0.0) and np.allclose(qdd, 0.0)


def test_quintic_peak_speed_and_midpoint() -> None:
    traj = Quintic(np.zeros(1), np.array([0.2]), 10.0)
    q, qd, qdd = traj.sample(5.0)
    assert q[0] == pytest.approx(0.1)
    assert qd[0] == pytest.approx(0.2 * PEAK_SPEED / 10.0)
    assert qdd[0] == pytest.approx(0.0, abs=1e-12)
    assert traj.peak_speed()[0] == pytest.approx(qd[0])


def test_quintic_velocity_is_the_derivative() -> None:
    q0, q1, T = np.array([0.3]), np.array([-0.4]), 3.0
    for t in (0.4, 1.1, 2.5):
        h = 1e-6
        qa, _, _ = quintic(q0, q1, T, t - h)
        qb, _, _ = quintic(q0, q1, T, t + h)
        _, qd_mid, _ = quintic(q0, q1, T, t)
        assert (qb - qa)[0] / (2 * h) == pytest.approx(qd_mid[0], rel=1e-5)


def test_quintic_rejects_a_zero_duration() -> None:
    with pytest.raises(ValueError, match="duration_s"):
        Quintic(np.zeros(1), np.ones(1), 0.0)


def _gains(ki: float = 0.0) -> PidGains:
    n = 3
    return PidGains(np.full(n, 10.0), np.full(n, ki), np.full(n, 2.0), np.full(n, 1.0))


def test_pid_on_target_outputs_gravity_only() -> None:
    g = np.array([1.0, -2.0, 3.0])
    q = np.array([0.1, 0.2, 0.3])
    tau = pid_update(_gains(), PidState(np.zeros(3)), q, np.zeros(3), q, np.zeros(3), g,
                     np.ones(3, bool), 0.005)  # fmt: skip
    assert np.allclose(tau, g)


def test_pid_terms_and_joints_off() -> None:
    tau = pid_update(
        _gains(),
        PidState(np.zeros(3)),
        np.zeros(3),
        np.array([0.0, 1.0, 0.0]),
        np.array([0.1, 0.0, 0.5]),
        np.zeros(3),
        np.zeros(3),
        np.array([True, True, False]),
        0.005,
    )
    assert tau == pytest.approx([1.0, -2.0, 0.0])  # kp x 0.1; kd x -1; off: nothing


def test_pid_integral_is_clamped_and_reset_when_off() -> None:
    state = PidState(np.zeros(3))
    gains = _gains(ki=5.0)  # i_max 1 N m -> integral bound 0.2 rad s
    on = np.ones(3, bool)
    for _ in range(1000):
        tau = pid_update(gains, state, np.zeros(3), np.zeros(3), np.ones(3), np.zeros(3),
                         np.zeros(3), on, 0.01)  # fmt: skip
    assert np.allclose(state.integral, 0.2)
    assert np.allclose(tau, 10.0 + 1.0)
    pid_update(gains, state, np.zeros(3), np.zeros(3), np.ones(3), np.zeros(3), np.zeros(3),
               np.zeros(3, bool), 0.01)  # fmt: skip
    assert np.allclose(state.integral, 0.0)


def test_the_in_place_forms_compute_what_the_plain_ones_do() -> None:
    rng = np.random.default_rng(3)
    q0, q1 = rng.normal(size=7), rng.normal(size=7)
    out = np.zeros((3, 7))
    for t in (-0.1, 0.0, 0.7, 1.3, 2.0, 2.5):
        quintic_into(q0, q1 - q0, 2.0, t, out[0], out[1], out[2])
        assert np.allclose(out, np.array(quintic(q0, q1, 2.0, t)), rtol=1e-12, atol=1e-12)
    g = PidGains(*(np.abs(rng.normal(size=7)) * 10 for _ in range(4)))
    a, b, work, tau = PidState(), PidState(), PidWork(), np.zeros(7)
    on = np.array([1, 1, 0, 1, 1, 1, 0], dtype=bool)
    for _ in range(50):
        args = [rng.normal(size=7) for _ in range(5)]
        ref = pid_update(g, a, *args, on, 0.005)
        pid_update_into(g, b, work, *args, on, 0.005, tau)
        assert np.allclose(tau, ref, rtol=1e-12, atol=1e-12)
        assert np.allclose(a.integral, b.integral, rtol=0, atol=0)

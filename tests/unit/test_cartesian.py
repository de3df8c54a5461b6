"""The Cartesian laws: rotations, pose error, impedance and hybrid force control."""

from __future__ import annotations

import numpy as np
import pytest

from redistro.control.cartesian import (
    ArmNow,
    ForceParams,
    HybridState,
    ImpedanceGains,
    LawParams,
    Reference,
    TaskFrameCommand,
    Tick,
    applied_wrench_task,
    hybrid_update,
    matrix_to_rotvec,
    pose_error,
    rotvec_to_matrix,
    slerp,
    start_state,
)
from redistro.control.dynamics import ArmModel, Kinematics
from redistro.robotmodel import Peg

Q0 = np.array([0.0, 0.5, 0.0, -1.2, 0.0, 1.0, 0.0])


@pytest.fixture(scope="module")
def arm() -> ArmModel:
    return ArmModel(Peg(0.02, 0.1, 0.1), [0.0, -0.45, 0.0])


def _step(
    st: HybridState,
    cmd: TaskFrameCommand,
    kin: Kinematics,
    g: np.ndarray,
    p_ref: np.ndarray,
    wrench: np.ndarray | None = None,
    t_s: float = 0.0,
    fp: ForceParams | None = None,
) -> np.ndarray:
    """One update at rest at Q0, reference orientation = the current one."""
    tau, _ = hybrid_update(
        LawParams(_gains(), fp or ForceParams()),
        st,
        cmd,
        ArmNow(kin, Q0, np.zeros(7), g, np.zeros(6) if wrench is None else wrench),
        Reference(p_ref, kin.R, np.zeros(6), Q0),
        Tick(t_s, 0.005),
    )
    return tau


def _gains() -> ImpedanceGains:
    return ImpedanceGains(
        k=np.array([300.0, 300, 300, 8, 8, 8]),
        d=np.zeros(6),
        ki=np.zeros(6),
        i_max=np.zeros(6),
        k_null=np.zeros(7),
        d_joint=np.zeros(7),
    )


@pytest.mark.parametrize(
    "r", [[0.3, -0.2, 0.1], [0.0, np.pi - 1e-3, 0.0], [1e-10, 0, 0], [0.0, 0.0, -2.5]]
)
def test_rotation_vector_round_trip(r: list[float]) -> None:
    R = rotvec_to_matrix(np.array(r))
    assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(rotvec_to_matrix(matrix_to_rotvec(R)), R, atol=1e-9)


def test_pose_error_points_at_the_reference() -> None:
    R = rotvec_to_matrix(np.array([0.0, np.pi, 0.0]))
    R_ref = rotvec_to_matrix(np.array([0.0, 0.0, 0.1])) @ R
    e = pose_error(np.zeros(3), R, np.array([0.01, 0, 0]), R_ref)
    assert np.allclose(e, [0.01, 0, 0, 0, 0, 0.1])
    assert np.allclose(slerp(R, R_ref, 0.5), rotvec_to_matrix(np.array([0, 0, 0.05])) @ R)


def test_the_tcp_jacobian_matches_finite_differences(arm: ArmModel) -> None:
    kin = arm.kinematics(Q0)
    eps = 1e-6
    for j in range(7):
        dq = np.zeros(7)
        dq[j] = eps
        k2 = arm.kinematics(Q0 + dq)
        assert np.allclose((k2.p - kin.p) / eps, kin.J[:3, j], atol=1e-4)
        w = matrix_to_rotvec(k2.R @ kin.R.T) / eps
        assert np.allclose(w, kin.J[3:, j], atol=1e-4)
    # the peg's tip: 0.1 m from the sensor along the tool axis
    assert np.isclose(np.linalg.norm(kin.p - kin.sensor_p), 0.1)


def test_impedance_on_target_is_gravity_only_and_pulls_toward_the_goal(arm: ArmModel) -> None:
    kin = arm.kinematics(Q0)
    cmd = TaskFrameCommand(np.concatenate([kin.p, matrix_to_rotvec(kin.R)]))
    g = arm.gravity(Q0)
    st = start_state(cmd, kin)
    tau = _step(st, cmd, kin, g, kin.p)
    assert np.allclose(tau, g)
    # a reference 1 cm above: the torque is J^T of an upward force of 3 N
    up = kin.p + np.array([0, 0, 0.01])
    tau = _step(st, cmd, kin, g, up)
    assert np.allclose(tau - g, kin.J[:3].T @ np.array([0, 0, 3.0]), atol=1e-9)


def test_a_force_axis_moves_its_reference_until_contact_then_feeds_the_goal(
    arm: ArmModel,
) -> None:
    kin = arm.kinematics(Q0)
    cmd = TaskFrameCommand(
        np.concatenate([kin.p, matrix_to_rotvec(kin.R)]),
        np.array([0, 0, -20.0, 0, 0, 0]),
        np.array([0, 0, 1.0, 0, 0, 0]),
    )
    fp = ForceParams(k_adm=0.002, v_max=0.01, a_max=0.02, contact_n=3.0, ramp_s=0.1)
    st = start_state(cmd, kin)
    g = arm.gravity(Q0)
    for _ in range(50):  # free space: the reference speeds up at a_max...
        _step(st, cmd, kin, g, kin.p, fp=fp)
    assert np.isclose(st.xi_v[2], -0.02 * 0.25) and np.isclose(st.a_ref[2], -0.02)
    assert np.isclose(st.xi[2], -0.5 * 0.02 * 0.25**2, rtol=0.05)
    for _ in range(150):  # ...to v_max, then goes down at v_max
        _step(st, cmd, kin, g, kin.p, fp=fp)
    assert np.isclose(st.xi_v[2], -0.01) and st.a_ref[2] == 0.0
    assert np.isclose(st.xi[2], -(0.0025 + 0.01 * 0.5), rtol=0.02)
    assert not st.contact and st.ramp == 0.0
    assert np.allclose(st.xi[:2], 0.0)  # position axes do not move
    # contact: the environment pushes up 10 N on the tool (sensor axes)
    ext_world = np.array([0, 0, 10.0, 0, 0, 0])
    ext_sensor = np.concatenate([kin.R.T @ ext_world[:3], np.zeros(3)])
    applied = applied_wrench_task(ext_sensor, kin, np.eye(3))
    assert np.allclose(applied[:3], [0, 0, -10.0])
    for _ in range(30):
        _step(st, cmd, kin, g, kin.p, ext_sensor, 1.0, fp)
    assert st.contact and st.contact_t_s == 1.0 and st.ramp == 1.0


def test_the_inertia_feedforward_gives_the_reference_acceleration(arm: ArmModel) -> None:
    kin = arm.kinematics(Q0)
    inertia = arm.task_inertia(Q0, kin.J)
    lam = inertia.lam
    assert np.allclose(lam, lam.T, atol=1e-9) and np.all(np.linalg.eigvalsh(lam) > 0)
    cmd = TaskFrameCommand(np.concatenate([kin.p, matrix_to_rotvec(kin.R)]))
    g = arm.gravity(Q0)
    a6 = np.array([0.0, 0.3, -0.2, 0.0, 0.0, 0.1])
    tau, _ = hybrid_update(
        LawParams(_gains()),
        start_state(cmd, kin),
        cmd,
        ArmNow(kin, Q0, np.zeros(7), g, np.zeros(6), inertia),
        Reference(kin.p, kin.R, np.zeros(6), Q0, a6),
        Tick(0.0, 0.005),
    )
    # at rest on target: gravity plus J^T Lambda a, and M^-1 of it accelerates the TCP by a
    assert np.allclose(tau - g, kin.J.T @ lam @ a6, atol=1e-9)
    import pinocchio as pin

    upper = pin.crba(arm.model, arm.data, Q0)
    M = np.triu(upper) + np.triu(upper, 1).T
    assert np.allclose(kin.J @ np.linalg.solve(M, tau - g), a6, atol=1e-4)
    # a posture torque through the projector does not accelerate the TCP
    # (away from the home pose, where joints 1, 3, 5 and 7 line up)
    q = np.array([0.3, 0.6, -0.2, -1.1, 0.4, 0.9, 0.2])
    J = arm.kinematics(q).J
    upper = pin.crba(arm.model, arm.data, q)
    M = np.triu(upper) + np.triu(upper, 1).T
    null = arm.task_inertia(q, J).null
    t0 = np.array([1.0, -2.0, 0.5, 3.0, -1.0, 0.2, 0.7])
    assert np.abs(null @ t0).max() > 0.1  # it passes some torque (the null space)...
    assert np.abs(J @ np.linalg.solve(M, t0)).max() > 1.0  # unprojected, it would
    assert np.allclose(J @ np.linalg.solve(M, null @ t0), 0.0, atol=1e-4)  # ...not to the TCP

"""Cartesian impedance and hybrid position/force control, as pure update functions.

A task-frame command in the style of MRROC++ says, per axis of a task frame
(the world's axes, or the tool's axes taken when the command starts), whether
the axis is position controlled (``selection_vector`` 0: the goal pose
``pos_xyz_rot_xyz`` holds) or force controlled (1: the goal wrench
``force_xyz_torque_xyz`` holds, the wrench the tool applies on its
environment). Both schemes end in the same Cartesian impedance law::

    F   = K e + D (v_ref - v) + Ki * integral(e)  +  ramp * S F_goal
    tau = J^T F + g(q) + N (k_null (q_null - q)) - d_joint qd

with ``e`` the pose error of the TCP against its reference (position, and a
rotation vector), ``J`` the TCP Jacobian, ``N`` the null-space projector of
``J^T``. On a force-controlled axis the reference is not the goal pose: it
moves by admittance, ``ref += dt clip(k_adm (F_goal - F), v_max)``, so the
tool approaches in free space at a bounded speed and, in contact, the
spring K pushes until the measured force meets the goal. When contact is
first felt (``contact_n`` along any force axis) the goal wrench is fed
forward, ramped in over ``ramp_s``. Pure impedance control is the same law
with every axis position controlled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from redistro.control.dynamics import Kinematics, TaskInertia

F64 = np.ndarray[Any, np.dtype[np.float64]]


def rotvec_to_matrix(r: F64) -> F64:
    """Rotation matrix of a rotation vector (axis x angle) [rad] (Rodrigues).

    Scalar arithmetic: on 3-vectors it is several times cheaper than numpy's
    per-call overhead, and it runs in every control cycle."""
    x, y, z = float(r[0]), float(r[1]), float(r[2])
    angle = math.sqrt(x * x + y * y + z * z)
    if angle < 1e-12:
        return np.eye(3)
    x, y, z = x / angle, y / angle, z / angle
    s, c = math.sin(angle), math.cos(angle)
    v = 1.0 - c
    return np.array(
        [
            [c + x * x * v, x * y * v - z * s, x * z * v + y * s],
            [y * x * v + z * s, c + y * y * v, y * z * v - x * s],
            [z * x * v - y * s, z * y * v + x * s, c + z * z * v],
        ]
    )


def matrix_to_rotvec(R: F64) -> F64:
    """The rotation vector of a rotation matrix (angle in [0, pi])."""
    (a, b, c_), (d, e, f), (g, h, i) = R.tolist()
    c = max(-1.0, min(1.0, (a + e + i - 1.0) / 2.0))
    angle = math.acos(c)
    wx, wy, wz = h - f, c_ - g, d - b
    if angle < 1e-9:
        return np.array([0.5 * wx, 0.5 * wy, 0.5 * wz])
    if math.pi - angle < 1e-6:
        # near pi: the axis from the symmetric part
        M = (np.asarray(R, dtype=np.float64) + np.eye(3)) / 2.0
        axis = np.sqrt(np.clip(np.diag(M), 0.0, None))
        k = int(np.argmax(axis))
        axis = M[:, k] / max(axis[k], 1e-12)
        axis /= np.linalg.norm(axis)
        near: F64 = axis * angle
        return near
    scale = angle / (2.0 * math.sin(angle))
    return np.array([wx * scale, wy * scale, wz * scale])


def pose_error(p: F64, R: F64, p_ref: F64, R_ref: F64) -> F64:
    """(position error [m], rotation error as a rotation vector [rad]), world axes:
    what would take the pose (p, R) onto (p_ref, R_ref)."""
    return np.concatenate([p_ref - p, matrix_to_rotvec(R_ref @ R.T)])


def slerp(R0: F64, R1: F64, s: float) -> F64:
    """The rotation ``s`` (0..1) of the way from R0 to R1, about one fixed axis."""
    return rotvec_to_matrix(matrix_to_rotvec(R1 @ R0.T) * s) @ R0


@dataclass(frozen=True)
class TaskFrameCommand:
    """A goal in a task frame (MRROC++'s task-frame command).

    pos_xyz_rot_xyz: goal pose of the TCP in the world: position [m] and a
        rotation vector [rad] (world from tool);
    force_xyz_torque_xyz: goal wrench the tool applies [N, N m], task axes;
    selection_vector: per task axis, 1 force controlled, 0 position controlled;
    frame: ``world`` (world axes) or ``tool`` (the tool's axes when the
        command starts).
    """

    pos_xyz_rot_xyz: F64
    force_xyz_torque_xyz: F64 = field(default_factory=lambda: np.zeros(6))
    selection_vector: F64 = field(default_factory=lambda: np.zeros(6))
    frame: Literal["world", "tool"] = "world"

    @property
    def goal_p(self) -> F64:
        return np.asarray(self.pos_xyz_rot_xyz[:3], dtype=np.float64)

    @property
    def goal_R(self) -> F64:
        return rotvec_to_matrix(np.asarray(self.pos_xyz_rot_xyz[3:], dtype=np.float64))


@dataclass(frozen=True)
class ImpedanceGains:
    """k, d, ki, i_max: per Cartesian axis (x, y, z, rx, ry, rz), world axes:
    stiffness [N/m, N m/rad], damping [N s/m, N m s/rad], integral gain
    [N/(m s), N m/(rad s)] and the bound on the integral's force [N, N m];
    k_null: posture stiffness in the null space [N m/rad] (7,);
    d_joint: joint damping [N m s/rad] (7,)."""

    k: F64
    d: F64
    ki: F64
    i_max: F64
    k_null: F64
    d_joint: F64
    zeta: float = 0.0


@dataclass(frozen=True)
class ForceParams:
    """k_adm: admittance [m/(N s)] and [rad/(N m s)]; v_max [m/s], w_max [rad/s]:
    bounds on the reference's speed on force axes; a_max [m/s^2], alpha_max
    [rad/s^2]: bounds on its acceleration (a reference that jumps to full
    speed jolts the arm sideways, and the peg misses a hole with 0.5 mm of
    clearance); contact_n: force that means contact [N]; ramp_s: time to
    feed the goal wrench in after contact."""

    k_adm: float = 0.002
    k_adm_rot: float = 0.05
    v_max: float = 0.01
    w_max: float = 0.05
    a_max: float = 0.02
    alpha_max: float = 0.1
    contact_n: float = 3.0
    ramp_s: float = 0.1


@dataclass
class HybridState:
    """What the law keeps between cycles (one per robot and segment)."""

    R_task: F64 = field(default_factory=lambda: np.eye(3))  # world from task axes
    xi: F64 = field(default_factory=lambda: np.zeros(6))  # force axes' reference offset (task)
    xi_v: F64 = field(default_factory=lambda: np.zeros(6))  # its rate of change (task axes)
    a_ref: F64 = field(default_factory=lambda: np.zeros(6))
    integral: F64 = field(default_factory=lambda: np.zeros(6))
    contact: bool = False
    contact_t_s: float = 0.0  # time in the segment when contact was first felt
    ramp: float = 0.0


def start_state(cmd: TaskFrameCommand, kin: Kinematics) -> HybridState:
    """The state for a command starting at pose ``kin``."""
    s = HybridState()
    s.R_task = kin.R.copy() if cmd.frame == "tool" else np.eye(3)
    return s


def _rot6(R: F64, v: F64) -> F64:
    return np.concatenate([R @ v[:3], R @ v[3:]])


def applied_wrench_task(wrench_sensor: F64, kin: Kinematics, R_task: F64) -> F64:
    """The wrench the tool applies on its environment, in task axes, moment about the TCP.

    wrench_sensor: the external wrench on the tool measured by the wrist
    sensor, sensor axes, about the sensor's origin."""
    f_w = kin.R @ wrench_sensor[:3]
    m_w = kin.R @ wrench_sensor[3:]
    r = kin.p - kin.sensor_p  # sensor origin -> TCP
    m_tcp = m_w - np.cross(r, f_w)
    applied = -np.concatenate([f_w, m_tcp])
    return np.concatenate([R_task.T @ applied[:3], R_task.T @ applied[3:]])


def damping_matrix(lam: F64, k: F64, zeta: float) -> F64:
    """Translational damping with the damping ratio ``zeta`` along every
    direction of the arm's own inertia ``lam`` (3x3, [kg]) under the
    stiffness ``k`` (3, [N/m]): D = 2 zeta L^1/2 (L^-1/2 K L^-1/2)^1/2 L^1/2,
    L^1/2 the symmetric square root of lam. A fixed D cannot do this: the
    TCP's inertia differs tenfold between directions, and a D that damps the
    heavy direction well goes unstable under loop delay in the light one."""
    w, v = np.linalg.eigh(lam)
    w = np.maximum(w, 1e-9)
    half = (v * np.sqrt(w)) @ v.T
    inv_half = (v / np.sqrt(w)) @ v.T
    a_w, a_v = np.linalg.eigh(inv_half @ np.diag(k) @ inv_half)
    a_half = (a_v * np.sqrt(np.maximum(a_w, 0.0))) @ a_v.T
    out: F64 = 2.0 * zeta * (half @ a_half @ half)
    return out


def hybrid_update(
    gains: ImpedanceGains,
    force: ForceParams,
    state: HybridState,
    cmd: TaskFrameCommand,
    kin: Kinematics,
    q: F64,
    qd: F64,
    gravity_nm: F64,
    p_ref: F64,
    R_ref: F64,
    v_ref: F64,
    wrench_sensor: F64,
    q_null: F64,
    t_s: float,
    dt_s: float,
    integrate: bool = True,
    a_ref: F64 | None = None,
    inertia: TaskInertia | None = None,
) -> tuple[F64, F64]:
    """Joint torques [N m] for one cycle, and the applied wrench in task axes.

    p_ref, R_ref, v_ref: the position-controlled reference at this time
    (world; v_ref = linear and angular velocity); integrate: let the integral
    act (off while the reference moves: tracking lag must not wind it up);
    a_ref: the position reference's acceleration (world, linear and angular);
    inertia: the arm's task-space inertia at q (``ArmModel.task_inertia``):
    with it the law adds the inertia feedforward of the reference's
    acceleration, damps the translation with the ratio ``gains.zeta`` (when
    not 0) and projects the posture torque with the dynamically consistent
    projector; without it, none of these, the fixed damping ``gains.d`` and
    the pseudo-inverse projector.
    Updates ``state``.
    """
    s = np.asarray(cmd.selection_vector, dtype=np.float64)
    Rt = state.R_task
    applied = applied_wrench_task(wrench_sensor, kin, Rt)
    goal_w = np.asarray(cmd.force_xyz_torque_xyz, dtype=np.float64)
    if s.any():
        if not state.contact and float(np.linalg.norm((s * applied)[:3])) >= force.contact_n:
            state.contact = True
            state.contact_t_s = t_s
        if state.contact:
            state.ramp = min(1.0, state.ramp + dt_s / max(force.ramp_s, 1e-9))
        err = goal_w - applied
        want = np.concatenate(
            [
                np.clip(force.k_adm * err[:3], -force.v_max, force.v_max),
                np.clip(force.k_adm_rot * err[3:], -force.w_max, force.w_max),
            ]
        )
        dv = np.array([force.a_max] * 3 + [force.alpha_max] * 3) * dt_s
        before_v = state.xi_v.copy()
        state.xi_v = s * (state.xi_v + np.clip(want - state.xi_v, -dv, dv))
        state.a_ref = (state.xi_v - before_v) / max(dt_s, 1e-9)
        # the reference offset is kept in the task frame, relative to the pose
        # reference: on a force axis the tool goes where the force says
        state.xi += state.xi_v * dt_s
    # reference pose: position axes from the trajectory, force axes offset by xi
    p_task = Rt.T @ p_ref
    p_task = np.where(s[:3] > 0, p_task + state.xi[:3], p_task)
    p_goal = Rt @ p_task
    R_goal = rotvec_to_matrix(Rt @ (s[3:] * state.xi[3:])) @ R_ref
    e = pose_error(kin.p, kin.R, p_goal, R_goal)
    v = kin.J @ qd
    v_ref_task = _rot6(Rt.T, v_ref) * (1.0 - s)
    v_goal = _rot6(Rt, v_ref_task)
    # integral action on the position-controlled axes only
    pos_mask = np.abs(_rot6(Rt, 1.0 - s)) > 0.5
    i_lim = np.divide(gains.i_max, gains.ki, out=np.zeros(6), where=gains.ki > 0)
    if integrate:
        state.integral = np.clip(state.integral + e * dt_s * pos_mask, -i_lim, i_lim)
    dv = v_goal - v
    damping = gains.d * dv
    if inertia is not None and gains.zeta > 0:
        damping[:3] = damping_matrix(inertia.lam_lin, gains.k[:3], gains.zeta) @ dv[:3]
    F = gains.k * e + damping + gains.ki * state.integral
    F += _rot6(Rt, s * state.ramp * goal_w)
    if inertia is not None:
        # inertia feedforward: the force that gives the reference's own
        # acceleration (trajectory on position axes, admittance on force
        # axes) through the arm's task-space inertia; without it the arm's
        # coupling turns a descent along z into a sideways error
        a_task = _rot6(Rt.T, a_ref) * (1.0 - s) if a_ref is not None else np.zeros(6)
        F += inertia.lam @ _rot6(Rt, a_task + s * state.a_ref)
    J = kin.J
    # null space of J^T: posture stiffness without disturbing the TCP
    if inertia is not None:
        N = inertia.null
    else:
        JJt = J @ J.T + 1e-4 * np.eye(6)
        pinvT = np.linalg.solve(JJt, J)  # (J^+)^T = (J J^T)^-1 J
        N = np.eye(7) - J.T @ pinvT
    tau: F64 = J.T @ F + gravity_nm + N @ (gains.k_null * (q_null - q)) - gains.d_joint * qd
    return tau, applied

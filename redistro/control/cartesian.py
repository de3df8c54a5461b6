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

The numpy composition here is the reference of the compiled law
(control/cartesian_kernel.c), which :mod:`redistro.control.cartesian_law`
drives cycle after cycle.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
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
    spring0: F64 = field(default_factory=lambda: np.zeros(3))  # spring offset at contact (task)


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


@dataclass(frozen=True)
class LawParams:
    """The law's fixed parameters: the impedance and the force axes'."""

    gains: ImpedanceGains
    force: ForceParams = field(default_factory=ForceParams)


@dataclass
class ArmNow:
    """The arm as measured this cycle: the TCP's kinematics, the joints
    (q, qd [rad, rad/s]), gravity's torques [N m], the wrist's wrench (sensor
    axes, about its origin) and, when known, the task-space inertia at q
    (``ArmModel.task_inertia``)."""

    kin: Kinematics
    q: F64
    qd: F64
    gravity_nm: F64
    wrench_sensor: F64
    inertia: TaskInertia | None = None


@dataclass
class Reference:
    """The position-controlled reference at this time (world): p, R, the
    linear and angular velocity v (6) and acceleration a (6; None: not
    fed forward), and the posture the null space pulls to (7)."""

    p: F64
    R: F64
    v: F64
    q_null: F64
    a: F64 | None = None


@dataclass(frozen=True)
class Tick:
    """This cycle's times: in the task and the cycle [s], and whether the
    integral may act (off while the reference moves: tracking lag must not
    wind it up)."""

    t_s: float
    dt_s: float
    integrate: bool = True


def _admittance(
    force: ForceParams, state: HybridState, s: F64, applied: F64, goal_w: F64, tick: Tick, push: F64
) -> None:
    """The force axes' reference offset: the contact's bumpless handover,
    the goal's ramp, and the admittance within speed and acceleration
    bounds. push: what the spring pushes along the force axes now."""
    dt_s = tick.dt_s
    if not state.contact and float(np.linalg.norm((s * applied)[:3])) >= force.contact_n:
        state.contact = True
        state.contact_t_s = tick.t_s
        # bumpless handover: the approach's speed stops, and what the spring
        # already pushes along the force axes is handed over to the goal's
        # ramp (else the two add up and overshoot the goal)
        state.spring0 = s[:3] * push
        state.xi_v[:3] = 0.0
    if state.contact:
        before_ramp = state.ramp
        state.ramp = min(1.0, state.ramp + dt_s / max(force.ramp_s, 1e-9))
        state.xi[:3] -= state.spring0 * (state.ramp - before_ramp)
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


def _task_wrench(
    gains: ImpedanceGains, state: HybridState, s: F64, arm: ArmNow, ref: Reference, tick: Tick
) -> tuple[F64, F64]:
    """The task-space wrench F (world) and the pose error's goal wrench part."""
    Rt, kin = state.R_task, arm.kin
    # reference pose: position axes from the trajectory, force axes offset by xi
    p_task = Rt.T @ ref.p
    p_task = np.where(s[:3] > 0, p_task + state.xi[:3], p_task)
    R_goal = rotvec_to_matrix(Rt @ (s[3:] * state.xi[3:])) @ ref.R
    e = pose_error(kin.p, kin.R, Rt @ p_task, R_goal)
    v_goal = _rot6(Rt, _rot6(Rt.T, ref.v) * (1.0 - s))
    # integral action on the position-controlled axes only
    pos_mask = np.abs(_rot6(Rt, 1.0 - s)) > 0.5
    i_lim = np.divide(gains.i_max, gains.ki, out=np.zeros(6), where=gains.ki > 0)
    if tick.integrate:
        state.integral = np.clip(state.integral + e * tick.dt_s * pos_mask, -i_lim, i_lim)
    dv = v_goal - kin.J @ arm.qd
    damping = gains.d * dv
    if arm.inertia is not None and gains.zeta > 0:
        damping[:3] = damping_matrix(arm.inertia.lam_lin, gains.k[:3], gains.zeta) @ dv[:3]
    F: F64 = gains.k * e + damping + gains.ki * state.integral
    return F, e


def hybrid_update(
    law: LawParams,
    state: HybridState,
    cmd: TaskFrameCommand,
    arm: ArmNow,
    ref: Reference,
    tick: Tick,
) -> tuple[F64, F64]:
    """Joint torques [N m] for one cycle, and the applied wrench in task axes.

    With the arm's task-space inertia (``arm.inertia``) the law adds the
    inertia feedforward of the reference's acceleration, damps the
    translation with the ratio ``gains.zeta`` (when not 0) and projects the
    posture torque with the dynamically consistent projector; without it,
    none of these, the fixed damping ``gains.d`` and the pseudo-inverse
    projector. Updates ``state``.
    """
    gains, kin, Rt = law.gains, arm.kin, state.R_task
    s = np.asarray(cmd.selection_vector, dtype=np.float64)
    applied = applied_wrench_task(arm.wrench_sensor, kin, Rt)
    goal_w = np.asarray(cmd.force_xyz_torque_xyz, dtype=np.float64)
    if s.any():
        push = Rt.T @ ref.p + state.xi[:3] - Rt.T @ kin.p
        _admittance(law.force, state, s, applied, goal_w, tick, push)
    F, _e = _task_wrench(gains, state, s, arm, ref, tick)
    F += _rot6(Rt, s * state.ramp * goal_w)
    if arm.inertia is not None:
        # inertia feedforward: the force that gives the reference's own
        # acceleration (trajectory on position axes, admittance on force
        # axes) through the arm's task-space inertia; without it the arm's
        # coupling turns a descent along z into a sideways error
        a_task = _rot6(Rt.T, ref.a) * (1.0 - s) if ref.a is not None else np.zeros(6)
        F += arm.inertia.lam @ _rot6(Rt, a_task + s * state.a_ref)
    J = kin.J
    # null space of J^T: posture stiffness without disturbing the TCP
    if arm.inertia is not None:
        N = arm.inertia.null
    else:
        JJt = J @ J.T + 1e-4 * np.eye(6)
        N = np.eye(7) - J.T @ np.linalg.solve(JJt, J)  # (J^+)^T = (J J^T)^-1 J
    posture = N @ (gains.k_null * (ref.q_null - arm.q))
    tau: F64 = J.T @ F + arm.gravity_nm + posture - gains.d_joint * arm.qd
    return tau, applied


def move_gains(
    into: np.ndarray[Any, Any], config: np.ndarray[Any, Any], k: Sequence[float]
) -> None:
    """A move's law gains (``into``): the config's, with the move's own
    stiffness ``k`` where it gives one (6: N/m, N m/rad), the rotation's
    damping scaled by sqrt(k / k_config) to keep its damping ratio."""
    into[...] = config
    if k:
        k0, d0 = config["k"][3:], config["d"][3:]
        into["k"][:] = k
        into["d"][3:] = d0 * np.sqrt(into["k"][3:] / np.where(k0 > 0, k0, into["k"][3:]))

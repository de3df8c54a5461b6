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

Past the house's ~400 lines: the law's numpy composition is the compiled
kernel's reference, and the class that drives either sits beside it.
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
            # bumpless handover: the approach's speed stops, and what the
            # spring already pushes along the force axes is handed over to
            # the goal's ramp (else the two add up and overshoot the goal)
            state.spring0 = s[:3] * (Rt.T @ p_ref + state.xi[:3] - Rt.T @ kin.p)
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


class CartesianLaw:
    """One arm's Cartesian law, cycle after cycle: the TCP from the tool
    frame, the segment's reference (a quintic in position, the same blend
    about one axis in rotation), the task-space inertia and
    :func:`hybrid_update`, in one compiled kernel call
    (``redistro._kernels.cartesian_law``) on preallocated buffers; the same
    composed from this module's functions (``use_kernel=False``) is its
    reference. Buffers (float64, filled in place):

    - ``kin``: the rigid-body terms of this cycle: J (6x7, the tool frame's
      Jacobian, LOCAL_WORLD_ALIGNED), R (3x3) and t (3) of the tool frame,
      M (7x7, upper triangle as CRBA leaves it), g (7), q, qd (7), the
      wrist wrench (6, sensor frame), then seg_t, dt, t (task) [s] and
      integrate (0/1);
    - ``ref``: start_p (3), goal_p (3), start_R (3x3), goal_R (3x3), the
      rotation's axis (rotation vector of goal_R start_R^T), move_s;
    - ``cmd``: selection (6), goal wrench (6), q_null (7);
    - ``gains``: k, d, ki, i_max (6 each), k_null, d_joint (7 each), zeta,
      the force parameters (8), the TCP offset [m], the base (3);
    - ``state``: R_task (3x3), xi, xi_v, a_ref, integral (6 each), contact,
      contact_t, ramp, the spring's offset at contact (3) (what
      :class:`HybridState` holds);
    - ``out``: tau (7), the applied wrench in task axes (6), TCP position
      (3), TCP rotation vector (3), the position reference (3).
    """

    def __init__(
        self,
        gains: ImpedanceGains,
        force: ForceParams,
        tcp_offset_m: float,
        base_xyz_m: F64,
        *,
        use_kernel: bool | None = None,
    ) -> None:
        from redistro import kernels

        self.kin = np.zeros(134)
        self.ref = np.zeros(28)
        self.cmd = np.zeros(19)
        self.gains = np.zeros(51)
        self.state = np.zeros(39)
        self.out = np.zeros(22)
        g = self.gains
        g[0:6], g[6:12], g[12:18], g[18:24] = gains.k, gains.d, gains.ki, gains.i_max
        g[24:31], g[31:38], g[38] = gains.k_null, gains.d_joint, gains.zeta
        g[39:47] = (
            force.k_adm,
            force.k_adm_rot,
            force.v_max,
            force.w_max,
            force.a_max,
            force.alpha_max,
            force.contact_n,
            force.ramp_s,
        )
        g[47], g[48:51] = tcp_offset_m, base_xyz_m
        self.impedance, self.force, self.tcp_offset = gains, force, tcp_offset_m
        self.base = np.asarray(base_xyz_m, dtype=np.float64)
        k = self.kin
        self.J, self.R, self.t = k[0:42].reshape(6, 7), k[42:51].reshape(3, 3), k[51:54]
        self.M, self.g = k[54:103].reshape(7, 7), k[103:110]
        self.q, self.qd, self.wrench = k[110:117], k[117:124], k[124:130]
        self.tau, self.applied = self.out[0:7], self.out[7:13]
        self.tcp_p, self.tcp_rot, self.ref_p = self.out[13:16], self.out[16:19], self.out[19:22]
        self.use_kernel = kernels.AVAILABLE if use_kernel is None else use_kernel
        self._run: Any = self._update_numpy
        if self.use_kernel:
            plan = kernels.plan(
                "cartesian_law",
                kin=self.kin,
                ref=self.ref,
                cmd=self.cmd,
                gains=self.gains,
                state=self.state,
                out=self.out,
            )
            law = kernels.KERNELS.cartesian_law
            self._run = lambda: law(plan)

    def start(
        self,
        cmd: TaskFrameCommand,
        start_p: F64,
        start_R: F64,
        move_s: float,
        q_null: F64,
        integral: F64 | None = None,
    ) -> None:
        """A new segment: its command, where it starts (the TCP's pose and the
        joints' posture), its move time; the integral to carry over (None:
        a fresh one)."""
        r = self.ref
        r[0:3], r[3:6] = start_p, cmd.goal_p
        r[6:15], r[15:24] = np.asarray(start_R).reshape(9), cmd.goal_R.reshape(9)
        r[24:27] = matrix_to_rotvec(cmd.goal_R @ np.asarray(start_R).T)
        r[27] = move_s
        c = self.cmd
        c[0:6], c[6:12], c[12:19] = cmd.selection_vector, cmd.force_xyz_torque_xyz, q_null
        s = self.state
        s[:] = 0.0
        s[0:9] = (np.asarray(start_R) if cmd.frame == "tool" else np.eye(3)).reshape(9)
        if integral is not None:
            s[27:33] = integral

    def release(self) -> None:
        """Back to free space along the force axes, mid-segment (the peg
        dropped into a hole): the contact is forgotten, the goal wrench's
        ramp starts again at the next contact, and the reference stands
        where the TCP is, still (else the spring's offset and the fed-forward
        goal throw the tool at whatever it meets next)."""
        st = self.state
        sel = self.cmd[0:3] > 0
        Rt = st[0:9].reshape(3, 3)
        offset = Rt.T @ (self.tcp_p - self.ref_p)
        st[9:12][sel] = offset[sel]
        st[15:18][sel] = 0.0
        st[21:24][sel] = 0.0
        st[33:39] = 0.0

    @property
    def integral(self) -> F64:
        out: F64 = self.state[27:33]
        return out

    @property
    def contact(self) -> bool:
        return bool(self.state[33])

    def update(self, seg_t: float, dt: float, t_s: float, integrate: bool) -> None:
        """One cycle, the rigid-body terms already in ``kin``: fills ``out``."""
        k = self.kin
        k[130], k[131], k[132], k[133] = seg_t, dt, t_s, 1.0 if integrate else 0.0
        if self._run():
            raise ValueError("the arm's joint-space inertia is not positive definite")

    def _update_numpy(self) -> int:
        """The kernel's arithmetic, composed from this module's functions."""
        from redistro.control.dynamics import Kinematics, TaskInertia

        k, r, c, st = self.kin, self.ref, self.cmd, self.state
        seg_t, dt, t_s, integrate = float(k[130]), float(k[131]), float(k[132]), bool(k[133])
        R = self.R.copy()
        sensor = self.t + self.base
        off = R[:, 2] * self.tcp_offset
        J = self.J.copy()
        J[:3] -= _skew3(off) @ J[3:]
        kin = Kinematics(p=sensor + off, R=R, J=J, sensor_p=sensor)
        start_p, goal_p = r[0:3], r[3:6]
        start_R, goal_R = r[6:15].reshape(3, 3), r[15:24].reshape(3, 3)
        axis, move_s = r[24:27], float(r[27])
        from redistro.control.trajectory import quintic

        p_ref, v_lin, a_lin = quintic(start_p, goal_p, move_s, seg_t)
        s = min(max(seg_t / move_s, 0.0), 1.0)
        blend = 10 * s**3 - 15 * s**4 + 6 * s**5
        R_ref = slerp(start_R, goal_R, blend)
        sd = (30 * s**2 - 60 * s**3 + 30 * s**4) / move_s if s < 1.0 else 0.0
        sdd = (60 * s - 180 * s**2 + 120 * s**3) / move_s**2 if s < 1.0 else 0.0
        v6 = np.concatenate([v_lin, axis * sd])
        a6 = np.concatenate([a_lin, axis * sdd])
        upper = self.M
        M = np.triu(upper) + np.triu(upper, 1).T
        MinvJt = np.linalg.solve(M, J.T)
        A = J @ MinvJt
        lam = np.asarray(np.linalg.inv(A + 1e-6 * np.eye(6)), dtype=np.float64)
        lam_lin = np.asarray(np.linalg.inv(A[:3, :3] + 1e-6 * np.eye(3)), dtype=np.float64)
        null = np.eye(7) - J.T @ (lam @ MinvJt.T)
        inertia = TaskInertia(lam=lam, lam_lin=lam_lin, null=null)
        cmd = TaskFrameCommand(np.zeros(6), c[6:12].copy(), c[0:6].copy())
        hs = HybridState(
            R_task=st[0:9].reshape(3, 3).copy(),
            xi=st[9:15].copy(),
            xi_v=st[15:21].copy(),
            a_ref=st[21:27].copy(),
            integral=st[27:33].copy(),
            contact=bool(st[33]),
            contact_t_s=float(st[34]),
            ramp=float(st[35]),
            spring0=st[36:39].copy(),
        )
        tau, applied = hybrid_update(
            self.impedance,
            self.force,
            hs,
            cmd,
            kin,
            self.q,
            self.qd,
            self.g,
            p_ref,
            R_ref,
            v6,
            self.wrench,
            c[12:19],
            t_s,
            dt,
            integrate=integrate,
            a_ref=a6,
            inertia=inertia,
        )
        st[9:15], st[15:21], st[21:27], st[27:33] = hs.xi, hs.xi_v, hs.a_ref, hs.integral
        st[33], st[34], st[35] = float(hs.contact), hs.contact_t_s, hs.ramp
        st[36:39] = hs.spring0
        self.tau[...], self.applied[...] = tau, applied
        self.tcp_p[...], self.tcp_rot[...], self.ref_p[...] = kin.p, matrix_to_rotvec(R), p_ref
        return 0


def _skew3(v: F64) -> F64:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])

"""One arm's Cartesian law, cycle after cycle, in one compiled call.

:class:`CartesianLaw` works on preallocated records whose layouts are
declared in :mod:`redistro.control.cartesian_layout` (``kin``, ``ref``,
``cmd``, ``gains``, ``state``, ``out``; read and written by field name):
the TCP from the tool frame, the segment's reference (a quintic in
position, the same blend about one axis in rotation), the task-space
inertia and :func:`~redistro.control.cartesian.hybrid_update`, in the
``cartesian_law`` kernel (control/cartesian_kernel.c). The same composed
from :mod:`redistro.control.cartesian`'s functions (``use_kernel=False``)
is its reference.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from redistro.control import cartesian_layout as lay
from redistro.control.cartesian import (
    F64,
    ArmNow,
    ForceParams,
    HybridState,
    ImpedanceGains,
    LawParams,
    Reference,
    TaskFrameCommand,
    Tick,
    hybrid_update,
    matrix_to_rotvec,
    slerp,
)

_FORCE_FIELDS = (
    "k_adm", "k_adm_rot", "v_max", "w_max", "a_max", "alpha_max", "contact_n", "ramp_s",
)  # fmt: skip
_STATE_FIELDS = ("xi", "xi_v", "a_ref", "integral", "spring0")


def _skew3(v: F64) -> F64:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


class CartesianLaw:
    """One arm's law (see the module's text). Records, filled in place:
    ``kin`` this cycle's rigid-body terms (the caller fills J, R, t, M, g,
    q, qd, wrench), ``ref`` the segment's reference, ``cmd`` its selection,
    goal wrench and posture, ``gains``, ``state`` (what
    :class:`HybridState` holds) and ``out`` (tau, the applied wrench in task
    axes, the TCP's pose, the position reference)."""

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

        self.kin = np.zeros((), lay.KIN)
        self.ref = np.zeros((), lay.REF)
        self.cmd = np.zeros((), lay.CMD)
        self.gains = np.zeros((), lay.GAINS)
        self.state = np.zeros((), lay.STATE)
        self.out = np.zeros((), lay.OUT)
        g = self.gains
        for name in ("k", "d", "ki", "i_max", "k_null", "d_joint", "zeta"):
            g[name] = getattr(gains, name)
        for name in _FORCE_FIELDS:
            g[name] = getattr(force, name)
        g["tcp_offset"], g["base"] = tcp_offset_m, base_xyz_m
        self.params = LawParams(gains, force)
        self.tcp_offset = tcp_offset_m
        self.base = np.asarray(base_xyz_m, dtype=np.float64)
        k = self.kin
        self.J, self.R, self.t, self.M, self.g = k["J"], k["R"], k["t"], k["M"], k["g"]
        self.q, self.qd, self.wrench = k["q"], k["qd"], k["wrench"]
        o = self.out
        self.tau, self.applied = o["tau"], o["applied"]
        self.tcp_p, self.tcp_rot, self.ref_p = o["tcp_p"], o["tcp_rot"], o["ref_p"]
        self._times = (k["seg_t"], k["dt"], k["t_task"], k["integrate"])
        self.use_kernel = kernels.AVAILABLE if use_kernel is None else use_kernel
        self._run: Any = self._update_numpy
        if self.use_kernel:
            plan = kernels.plan(
                "cartesian_law", kin=k, ref=self.ref, cmd=self.cmd, gains=g, state=self.state,
                out=o,
            )  # fmt: skip
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
        r["start_p"], r["goal_p"] = start_p, cmd.goal_p
        r["start_R"], r["goal_R"] = start_R, cmd.goal_R
        r["axis"] = matrix_to_rotvec(cmd.goal_R @ np.asarray(start_R).T)
        r["move_s"] = move_s
        c = self.cmd
        c["selection"], c["goal_wrench"], c["q_null"] = (
            cmd.selection_vector,
            cmd.force_xyz_torque_xyz,
            q_null,
        )
        s = self.state
        s[...] = 0
        s["R_task"] = np.asarray(start_R) if cmd.frame == "tool" else np.eye(3)
        if integral is not None:
            s["integral"] = integral

    def release(self) -> None:
        """Back to free space along the force axes, mid-segment (the peg
        dropped into a hole): the contact is forgotten, the goal wrench's
        ramp starts again at the next contact, and the reference stands
        where the TCP is, still (else the spring's offset and the fed-forward
        goal throw the tool at whatever it meets next)."""
        st = self.state
        sel = self.cmd["selection"][:3] > 0
        offset = st["R_task"].T @ (self.tcp_p - self.ref_p)
        st["xi"][:3][sel] = offset[sel]
        st["xi_v"][:3][sel] = 0.0
        st["a_ref"][:3][sel] = 0.0
        for name in ("contact", "contact_t", "ramp", "spring0"):
            st[name] = 0.0

    @property
    def integral(self) -> F64:
        out: F64 = self.state["integral"]
        return out

    @property
    def contact(self) -> bool:
        return bool(self.state["contact"])

    def update(self, seg_t: float, dt: float, t_s: float, integrate: bool) -> None:
        """One cycle, the rigid-body terms already in ``kin``: fills ``out``."""
        a, b, c, d = self._times
        a[...], b[...], c[...], d[...] = seg_t, dt, t_s, 1.0 if integrate else 0.0
        if self._run():
            raise ValueError("the arm's joint-space inertia is not positive definite")

    # -- the reference: the same, composed from control/cartesian.py --

    def _reference(self, seg_t: float) -> Reference:
        """The segment's reference at seg_t (a quintic; the rotation's blend)."""
        from redistro.control.trajectory import quintic

        r = self.ref
        move_s = float(r["move_s"])
        p_ref, v_lin, a_lin = quintic(r["start_p"], r["goal_p"], move_s, seg_t)
        s = min(max(seg_t / move_s, 0.0), 1.0)
        blend = 10 * s**3 - 15 * s**4 + 6 * s**5
        sd = (30 * s**2 - 60 * s**3 + 30 * s**4) / move_s if s < 1.0 else 0.0
        sdd = (60 * s - 180 * s**2 + 120 * s**3) / move_s**2 if s < 1.0 else 0.0
        return Reference(
            p=p_ref,
            R=slerp(r["start_R"], r["goal_R"], blend),
            v=np.concatenate([v_lin, r["axis"] * sd]),
            q_null=self.cmd["q_null"],
            a=np.concatenate([a_lin, r["axis"] * sdd]),
        )

    def _arm(self) -> ArmNow:
        """The arm's kinematics at its TCP and its task-space inertia."""
        from redistro.control.dynamics import Kinematics, TaskInertia

        R = self.R.copy()
        sensor = self.t + self.base
        off = R[:, 2] * self.tcp_offset
        J = self.J.copy()
        J[:3] -= _skew3(off) @ J[3:]
        M = np.triu(self.M) + np.triu(self.M, 1).T
        MinvJt = np.linalg.solve(M, J.T)
        A = J @ MinvJt
        lam = np.asarray(np.linalg.inv(A + 1e-6 * np.eye(6)), dtype=np.float64)
        lam_lin = np.asarray(np.linalg.inv(A[:3, :3] + 1e-6 * np.eye(3)), dtype=np.float64)
        null = np.eye(7) - J.T @ (lam @ MinvJt.T)
        return ArmNow(
            kin=Kinematics(p=sensor + off, R=R, J=J, sensor_p=sensor),
            q=self.q,
            qd=self.qd,
            gravity_nm=self.g,
            wrench_sensor=self.wrench,
            inertia=TaskInertia(lam=lam, lam_lin=lam_lin, null=null),
        )

    def _update_numpy(self) -> int:
        """The kernel's arithmetic, composed from control/cartesian.py."""
        k, c, st = self.kin, self.cmd, self.state
        seg_t = float(k["seg_t"])
        ref, arm = self._reference(seg_t), self._arm()
        tick = Tick(float(k["t_task"]), float(k["dt"]), bool(k["integrate"]))
        cmd = TaskFrameCommand(np.zeros(6), c["goal_wrench"].copy(), c["selection"].copy())
        hs = HybridState(
            R_task=st["R_task"].copy(),
            contact=bool(st["contact"]),
            contact_t_s=float(st["contact_t"]),
            ramp=float(st["ramp"]),
            **{name: st[name].copy() for name in _STATE_FIELDS},
        )
        tau, applied = hybrid_update(self.params, hs, cmd, arm, ref, tick)
        for name in _STATE_FIELDS:
            st[name] = getattr(hs, name)
        st["contact"], st["contact_t"], st["ramp"] = float(hs.contact), hs.contact_t_s, hs.ramp
        self.tau[...], self.applied[...] = tau, applied
        self.tcp_p[...], self.tcp_rot[...], self.ref_p[...] = (
            arm.kin.p,
            matrix_to_rotvec(arm.kin.R),
            ref.p,
        )
        return 0

"""Rigid-body terms of one arm from Pinocchio, built from the plant's own URDF."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from redistro.robotmodel import JOINT_NAMES, PLATE, TOOL_LINK, Peg, write_arm_urdf

F64 = np.ndarray[Any, np.dtype[np.float64]]


@dataclass(frozen=True)
class Kinematics:
    """The tool centre point (TCP) of one arm at one joint position, world frame.

    p: TCP position [m]; R: world-from-tool rotation (the wrist sensor's
    frame has the same axes); J: 6x7 Jacobian of the TCP's linear and angular
    velocity in world axes; sensor_p: the wrist sensor's origin [m].
    """

    p: F64
    R: F64
    J: F64
    sensor_p: F64


@dataclass(frozen=True)
class TaskInertia:
    """The arm's inertia as the TCP feels it, at one joint position.

    lam: Lambda = (J M^-1 J^T)^-1, 6x6 [kg, kg m^2]; lam_lin: the
    translational inertia with the rotation free, (J_lin M^-1 J_lin^T)^-1,
    3x3 [kg]; null: the dynamically consistent null-space projector
    I - J^T (M^-1 J^T Lambda)^T (7x7): posture torques through it do not
    move the TCP.
    """

    lam: F64
    lam_lin: F64
    null: F64


class ArmModel:
    """Gravity torques and TCP kinematics of one arm (its tool included).

    The URDF is the plant's (:mod:`redistro.robotmodel`): same links, same
    inertias, same tool. The base is not rotated; gravity is -z. The TCP is
    the tool's far end on the tool axis: the peg's tip on an arm carrying the
    peg, the sensor plate's face otherwise. ``base_xyz_m`` places the arm in
    the world.
    """

    def __init__(self, peg: Peg | None, base_xyz_m: list[float] | None = None) -> None:
        import pinocchio as pin

        self._pin = pin
        with tempfile.TemporaryDirectory(prefix="redistro-pin-") as tmp:
            path = write_arm_urdf(Path(tmp), "arm", peg)
            self.model = pin.buildModelFromUrdf(str(path))
        names = [self.model.names[i] for i in range(1, self.model.njoints)]
        if names != JOINT_NAMES:
            raise ValueError(f"unexpected joints in the arm model: {names}")
        self.data = self.model.createData()
        self.tool_frame = self.model.getFrameId(TOOL_LINK)
        self.tcp_offset_m = peg.length_m if peg is not None else PLATE[1]
        self.base = np.asarray(base_xyz_m or [0.0, 0.0, 0.0], dtype=np.float64)

    def gravity(self, q: F64) -> F64:
        """g(q): joint torques [N m] that hold the arm still against gravity."""
        out: F64 = self._pin.computeGeneralizedGravity(self.model, self.data, q).copy()
        return out

    def gravity_into(self, q: F64, out: F64) -> None:
        """g(q) into ``out`` [N m]."""
        out[...] = self._pin.computeGeneralizedGravity(self.model, self.data, q)

    def task_inertia(self, q: F64, J: F64) -> TaskInertia:
        """The TCP's task-space inertia at q (regularized near singularities)
        and the dynamically consistent null-space projector."""
        upper = self._pin.crba(self.model, self.data, q)
        M = np.triu(upper) + np.triu(upper, 1).T  # crba fills the upper triangle
        MinvJt = np.linalg.solve(M, J.T)
        A = J @ MinvJt
        lam = np.asarray(np.linalg.inv(A + 1e-6 * np.eye(6)), dtype=np.float64)
        lam_lin = np.asarray(np.linalg.inv(A[:3, :3] + 1e-6 * np.eye(3)), dtype=np.float64)
        # N = I - J^T Jbar^T, Jbar = M^-1 J^T Lambda: a torque N t0 gives the
        # TCP no acceleration at all (J M^-1 N t0 = 0)
        null = np.eye(J.shape[1]) - J.T @ (lam @ MinvJt.T)
        return TaskInertia(lam=lam, lam_lin=lam_lin, null=null)

    def terms_into(self, q: F64, J: F64, R: F64, t: F64, M: F64, g: F64) -> None:
        """The rigid-body terms a Cartesian law needs at ``q``, into the given
        arrays: the tool frame's Jacobian J (6x7, LOCAL_WORLD_ALIGNED; not
        yet moved to the TCP), its rotation R and position t (the base not
        added), the joint-space inertia M (7x7: its upper triangle, as CRBA
        fills it) and gravity g (7). Pinocchio once per quantity."""
        pin, model, data = self._pin, self.model, self.data
        J[...] = pin.computeFrameJacobian(
            model, data, q, self.tool_frame, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
        )
        oMf = data.oMf[self.tool_frame]
        R[...] = oMf.rotation
        t[...] = oMf.translation
        M[...] = pin.crba(model, data, q)
        g[...] = pin.computeGeneralizedGravity(model, data, q)

    def pose_into(self, q: F64, R: F64, t: F64) -> None:
        """The tool frame's rotation and position at ``q`` (base not added)."""
        pin, model, data = self._pin, self.model, self.data
        pin.forwardKinematics(model, data, q)
        oMf = pin.updateFramePlacement(model, data, self.tool_frame)
        R[...] = oMf.rotation
        t[...] = oMf.translation

    def kinematics(self, q: F64) -> Kinematics:
        """TCP pose and Jacobian at ``q`` (world frame)."""
        pin = self._pin
        J = pin.computeFrameJacobian(
            self.model, self.data, q, self.tool_frame, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
        )
        M = self.data.oMf[self.tool_frame]
        R = np.array(M.rotation)
        sensor = np.array(M.translation) + self.base
        r = R[:, 2] * self.tcp_offset_m  # tool origin -> TCP, world axes
        Jt = np.array(J)
        # v_tcp = v_tool + w x r  =>  J_lin -= [r]x J_ang
        Jt[:3] -= _skew(r) @ Jt[3:]
        return Kinematics(p=sensor + r, R=R, J=Jt, sensor_p=sensor)


def _skew(v: F64) -> F64:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])

"""A move that follows the hand holding its target: a goal relative to
``<object>.hole`` while another robot's gripper holds the object. The plan
put the hole where that hand's pose goal takes it; in the cell the hand is
off its goal (its impedance yields to the contact, the grip is not where
the plan thought). Each cycle the follower's law sees its own TCP in the
frame the plan drew: measured, less where the hole really went from its
planned place by the holder's measured pose (``delta``); its plan record
(the log) shows the TCP in that frame too. Per cycle, in
following moves only: the holder's forward kinematics and a 3x3 product
(:meth:`Follow.update`, hot: 10 µs p50, 22 µs p99 on the project's machine)."""

from __future__ import annotations

from typing import Any

import numpy as np

from redistro.control.cartesian import rotvec_to_matrix


class Follow:
    """The holder's planned tool pose and the planned point (the hole's
    mouth) it carries, for :meth:`delta`."""

    def __init__(self, holder_pose: np.ndarray[Any, Any], point: np.ndarray[Any, Any]) -> None:
        self.point = np.asarray(point, dtype=np.float64)
        # the point in the holder's tool frame, as planned
        self.local = rotvec_to_matrix(np.asarray(holder_pose[3:])).T @ (
            self.point - np.asarray(holder_pose[:3], dtype=np.float64)
        )
        # scratch, made once: the holder's tool frame, its TCP, a product
        self.R, self.t, self.p, self.v = np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3)
        self.d = np.zeros(3)

    def update(self, holder: Any) -> np.ndarray[Any, Any]:
        """:meth:`delta` with the holder's TCP measured now (``holder``: its
        robot state in the SSC worker), into ``self.d`` (nothing allocated)."""
        holder.model.pose_into(holder.views["q"], self.R, self.t)
        p, v = self.p, self.v
        np.multiply(self.R[:, 2], holder.tcp_offset_m, out=v)
        np.add(holder.base, self.t, out=p)
        p += v
        np.matmul(self.R, self.local, out=v)
        np.add(p, v, out=self.d)
        self.d -= self.point
        return self.d

    def delta(self, p: np.ndarray[Any, Any], R: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        """Where the point is with the holder's TCP measured at ``p``, ``R``
        (world), less where the plan put it [m]."""
        out: np.ndarray[Any, Any] = p + R @ self.local - self.point
        return out

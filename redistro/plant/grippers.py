"""The flanges' grippers, as the plant sees them: each closes while its DIO
output is on (open at power-on), and the world welds whatever it closes on
(a PyBullet fixed constraint, where the object really is). Per physics
step: one bit test per fitted gripper; the rest only when one changes."""

from __future__ import annotations

import math
from typing import Any

from redistro.config.hardware import RobotHardware

GRASP_REACH_M = 0.015  # a gripper takes an object whose top face is this near its tool point
WELD_MAX_N = 5000.0  # the weld's strength: far above what the arms' torques can pull


class Grippers:
    def __init__(
        self, rigs: list[Any], hardware: dict[str, RobotHardware], row: dict[int, int], world: Any
    ) -> None:
        self.world = world
        # (robot, arm, DIO board row, bit) of each fitted gripper
        self.fitted: list[tuple[str, Any, int, int]] = []
        for rig in rigs:
            ch = hardware[rig.name].gripper
            if ch is not None:
                self.fitted.append((rig.name, rig.arm, row[ch.address], ch.index))
        self.closed = [False] * len(self.fitted)
        self.held: dict[str, tuple[int, str]] = {}  # robot -> (constraint, object)
        # every change: robot, step, closed, the object taken ('' none) and
        # the tool point it was taken at [m, world]
        self.events: list[dict[str, Any]] = []
        self.start = self.object_poses()  # where the objects were at power-on

    def apply(self, dio_outputs: Any, step: int) -> None:
        """Act on the DIO outputs as the controller left them this step."""
        for k, (robot, arm, row, bit) in enumerate(self.fitted):
            closed = (int(dio_outputs[row]) >> bit) & 1 == 1
            if closed == self.closed[k]:
                continue
            self.closed[k] = closed
            took, at = self.set(robot, arm, closed)
            if len(self.events) < 1000:
                self.events.append(
                    {"robot": robot, "step": step, "closed": closed, "took": took, "at_xyz_m": at}
                )

    def set(self, robot: str, arm: Any, closed: bool) -> tuple[str, list[float]]:
        """The gripper of ``arm`` closed or opened. Closing on an object
        within reach (the tool point over its top face, within
        ``GRASP_REACH_M`` of it) welds the object to the tool link where it
        is (a fixed constraint); opening lets it go. Returns the name of the
        object taken ('' when none) and the tool point [m, world]."""
        pb, cid = self.world.pb, self.world.client
        held = self.held.pop(robot, None)
        if held is not None:
            pb.removeConstraint(held[0], physicsClientId=cid)
            self._touching(arm, self.world.objects[held[1]], True)
        ls = pb.getLinkState(arm.body, arm.tool_link, physicsClientId=cid)
        com_p, com_o, tool_p, tool_o = ls[0], ls[1], ls[4], ls[5]
        at = [round(float(v), 6) for v in tool_p]
        if not closed:
            return "", at
        for name, body in self.world.objects.items():
            pos, orn = pb.getBasePositionAndOrientation(body, physicsClientId=cid)
            inv_p, inv_o = pb.invertTransform(pos, orn)
            local, _ = pb.multiplyTransforms(inv_p, inv_o, tool_p, tool_o)
            hx, hy, hz = (v / 2 for v in self.world.cfg.workcell.objects[name].size_xyz_m)
            if abs(local[0]) > hx or abs(local[1]) > hy or abs(local[2] - hz) > GRASP_REACH_M:
                continue
            # the object where it is, in the tool link's centre-of-mass frame
            inv_p, inv_o = pb.invertTransform(com_p, com_o)
            rel_p, rel_o = pb.multiplyTransforms(inv_p, inv_o, pos, orn)
            c = pb.createConstraint(
                arm.body, arm.tool_link, body, -1, pb.JOINT_FIXED, [0, 0, 0],
                parentFramePosition=rel_p, childFramePosition=[0, 0, 0],
                parentFrameOrientation=rel_o, physicsClientId=cid,
            )  # fmt: skip
            pb.changeConstraint(c, maxForce=WELD_MAX_N, physicsClientId=cid)
            self._touching(arm, body, False)  # (the fingers' own contact is the weld)
            self.held[robot] = (int(c), str(name))
            return str(name), at
        return "", at

    def _touching(self, arm: Any, body: int, on: bool) -> None:
        """Contacts between an arm's links and an object on or off."""
        pb, cid = self.world.pb, self.world.client
        for link in range(-1, pb.getNumJoints(arm.body, physicsClientId=cid)):
            pb.setCollisionFilterPair(arm.body, body, link, -1, on, physicsClientId=cid)

    def object_poses(self) -> dict[str, dict[str, Any]]:
        """Each object's pose (its centre [m], its yaw about the world's z
        [deg], its tilt from upright [deg], its orientation as a quaternion
        x, y, z, w) and the robots holding it (two
        hands on one object: a closed chain)."""
        pb, cid = self.world.pb, self.world.client
        holders: dict[str, list[str]] = {}
        for robot, (_, n) in sorted(self.held.items()):
            holders.setdefault(n, []).append(robot)
        out: dict[str, dict[str, Any]] = {}
        for name, body in self.world.objects.items():
            pos, orn = pb.getBasePositionAndOrientation(body, physicsClientId=cid)
            R = pb.getMatrixFromQuaternion(orn)
            out[name] = {
                "xyz_m": [round(float(v), 5) for v in pos],
                "yaw_deg": round(math.degrees(math.atan2(R[3], R[0])), 3),
                "tilt_deg": round(math.degrees(math.acos(max(-1.0, min(1.0, R[8])))), 3),
                "quat_xyzw": [round(float(v), 7) for v in orn],
                "held_by": holders.get(name, []),
            }
        return out

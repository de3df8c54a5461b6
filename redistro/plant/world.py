"""The PyBullet world: floor, table, hole fixture, two arms with their tools.

Only this module talks to PyBullet. PyBullet's tuples are wrapped in
NamedTuples; joints are found by name, never by a hard-coded index.

Past the house's ~400 lines on purpose: it is the one place that talks to
PyBullet (the scene, the arms, the motors, the sensors' truth).
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from redistro.config.model import Config, ObjectConfig
from redistro.plant.truth import HolePose
from redistro.robotmodel import JOINT_NAMES, SENSOR_JOINT, TOOL_LINK, Peg, write_arm_urdf

GRAVITY = 9.81


class JointInfo(NamedTuple):
    joint: int
    name: str
    type: int
    lower: float
    upper: float
    max_force: float
    max_velocity: float
    link_name: str


class JointState(NamedTuple):
    position: float
    velocity: float
    reaction: tuple[float, float, float, float, float, float]
    applied_torque: float


class ContactPoint(NamedTuple):
    flag: int
    body_a: int
    body_b: int
    link_a: int
    link_b: int
    position_on_a: tuple[float, float, float]
    position_on_b: tuple[float, float, float]
    normal_on_b: tuple[float, float, float]
    distance: float
    normal_force: float
    friction1: float
    friction_dir1: tuple[float, float, float]
    friction2: float
    friction_dir2: tuple[float, float, float]


@dataclass
class Arm:
    name: str
    body: int
    joints: list[int]  # PyBullet joint indices of the 7 revolute joints
    sensor_joint: int  # the fixed wrist_ft joint
    tool_link: int
    tool_mass_kg: float
    tool_com_m: np.ndarray  # tool centre of mass in the sensor frame
    braked: np.ndarray  # bool (7,): brake engaged (the joint motor is a brake)
    brake_torque_nm: np.ndarray
    # bool (7,): the engaged brake has stopped its joint and holds its angle
    brake_held: np.ndarray = field(default_factory=lambda: np.zeros(7, dtype=bool))
    # (7,): the motor torques of the last step [N m] (0 on a braked joint)
    motor_tau: np.ndarray = field(default_factory=lambda: np.zeros(7))

    # tool_com_m as plain floats (read every step)
    tool_com: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        x, y, z = self.tool_com_m.tolist()
        self.tool_com = (x, y, z)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """3-vector cross product (np.cross costs ten times more for one pair)."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def _quat_matrix(pb: Any, quat: Any) -> np.ndarray:
    return np.asarray(pb.getMatrixFromQuaternion(quat), dtype=np.float64).reshape(3, 3)


# A braked joint slower than this has stopped; its brake then holds the angle
# with PyBullet's position motor (velocity target = gain x angle error / dt).
BRAKE_STOPPED_RAD_S = 1e-3
BRAKE_POSITION_GAIN = 0.1


class World:
    """The simulated scene. ``step()`` advances physics by one time step."""

    hole: HolePose  # where the plant's truth puts the hole (build_table_and_fixture)

    def __init__(
        self,
        cfg: Config,
        *,
        gui: bool = False,
        urdf_dir: Path | None = None,
        start_q: dict[str, list[float]] | None = None,
    ) -> None:
        """start_q: per robot, the joint angles to start from [rad] (default:
        the robot's initial_q_rad)."""
        import pybullet
        import pybullet_data

        self.pb = pybullet
        self.cfg = cfg
        self.dt = 1.0 / cfg.plant.physics_hz
        # the wrist sensors' electronics: a first-order low-pass (the strain
        # gauges' amplifier and anti-aliasing filter) on what read_wrist gives
        bw = cfg.plant.ft_bandwidth_hz
        self.ft_alpha = 1.0 - math.exp(-2.0 * math.pi * bw * self.dt) if bw > 0 else 1.0
        mode = pybullet.GUI if gui else pybullet.DIRECT
        self.client = pybullet.connect(mode)
        if self.client < 0:
            raise RuntimeError("PyBullet could not connect (no display for --gui?)")
        pb = self.pb
        cid = self.client
        pb.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=cid)
        pb.setGravity(0, 0, -GRAVITY, physicsClientId=cid)
        pb.setTimeStep(self.dt, physicsClientId=cid)
        self.floor = pb.loadURDF("plane.urdf", physicsClientId=cid)
        self._tmp = None
        if urdf_dir is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="redistro-urdf-")
            urdf_dir = Path(self._tmp.name)
        self.objects: dict[str, int] = {}  # the objects on the table: their bodies
        try:
            self.fixture = build_table_and_fixture(self)
            self.objects = build_objects(self)
        except BaseException:
            pb.disconnect(physicsClientId=cid)
            raise
        peg_cfg = cfg.workcell.peg
        self.arms: dict[str, Arm] = {}
        for name, rc in cfg.robots.items():
            peg = Peg(peg_cfg.side_m, peg_cfg.length_m, peg_cfg.mass_kg) if rc.peg else None
            q_start = (start_q or {}).get(name, rc.initial_q_rad)
            self.arms[name] = self._load_arm(name, write_arm_urdf(urdf_dir, name, peg), rc, q_start)
        overlap = self.overlap()
        if overlap:
            from redistro.errors import ConfigError

            self.close()
            raise ConfigError(
                f"{cfg.source}: the plant refuses a world whose bodies overlap: {overlap}"
            )

    def _load_arm(self, name: str, path: Path, rc: Any, q_start: list[float]) -> Arm:
        """One arm loaded from its URDF at its base, torque driven (the
        default velocity motors off), at ``q_start``, its wrist's sensor on."""
        pb, cid = self.pb, self.client
        body = pb.loadURDF(
            str(path),
            basePosition=rc.base_xyz_m,
            useFixedBase=True,
            flags=pb.URDF_USE_INERTIA_FROM_FILE,
            physicsClientId=cid,
        )
        infos = [self.joint_info(body, j) for j in range(pb.getNumJoints(body, cid))]
        by_name = {i.name: i for i in infos}
        joints = [by_name[n].joint for n in JOINT_NAMES]
        sensor = by_name[SENSOR_JOINT].joint
        tool_link = next(i.joint for i in infos if i.link_name == TOOL_LINK)
        dyn = pb.getDynamicsInfo(body, tool_link, physicsClientId=cid)
        pb.setJointMotorControlArray(
            body, joints, pb.VELOCITY_CONTROL, forces=[0.0] * 7, physicsClientId=cid
        )
        for j, q in zip(joints, q_start, strict=True):
            pb.resetJointState(body, j, q, 0.0, physicsClientId=cid)
        pb.enableJointForceTorqueSensor(body, sensor, True, physicsClientId=cid)
        return Arm(
            name=name,
            body=body,
            joints=joints,
            sensor_joint=sensor,
            tool_link=tool_link,
            tool_mass_kg=float(dyn[0]),
            tool_com_m=np.asarray(dyn[3], dtype=np.float64),
            braked=np.zeros(7, dtype=bool),
            brake_torque_nm=np.zeros(7),
        )

    def overlap(self, tolerance_m: float = 0.002) -> str:
        """Where a robot's base stands in another body (another arm, the
        table, the fixture), or any of its links in an object on the table,
        by more than ``tolerance_m`` ('' when none)."""
        pb, cid = self.pb, self.client
        pb.performCollisionDetection(physicsClientId=cid)
        names = list(self.arms)
        for name in names:
            arm = self.arms[name]
            others = [(f"robot {n}", self.arms[n].body) for n in names if n != name]
            others += [
                ("the table" if k == 0 else "the fixture", b) for k, b in enumerate(self.fixture)
            ]
            for what, body in others:
                points = pb.getClosestPoints(
                    arm.body, body, 0.0, linkIndexA=-1, physicsClientId=cid
                )
                deepest = min((p[8] for p in points), default=0.0)
                if deepest < -tolerance_m:
                    return f"robot {name}'s base is {-deepest * 1e3:.0f} mm inside {what}"
            for what, body in self.objects.items():  # (any link: the arm starts where it was left)
                points = pb.getClosestPoints(arm.body, body, 0.0, physicsClientId=cid)
                deepest = min((p[8] for p in points), default=0.0)
                if deepest < -tolerance_m:
                    return f"robot {name} stands {-deepest * 1e3:.0f} mm inside the object {what}"
        return ""

    # -- scene --

    # -- queries --

    def joint_info(self, body: int, j: int) -> JointInfo:
        i = self.pb.getJointInfo(body, j, physicsClientId=self.client)
        return JointInfo(i[0], i[1].decode(), i[2], i[8], i[9], i[10], i[11], i[12].decode())

    def joint_states(self, arm: Arm) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """q [rad], qd [rad/s], applied joint torque [N m] (motor or brake)."""
        q, qd, applied = np.zeros(7), np.zeros(7), np.zeros(7)
        self.read_joints(arm, q, qd, applied)
        # PyBullet reports the applied torque of a velocity-controlled joint
        # (a brake) but not of a torque-controlled one: there it keeps the last
        # velocity-control value. A released joint's torque is its motor's.
        tau = np.where(arm.braked, applied, arm.motor_tau)
        return q, qd, tau

    def joint_states_raw(self, arm: Arm) -> Any:
        """PyBullet's joint states of the arm's joints, as it returns them
        (position, velocity, reaction, applied torque per joint)."""
        return self.pb.getJointStates(arm.body, arm.joints, physicsClientId=self.client)

    def read_joints(self, arm: Arm, q: np.ndarray, qd: np.ndarray, applied: np.ndarray) -> None:
        """Into the given (7,) arrays: q [rad], qd [rad/s] and PyBullet's applied
        joint torque [N m] (only meaningful on a braked joint: see joint_states)."""
        states = self.pb.getJointStates(arm.body, arm.joints, physicsClientId=self.client)
        # JointState's order: position, velocity, reaction, applied torque
        pos, vel, _, app = zip(*states, strict=True)
        q[:] = pos
        qd[:] = vel
        applied[:] = app

    def sensor_frame(self, arm: Arm) -> tuple[np.ndarray, np.ndarray]:
        """Position [m] and rotation matrix (world from sensor) of the wrist sensor frame."""
        ls = self.pb.getLinkState(
            arm.body, arm.tool_link, computeForwardKinematics=True, physicsClientId=self.client
        )
        # link frame (not the inertial frame): world position/orientation of the URDF link frame
        return np.asarray(ls[4]), _quat_matrix(self.pb, ls[5])

    def read_wrist(self, arm: Arm, xyz: np.ndarray, rot9: np.ndarray, wrench: np.ndarray) -> None:
        """Into the given arrays: the wrist sensor frame's position [m] (3,), its
        rotation (world from sensor, row-major, (9,)), and the external wrench
        on the tool in that frame (6,) as the sensor reads it: what
        :meth:`sensor_frame` and :meth:`wrist_wrench` give, in plain floats
        (this runs every step), the wrench through the sensor's first-order
        low-pass (``plant.ft_bandwidth_hz``; ``wrench`` holds its state).

        Rigid contacts in the physics resolve an impact in one step: a peg
        that drops 0.1 mm onto an edge gives a 40-80 N reaction for 1 ms
        between steps of 6 N. A real sensor's reading is the deflection of
        its flexure, amplified and filtered before it is sampled; at 100 Hz
        that step reads 25-40 N, a sustained force 95 % of it within 5 ms."""
        pb, cid = self.pb, self.client
        ls = pb.getLinkState(
            arm.body, arm.tool_link, computeForwardKinematics=True, physicsClientId=cid
        )
        m = pb.getMatrixFromQuaternion(ls[5])
        xyz[:] = ls[4]
        rot9[:] = m
        r = pb.getJointState(arm.body, arm.sensor_joint, physicsClientId=cid)[2]
        # the tool's weight in the sensor frame: rot.T @ (0, 0, -g m) = -g m rot[2, :]
        gm = GRAVITY * arm.tool_mass_kg
        fx, fy, fz = -r[0] + gm * m[6], -r[1] + gm * m[7], -r[2] + gm * m[8]
        cx, cy, cz = arm.tool_com
        a = self.ft_alpha
        w0, w1, w2, w3, w4, w5 = wrench.tolist()
        wrench[:] = (
            w0 + a * (fx - w0),
            w1 + a * (fy - w1),
            w2 + a * (fz - w2),
            w3 + a * (-r[3] + cy * fz - cz * fy - w3),
            w4 + a * (-r[4] + cz * fx - cx * fz - w4),
            w5 + a * (-r[5] + cx * fy - cy * fx - w5),
        )

    def wrist_wrench(self, arm: Arm, rot: np.ndarray | None = None) -> np.ndarray:
        """The external wrench on the tool, in the sensor frame, about its origin
        [Fx, Fy, Fz, Mx, My, Mz] (N, N m), with the tool's own weight taken out
        (the sensor is tared with the tool on).

        PyBullet reports the fixed joint's reaction as minus the sum of the
        forces on the tool (external and weight), with the moment taken about
        the tool's centre of mass; both were checked against known forces
        (tests/integration/test_plant.py).
        """
        s = JointState(
            *self.pb.getJointState(arm.body, arm.sensor_joint, physicsClientId=self.client)
        )
        reaction = np.asarray(s.reaction, dtype=np.float64)
        if rot is None:
            _, rot = self.sensor_frame(arm)
        weight = rot.T @ np.array([0.0, 0.0, -GRAVITY * arm.tool_mass_kg])
        force = -reaction[:3] - weight
        moment = -reaction[3:] + _cross(arm.tool_com_m, force)
        return np.concatenate([force, moment])

    def contact_wrench_world(self, arm: Arm, origin: np.ndarray | None = None) -> np.ndarray:
        """Sum of PyBullet's contact forces on the tool (world frame, N), and
        their moment about the sensor origin (N m)."""
        if origin is None:
            origin, _ = self.sensor_frame(arm)
        contacts = self.pb.getContactPoints(
            bodyA=arm.body, linkIndexA=arm.tool_link, physicsClientId=self.client
        )
        if not contacts:
            return np.zeros(6)
        cps = [ContactPoint(*c) for c in contacts]
        # the normal force acts on A along the normal on B; the friction
        # directions are reported for B (measured: see the wrist test)
        normal = np.array([c.normal_force for c in cps])[:, None]
        fric1 = np.array([c.friction1 for c in cps])[:, None]
        fric2 = np.array([c.friction2 for c in cps])[:, None]
        f = (
            normal * np.array([c.normal_on_b for c in cps])
            - fric1 * np.array([c.friction_dir1 for c in cps])
            - fric2 * np.array([c.friction_dir2 for c in cps])
        )
        r = np.array([c.position_on_a for c in cps]) - origin
        return np.concatenate([f.sum(axis=0), np.cross(r, f).sum(axis=0)])

    def contact_wrench_world_into(self, arm: Arm, origin: np.ndarray, out: np.ndarray) -> None:
        """:meth:`contact_wrench_world` into ``out`` (6,), in plain floats (every step)."""
        contacts = self.pb.getContactPoints(
            bodyA=arm.body, linkIndexA=arm.tool_link, physicsClientId=self.client
        )
        if not contacts:
            out[...] = 0.0
            return
        ox, oy, oz = origin.tolist()
        fx = fy = fz = mx = my = mz = 0.0
        for c in contacts:
            # ContactPoint: position_on_a 5, normal_on_b 7, normal_force 9,
            # friction1 10, friction_dir1 11, friction2 12, friction_dir2 13
            n, f1, f2 = c[9], c[10], c[12]
            nb, d1, d2 = c[7], c[11], c[13]
            x = n * nb[0] - f1 * d1[0] - f2 * d2[0]
            y = n * nb[1] - f1 * d1[1] - f2 * d2[1]
            z = n * nb[2] - f1 * d1[2] - f2 * d2[2]
            p = c[5]
            rx, ry, rz = p[0] - ox, p[1] - oy, p[2] - oz
            fx, fy, fz = fx + x, fy + y, fz + z
            mx += ry * z - rz * y
            my += rz * x - rx * z
            mz += rx * y - ry * x
        out[...] = (fx, fy, fz, mx, my, mz)

    # -- actuation --

    def set_brakes(self, arm: Arm, engaged: np.ndarray, torque_nm: np.ndarray) -> None:
        """Engage or release brakes. An engaged brake is a friction clamp: it
        stops its joint (a zero-velocity motor up to ``torque_nm``), and once
        the joint has stopped it holds that angle (:meth:`settle_brakes`), so
        it does not creep under a steady load."""
        changed = engaged != arm.braked
        if not changed.any():
            return
        idx = [arm.joints[j] for j in np.flatnonzero(changed)]
        forces = [float(torque_nm[j]) if engaged[j] else 0.0 for j in np.flatnonzero(changed)]
        self.pb.setJointMotorControlArray(
            arm.body,
            idx,
            self.pb.VELOCITY_CONTROL,
            targetVelocities=[0.0] * len(idx),
            forces=forces,
            physicsClientId=self.client,
        )
        # in place: the chassis keeps these arrays as views of its own
        arm.braked[...] = engaged
        arm.brake_held &= engaged
        arm.brake_torque_nm[...] = torque_nm

    def settle_brakes(self, arm: Arm, q: np.ndarray, qd: np.ndarray) -> None:
        """Braked joints that have stopped are held at their angle from now on."""
        stopped = arm.braked & ~arm.brake_held & (np.abs(qd) < BRAKE_STOPPED_RAD_S)
        if not stopped.any():
            return
        js = np.flatnonzero(stopped)
        self.pb.setJointMotorControlArray(
            arm.body,
            [arm.joints[j] for j in js],
            self.pb.POSITION_CONTROL,
            targetPositions=[float(q[j]) for j in js],
            targetVelocities=[0.0] * len(js),
            forces=[float(arm.brake_torque_nm[j]) for j in js],
            positionGains=[BRAKE_POSITION_GAIN] * len(js),
            velocityGains=[1.0] * len(js),
            physicsClientId=self.client,
        )
        arm.brake_held |= stopped

    def push(self, arm: Arm, force_world: np.ndarray) -> None:
        """A force [N] (world frame) on the tool at the sensor's origin, for the
        next step only (someone pushing the peg)."""
        pos, _ = self.sensor_frame(arm)
        self.pb.applyExternalForce(
            arm.body,
            arm.tool_link,
            [float(v) for v in force_world],
            [float(v) for v in pos],
            self.pb.WORLD_FRAME,
            physicsClientId=self.client,
        )

    def set_torques(self, arm: Arm, tau_nm: np.ndarray) -> None:
        """Motor torques for the next step [N m]; a braked joint's motor is inhibited."""
        np.copyto(arm.motor_tau, np.where(arm.braked, 0.0, tau_nm))
        self.apply_motor_torques(arm)

    def apply_motor_torques(self, arm: Arm) -> None:
        """Apply ``arm.motor_tau`` (already zero on braked joints) for the next step."""
        self.pb.setJointMotorControlArray(
            arm.body,
            arm.joints,
            self.pb.TORQUE_CONTROL,
            forces=arm.motor_tau.tolist(),
            physicsClientId=self.client,
        )

    def step(self) -> None:
        self.pb.stepSimulation(physicsClientId=self.client)

    def close(self) -> None:
        import contextlib

        with contextlib.suppress(Exception):
            self.pb.disconnect(physicsClientId=self.client)
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None


def _box(
    w: World,
    half: list[float],
    pos: list[float],
    rgba: list[float],
    orn: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0),
) -> int:
    pb, cid = w.pb, w.client
    col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half, physicsClientId=cid)
    vis = pb.createVisualShape(pb.GEOM_BOX, halfExtents=half, rgbaColor=rgba, physicsClientId=cid)
    return int(
        pb.createMultiBody(
            baseMass=0,
            baseCollisionShapeIndex=col,
            baseVisualShapeIndex=vis,
            basePosition=pos,
            baseOrientation=orn,
            physicsClientId=cid,
        )
    )


def object_boxes(o: ObjectConfig) -> tuple[list[list[float]], list[list[float]]]:
    """The boxes an object is made of (half extents, centres), in its own
    frame (origin at its centre): the one box, or, with a hole in its top
    face, a floor under the hole and four walls around it."""
    sx, sy, sz = o.size_xyz_m
    if o.hole_side_m <= 0:
        return [[sx / 2, sy / 2, sz / 2]], [[0.0, 0.0, 0.0]]
    side, depth = o.hole_side_m, o.hole_depth_m
    ax, ay = o.hole_at_xy_m
    floor, zc = sz - depth, sz / 2 - depth / 2
    halves = [[sx / 2, sy / 2, floor / 2]]
    centres = [[0.0, 0.0, -sz / 2 + floor / 2]]
    for lo, hi in ((-sx / 2, ax - side / 2), (ax + side / 2, sx / 2)):  # full length in y
        halves.append([(hi - lo) / 2, sy / 2, depth / 2])
        centres.append([(lo + hi) / 2, 0.0, zc])
    for lo, hi in ((-sy / 2, ay - side / 2), (ay + side / 2, sy / 2)):  # between those
        halves.append([side / 2, (hi - lo) / 2, depth / 2])
        centres.append([ax, (lo + hi) / 2, zc])
    return halves, centres


def build_objects(w: World) -> dict[str, int]:
    """The objects of ``workcell.objects``, where the plant's truth puts
    them (:func:`redistro.plant.truth.object_pose`): boxes resting on the table."""
    from redistro.plant.truth import object_pose

    pb, cid = w.pb, w.client
    out: dict[str, int] = {}
    for name, o in w.cfg.workcell.objects.items():
        (x, y, z), yaw = object_pose(w.cfg, name)
        halves, centres = object_boxes(o)
        n = len(halves)
        col = pb.createCollisionShapeArray(
            shapeTypes=[pb.GEOM_BOX] * n, halfExtents=halves, collisionFramePositions=centres,
            physicsClientId=cid,
        )  # fmt: skip
        vis = pb.createVisualShapeArray(
            shapeTypes=[pb.GEOM_BOX] * n, halfExtents=halves, visualFramePositions=centres,
            rgbaColors=[[0.2, 0.5, 0.8, 1]] * n, physicsClientId=cid,
        )  # fmt: skip
        out[name] = int(
            pb.createMultiBody(
                baseMass=o.mass_kg,
                baseCollisionShapeIndex=col,
                baseVisualShapeIndex=vis,
                basePosition=[x, y, z],
                baseOrientation=pb.getQuaternionFromEuler([0.0, 0.0, math.radians(yaw)]),
                physicsClientId=cid,
            )
        )
    return out


def build_table_and_fixture(w: World) -> list[int]:
    """The table, and on it the fixture as drawn (``workcell.hole``) but
    where the plant's truth puts it (``plant.hole``: offset, yaw, tilt)."""
    from redistro.config.model import FIXTURE_FLOOR_M, TABLE_HALF_XY_M
    from redistro.plant.truth import hole_pose, placement_problem

    hole = w.cfg.workcell.hole
    peg = w.cfg.workcell.peg
    w.hole = truth = hole_pose(w.cfg)
    x, y, top = truth.xyz_m
    side = peg.side_m + hole.clearance_m
    depth, wall = hole.depth_m, hole.wall_m
    table_top = top - depth - FIXTURE_FLOOR_M
    problem = placement_problem(w.cfg)
    if problem:
        from redistro.errors import ConfigError

        raise ConfigError(f"{w.cfg.source}: {problem}")
    grey, steel = [0.6, 0.45, 0.3, 1], [0.5, 0.55, 0.6, 1]
    hx, hy = TABLE_HALF_XY_M
    bodies = [_box(w, [hx, hy, table_top / 2], [x, 0.0, table_top / 2], grey)]
    # the fixture: a floor plate and four walls around a square hole, in
    # the fixture's frame (origin at the mouth's centre), then placed
    orn = truth.quaternion()
    R = truth.rotation()
    centre = np.array([x, y, top])

    def place(half: list[float], local: list[float]) -> None:
        pos = centre + R @ np.asarray(local, dtype=np.float64)
        bodies.append(_box(w, half, [float(v) for v in pos], steel, orn))

    outer = side / 2 + wall
    place([outer, outer, FIXTURE_FLOOR_M / 2], [0.0, 0.0, -depth - FIXTURE_FLOOR_M / 2])
    for sx in (-1, 1):  # walls along y, full length
        place([wall / 2, outer, depth / 2], [sx * (side / 2 + wall / 2), 0.0, -depth / 2])
    for sy in (-1, 1):  # walls along x, between the others
        place([side / 2, wall / 2, depth / 2], [0.0, sy * (side / 2 + wall / 2), -depth / 2])
    return bodies

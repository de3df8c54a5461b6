"""The plant's truth: where the hole really is (the work-cell's drawn pose,
``workcell.hole``, moved by ``plant.hole``'s fixed offset and its random
draw), whether the arms touched (:class:`ArmsTruth`) and how deep a peg
went into the real hole (:class:`PegTruth`). Only the plant
and the tools that judge a run (the peg campaign, the summary, the fault
harness) use this; controller nodes never get ``plant.hole``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from redistro.config.model import FIXTURE_FLOOR_M, TABLE_HALF_XY_M, Config
from redistro.plant.in_hole import in_hole


@dataclass(frozen=True)
class HolePose:
    """The hole's real pose: its mouth's centre [m], its rotation (world from
    fixture: yaw about the axis, then the tilt), and how far both are from
    the drawn pose."""

    xyz_m: tuple[float, float, float]
    yaw_deg: float
    tilt_xy_deg: tuple[float, float]
    offset_xyz_m: tuple[float, float, float]

    @property
    def lateral_m(self) -> float:
        return math.hypot(self.offset_xyz_m[0], self.offset_xyz_m[1])

    def quaternion(self) -> tuple[float, float, float, float]:
        """x, y, z, w (PyBullet's order) of R = Rz(yaw) Ry(tilt y) Rx(tilt x)."""
        from redistro.robotmodel import quat_rpy

        rx, ry, rz = (math.radians(v) for v in (*self.tilt_xy_deg, self.yaw_deg))
        return quat_rpy(rx, ry, rz)

    def rotation(self) -> np.ndarray[Any, Any]:
        x, y, z, w = self.quaternion()
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
        )

    def as_dict(self) -> dict[str, Any]:
        return {
            "xyz_m": [round(v, 6) for v in self.xyz_m],
            "offset_xyz_m": [round(v, 6) for v in self.offset_xyz_m],
            "lateral_offset_m": round(self.lateral_m, 6),
            "yaw_deg": round(self.yaw_deg, 4),
            "tilt_xy_deg": [round(v, 4) for v in self.tilt_xy_deg],
        }


def hole_pose(cfg: Config) -> HolePose:
    """The drawn pose, the fixed offset, and the seeded draw: a lateral
    offset uniform over the disc of ``offset_radius_m`` (the ring outside
    ``offset_min_radius_m``) and a yaw uniform
    within ``yaw_range_deg``. The three numbers are always drawn, so that the
    yaw of a seed does not change with the radius."""
    t = cfg.plant.hole
    rng = np.random.default_rng(t.seed)
    u_r, u_a, u_y = (float(v) for v in rng.uniform(size=3))
    dx, dy, dz = (float(v) for v in t.offset_xyz_m)
    r0 = min(t.offset_min_radius_m, t.offset_radius_m)
    r = math.sqrt(r0 * r0 + u_r * (t.offset_radius_m**2 - r0 * r0))
    a = 2.0 * math.pi * u_a
    dx, dy = dx + r * math.cos(a), dy + r * math.sin(a)
    yaw = t.yaw_deg + t.yaw_range_deg * (2.0 * u_y - 1.0)
    x, y, z = (float(v) for v in cfg.workcell.hole.xyz_m)
    return HolePose(
        xyz_m=(x + dx, y + dy, z + dz),
        yaw_deg=yaw,
        tilt_xy_deg=(float(t.tilt_xy_deg[0]), float(t.tilt_xy_deg[1])),
        offset_xyz_m=(dx, dy, dz),
    )


def object_pose(cfg: Config, name: str) -> tuple[tuple[float, float, float], float]:
    """Where the plant puts object ``name``: (its centre [m], its yaw [deg]),
    resting on the table (which the hole's truth moves with its fixture)."""
    from redistro.config.model import ObjectTruth, table_top_m

    o = cfg.workcell.objects[name]
    t = cfg.plant.objects.get(name, ObjectTruth())
    top = table_top_m(cfg.workcell.hole, hole_pose(cfg).offset_xyz_m[2])
    x, y = (float(a) + float(b) for a, b in zip(o.xy_m, t.offset_xy_m, strict=True))
    return (x, y, top + o.size_xyz_m[2] / 2), o.yaw_deg + t.yaw_deg


BASE_RADIUS_M = 0.12  # an arm's base link, as a cylinder about its axis


def placement_problem(cfg: Config) -> str:
    """Why the plant cannot build the work-cell of ``cfg`` ('' when it can):
    the hole (where its truth puts it) needs a table under its fixture, and
    no arm's base may stand in the table."""
    hole = cfg.workcell.hole
    x, _, top = hole_pose(cfg).xyz_m
    table_top = top - hole.depth_m - FIXTURE_FLOOR_M
    if table_top <= 0.01:
        return (
            f"workcell.hole.xyz_m: the hole's mouth at z={top:.3f} m (plant.hole included) leaves "
            f"no room for the table under a {hole.depth_m} m deep fixture"
        )
    hx, hy = TABLE_HALF_XY_M
    for name, rc in cfg.robots.items():
        bx, by, bz = rc.base_xyz_m
        dx = max(abs(bx - x) - hx, 0.0)
        dy = max(abs(by) - hy, 0.0)
        if (dx * dx + dy * dy) ** 0.5 < BASE_RADIUS_M and bz < table_top:
            return (
                f"robots.{name}.base_xyz_m: the base at {[round(v, 3) for v in rc.base_xyz_m]} "
                f"stands in the table under the hole (x {x - hx:.2f}..{x + hx:.2f} m, "
                f"y {-hy:.2f}..{hy:.2f} m)"
            )
    return ""


class ArmsTruth:
    """Did two arms touch, and how near did they come? PyBullet's own
    view, sampled in the plant's loop: every ``TOUCH_EVERY`` steps the
    contacts of the last step between each two arms (touching: a contact
    at distance <= 0), every ``NEAR_EVERY`` steps their closest points
    within ``NEAR_M``."""

    TOUCH_EVERY = 8
    NEAR_EVERY = 64
    NEAR_M = 0.3

    def __init__(self, world: Any) -> None:
        self.pb, self.cid = world.pb, world.client
        bodies = [arm.body for arm in world.arms.values()]
        self.pairs = [(a, b) for i, a in enumerate(bodies) for b in bodies[i + 1 :]]
        self.min_m = math.inf  # the least distance seen (inf: never within NEAR_M)
        self.touched_step = 0  # the first step at which two arms touched (0: never)

    def sample(self, step: int) -> None:
        if step % self.TOUCH_EVERY:
            return
        pb, cid = self.pb, self.cid
        near = not step % self.NEAR_EVERY
        for a, b in self.pairs:
            points = pb.getContactPoints(a, b, physicsClientId=cid)
            if near:
                points = points + pb.getClosestPoints(a, b, self.NEAR_M, physicsClientId=cid)
            for p in points:
                d = float(p[8])  # contactDistance [m] (negative: through each other)
                self.min_m = min(self.min_m, d)
                if d <= 0.0 and not self.touched_step:
                    self.touched_step = step

    def report(self) -> dict[str, Any]:
        return {
            "min_distance_m": round(self.min_m, 4) if math.isfinite(self.min_m) else None,
            "touched": bool(self.touched_step),
            "touched_at_step": self.touched_step,
        }


class PegTruth:
    """How deep each peg's tip went into the real hole: every
    ``EVERY`` steps the tip (the tool frame's origin, the flange face, plus
    the peg's length along its axis) in the hole's frame; a tip within the
    hole's mouth (laterally inside its square) counts, and the deepest one
    is kept. PyBullet's link state, the plant's own view."""

    EVERY = 8

    def __init__(self, world: Any) -> None:
        self.pb, self.cid = world.pb, world.client
        cfg = world.cfg
        hole = world.hole
        self.mouth = np.asarray(hole.xyz_m, dtype=np.float64)
        self.R = hole.rotation()  # world from the hole's frame (its z: out of the hole)
        self.half = (cfg.workcell.peg.side_m + cfg.workcell.hole.clearance_m) / 2
        length = cfg.workcell.peg.length_m
        self.pegs = [
            (name, arm.body, arm.tool_link, length)
            for name, arm in world.arms.items()
            if cfg.robots[name].peg
        ]
        self.depth = {name: 0.0 for name, *_ in self.pegs}  # the deepest [m]

    def sample(self, step: int) -> None:
        if step % self.EVERY:
            return
        pb = self.pb
        for name, body, link, length in self.pegs:
            state = pb.getLinkState(
                body, link, computeForwardKinematics=True, physicsClientId=self.cid
            )
            pos, quat = np.asarray(state[4]), state[5]
            axis = np.asarray(pb.getMatrixFromQuaternion(quat)).reshape(3, 3)[:, 2]
            tip = self.R.T @ (pos + length * axis - self.mouth)  # in the hole's frame
            if abs(tip[0]) <= self.half and abs(tip[1]) <= self.half and -tip[2] > self.depth[name]:
                self.depth[name] = float(-tip[2])

    def report(self) -> dict[str, Any]:
        return {name: {"depth_m": round(d, 6)} for name, d in self.depth.items()}


class ObjectsInHoles:
    """How deep each object went into another's hole: for every object
    with a hole and every other whose footprint fits it, every ``EVERY``
    steps the pair's poses (PyBullet's, the plant's own view) through
    :func:`~redistro.plant.in_hole.in_hole`; a bottom laterally inside the
    hole counts, and the deepest is kept."""

    EVERY = 8

    def __init__(self, world: Any) -> None:
        self.pb, self.cid = world.pb, world.client
        objs, bodies = world.cfg.workcell.objects, world.objects
        self.pairs = [
            (peg, hole, objs[peg], objs[hole], bodies[peg], bodies[hole])
            for hole, h in objs.items()
            if h.hole_side_m > 0 and hole in bodies
            for peg, p in objs.items()
            if peg != hole and peg in bodies and max(p.size_xyz_m[:2]) < h.hole_side_m
        ]
        self.depth = {peg: (hole, 0.0) for peg, hole, *_ in self.pairs}

    def sample(self, step: int) -> None:
        if step % self.EVERY or not self.pairs:
            return
        pose = self.pb.getBasePositionAndOrientation
        for peg, hole, p_cfg, h_cfg, p_body, h_body in self.pairs:
            p_xyz, p_q = pose(p_body, physicsClientId=self.cid)
            h_xyz, h_q = pose(h_body, physicsClientId=self.cid)
            got = in_hole(
                p_cfg, {"xyz_m": p_xyz, "quat_xyzw": p_q}, h_cfg, {"xyz_m": h_xyz, "quat_xyzw": h_q}
            )
            if got["inside"] and float(got["depth_m"]) > self.depth[peg][1]:
                self.depth[peg] = (hole, float(got["depth_m"]))

    def report(self) -> dict[str, Any]:
        return {p: {"hole_of": h, "depth_m": round(d, 6)} for p, (h, d) in self.depth.items()}

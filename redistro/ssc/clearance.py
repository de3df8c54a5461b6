"""Do the arms keep apart? Checked before anything starts, and in every SSC cycle.

Every segment's planned motion is sampled: a joint move along its straight
line in joint space, a Cartesian move (position, force) along the TCP's
straight line and rotation, each sample solved by inverse kinematics from
the one before (:mod:`redistro.ssc.reach`), while every other robot holds
where it is. At each sample the arms' collision geometry (each link's mesh
from the URDF, through Pinocchio's geometry model, as its convex hull:
coal's GJK) must keep every link of one arm at least ``MIN_CLEARANCE_M``
from every link of another, and every link but the tool from the fixed
work-cell as drawn (the table, the fixture's block: the task puts the tool
into the fixture). The first sample closer than that is refused
with the segment, the time and the two links named.

Samples: one per ``STEP_RAD`` of the largest joint's travel (a Cartesian
move: per ``STEP_M`` of the TCP's path), at least one per move and its end;
a sample's time is where the move's quintic profile reaches it.

In every SSC cycle (:class:`ClearanceWatch`) the measured arms are held to
``TRIP_M``: closer than that, the SSC asks for the group's e-stop before
the links touch. A pair of links cannot close faster than the joints'
speed limits let them (``esc.safety.qd_max_rad_s``: past them an ESC's
guard stops its robot): each link's points move at most at the sum over
the joints before it of the joint's limit times the link's reach from
that joint. A pair measured ``d`` apart at ``t`` therefore stays over
``TRIP_M`` until ``t + (d - TRIP_M) / v``, and each cycle measures (GJK on
the hulls) only the pairs due before the next one: all of them in the
first cycle, then the near ones often and the far ones seldom. Each pair
comes due early by its own fraction (``EARLY``, spread over the pairs), so
the pairs measured together at the start do not stay due together.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from redistro.config.model import MIN_CLEARANCE_M, TRIP_M, Config
from redistro.config.task import Task

GJK_GAP_M = 1e-5  # a measured distance is within this of the true one
ALL_AT = 16  # more pairs due than this: every pair measured in one call
EARLY = 0.5  # a pair comes due early by up to this share of its time
STOP_S = 0.03  # a sample's age, the e-stop's way to the robots and their brakes [s]
RATE_S = 0.05  # a pair measured again within this: its closing speed is known [s]
STEP_RAD = 0.0125  # joint-space sampling (a point 0.8 m out moves 1 cm)
STEP_M = 0.01  # Cartesian sampling (the TCP's path)


@dataclass
class Closest:
    """The closest pair (two arms' links, or a link and the work-cell) at one configuration."""

    distance_m: float
    links: tuple[str, str]  # "r1 lbr_iiwa_link_5", "r2 lbr_iiwa_link_6"
    ahead_m: float = math.nan  # (the watch) where they will be once the group has stopped


class GroupGeometry:
    """The robots' collision geometry in one Pinocchio model (each arm at
    its base) and the work-cell's boxes, with the pairs to measure: every
    two links of two different arms, every link and a work-cell box."""

    def __init__(self, cfg: Config, robots: list[str]) -> None:
        import coal
        import pinocchio as pin

        from redistro.robotmodel import arm_urdf
        from redistro.ssc.reach import arm_tool

        self._pin = pin
        model, geom = pin.Model(), pin.GeometryModel()
        self.offsets: dict[str, int] = {}  # each robot's first index in q
        for r in robots:
            rc = cfg.robots[r]
            text, meshes = _placeholders(arm_urdf(arm_tool(cfg, r)))
            m = pin.buildModelFromXML(text)
            g = pin.buildGeomFromUrdfString(m, text, pin.GeometryType.COLLISION)
            for i in range(1, m.njoints):  # one model holds every arm: names apart
                m.names[i] = f"{r} {m.names[i]}"
            for i in range(m.nframes):
                f = m.frames[i]
                f.name = f"{r} {f.name}"
                m.frames[i] = f
            for go in g.geometryObjects:
                mesh = meshes.get(go.name)
                if mesh is not None:  # GJK on the mesh's hull
                    go.geometry = _mesh_hull(*mesh)
                go.name = f"{r} {go.name.rsplit('_', 1)[0]}"
            base = pin.SE3(np.eye(3), np.asarray(rc.base_xyz_m, dtype=np.float64))
            self.offsets[r] = model.nq
            model, geom = pin.appendModel(model, m, geom, g, 0, base)
        for name, half, centre in workcell_boxes(cfg):
            box = coal.Box(*(2 * np.asarray(half)))
            where = pin.SE3(np.eye(3), np.asarray(centre, dtype=np.float64))
            geom.addGeometryObject(pin.GeometryObject(f"workcell {name}", 0, 0, where, box))
        objs = [go.name for go in geom.geometryObjects]
        owner = [n.split(" ", 1)[0] for n in objs]
        arms: list[tuple[int, int]] = []  # (the pairs of two arms first, then the work-cell)
        cell: list[tuple[int, int]] = []
        for i in range(len(owner)):
            for j in range(i + 1, len(owner)):
                if owner[i] != owner[j] and not _meant_to_touch(objs[i], objs[j]):
                    (cell if "workcell" in (owner[i], owner[j]) else arms).append((i, j))
        for i, j in arms + cell:
            geom.addCollisionPair(pin.CollisionPair(i, j))
        self.n_arms = len(arms)  # pairs [0, n_arms): two arms' links
        self.model, self.geom = model, geom
        self.data = model.createData()
        self.gdata = pin.GeometryData(geom)
        # GJK run to a duality gap under 10 um: coal's default criterion
        # stopped up to 6 mm over the distance on these hulls (over: unsafe)
        for req in self.gdata.distanceRequests:
            req.gjk_convergence_criterion = coal.GJKConvergenceCriterion.DualityGap
            req.gjk_convergence_criterion_type = coal.GJKConvergenceCriterionType.Absolute
            req.gjk_tolerance = GJK_GAP_M
        self.q = pin.neutral(model)

    def closest(self, qs: dict[str, np.ndarray]) -> Closest:
        """The two closest links of different arms at the robots' postures."""
        pin = self._pin
        for r, q in qs.items():
            k = self.offsets[r]
            self.q[k : k + 7] = q
        pin.computeDistances(self.model, self.data, self.geom, self.gdata, self.q)
        best, at = math.inf, 0
        for k, res in enumerate(self.gdata.distanceResults):
            if res.min_distance < best:
                best, at = res.min_distance, k
        pair = self.geom.collisionPairs[at]
        objs = self.geom.geometryObjects
        return Closest(float(best), (objs[pair.first].name, objs[pair.second].name))


def _path(model: Any, q0: np.ndarray, pose: np.ndarray, lo: Any, hi: Any) -> list[np.ndarray]:
    """Postures along the TCP's straight line from its pose at ``q0`` to
    ``pose`` (position + rotation vector), each solved from the one before
    (a sample no posture reaches ends the path: the reach check names it)."""
    from redistro.control.cartesian import matrix_to_rotvec, rotvec_to_matrix
    from redistro.ssc.reach import solve

    k = model.kinematics(q0)
    p0, R0 = k.p, k.R
    p1, R1 = np.asarray(pose[:3], dtype=np.float64), rotvec_to_matrix(np.asarray(pose[3:]))
    w = matrix_to_rotvec(R0.T @ R1)  # the rotation to make, in the tool's frame
    n = max(1, math.ceil(float(np.linalg.norm(p1 - p0)) / STEP_M))
    out, q = [], q0
    for i in range(1, n + 1):
        f = i / n
        rot = matrix_to_rotvec(R0 @ rotvec_to_matrix(f * w))
        target = np.concatenate([p0 + f * (p1 - p0), rot])
        ok, _, qf = solve(model, target, [q], lo, hi)
        if not ok or qf is None:
            break
        out.append(qf)
        q = qf
    return out


def _time_at(fraction: float, move_s: float) -> float:
    """When the move's quintic profile (control/trajectory.py) reaches ``fraction``."""
    from redistro.control.trajectory import quintic

    zero, one = np.zeros(1), np.ones(1)
    lo, hi = 0.0, 1.0
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        if quintic(zero, one, 1.0, mid)[0][0] < fraction:
            lo = mid
        else:
            hi = mid
    return hi * move_s


def _joint_path(q0: np.ndarray, q1: np.ndarray) -> list[np.ndarray]:
    n = max(1, math.ceil(float(np.max(np.abs(q1 - q0))) / STEP_RAD))
    return [q0 + (i / n) * (q1 - q0) for i in range(1, n + 1)]


def clearance_problems(cfg: Config, task: Task, start_q: dict[str, list[float]]) -> list[str]:
    """One line for the first sample of the task's motion where an arm comes
    closer than MIN_CLEARANCE_M to another or to the work-cell (empty: they
    keep apart)."""
    if task.kind != "strategy":
        return []
    from redistro.config.limits import joint_limits
    from redistro.ssc.plan import segment_plans
    from redistro.ssc.reach import arm_model

    limits = joint_limits(cfg)
    group = GroupGeometry(cfg, list(task.robots))
    q: dict[str, np.ndarray] = {
        r: np.asarray(start_q.get(r, cfg.robots[r].initial_q_rad), dtype=np.float64)
        for r in task.robots
    }
    models: dict[str, Any] = {}
    for i, (seg, plan) in enumerate(zip(task.segments, segment_plans(task, cfg), strict=True)):
        paths: dict[str, list[np.ndarray]] = {}
        for mv in plan.moves:
            r = mv.robot
            if mv.scheme == "joint":
                paths[r] = _joint_path(q[r], mv.q_goal)
            else:
                model = arm_model(cfg, r, models)
                paths[r] = _path(model, q[r], mv.pose, limits.inner_lower, limits.inner_upper)
        # the moves share one clock (one quintic over move_s): the same
        # share of each path at the same time
        n = max((len(p) for p in paths.values()), default=0)
        for k in range(n):
            at = {r: p[math.ceil((k + 1) * len(p) / n) - 1] for r, p in paths.items() if p}
            c = group.closest({**q, **at})
            if c.distance_m < MIN_CLEARANCE_M:
                t = _time_at((k + 1) / n, plan.move_s)
                gap = (
                    f"come {c.distance_m * 100:.1f} cm apart"
                    if c.distance_m >= 0
                    else f"overlap by {-c.distance_m * 100:.1f} cm"
                )
                return [
                    f"{task.source}: segments[{i}] ({seg.name}) at t={t:.2f} s: {c.links[0]} "
                    f"and {c.links[1]} {gap} (at least {MIN_CLEARANCE_M * 100:.0f} cm apart)"
                ]
        for r, p in paths.items():
            if p:
                q[r] = p[-1]
    return []


def workcell_boxes(cfg: Config) -> list[tuple[str, list[float], list[float]]]:
    """The fixed work-cell as drawn (``workcell.hole``; the plant builds the
    same drawing where ``plant.hole`` moves it): (name, half extents,
    centre) of the table and of the fixture's outer block [m]."""
    from redistro.config.model import FIXTURE_FLOOR_M, TABLE_HALF_XY_M

    hole, peg = cfg.workcell.hole, cfg.workcell.peg
    x, y, top = (float(v) for v in hole.xyz_m)
    table_top = top - hole.depth_m - FIXTURE_FLOOR_M
    outer = (peg.side_m + hole.clearance_m) / 2 + hole.wall_m
    block = (hole.depth_m + FIXTURE_FLOOR_M) / 2
    return [
        ("table", [*TABLE_HALF_XY_M, table_top / 2], [x, 0.0, table_top / 2]),
        ("fixture", [outer, outer, block], [x, y, top - block]),
    ]


def _meant_to_touch(a: str, b: str) -> bool:
    """A tool and the work-cell: a task puts the peg into the fixture, its
    tip 1 cm over the table at the bottom (a tool's contacts there are the
    force law's and the guard's, which limits the wrist's force)."""
    return a.endswith(" tool") and b.startswith("workcell ")


def _placeholders(urdf: str) -> tuple[str, dict[str, tuple[str, tuple[float, ...]]]]:
    """The URDF with each collision mesh a point-sized sphere (Pinocchio
    places it; its hull replaces it), and each such geometry's (mesh file,
    scale) by the name Pinocchio gives it (``<link>_<k>``, k the link's
    collision). Loading the meshes themselves (their bounding-volume
    trees, unused here) was 60 of the model's 120 ms."""
    import xml.etree.ElementTree as ET

    root = ET.fromstring(urdf)
    meshes: dict[str, tuple[str, tuple[float, ...]]] = {}
    for link in root.iter("link"):
        for k, col in enumerate(link.iter("collision")):
            geo = col.find("geometry")
            mesh = None if geo is None else geo.find("mesh")
            if geo is None or mesh is None:
                continue
            scale = tuple(float(v) for v in mesh.get("scale", "1 1 1").split())
            meshes[f"{link.get('name')}_{k}"] = (str(mesh.get("filename")), scale)
            geo.remove(mesh)
            ET.SubElement(geo, "sphere", radius="0.001")
    return ET.tostring(root, encoding="unicode"), meshes


STL_TRIANGLE = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])


def mesh_vertices(path: str, scale: tuple[float, ...] = (1.0, 1.0, 1.0)) -> np.ndarray:
    """A mesh file's distinct vertices, scaled [m] (n x 3): a binary STL
    read here (its 50-byte triangles), any other file through coal's
    loader (assimp)."""
    raw = Path(path).read_bytes()
    n = int.from_bytes(raw[80:84], "little") if len(raw) >= 84 else -1
    if n >= 0 and len(raw) == 84 + STL_TRIANGLE.itemsize * n and not raw.startswith(b"solid"):
        v = np.ascontiguousarray(np.frombuffer(raw, STL_TRIANGLE, n, 84)["v"].reshape(-1, 3))
        v = np.unique(v.view(np.dtype((np.void, 12))).ravel()).view("<f4").reshape(-1, 3)
    else:
        import coal

        v = np.asarray(coal.MeshLoader().load(path, np.ones(3)).vertices())
    return np.asarray(v, dtype=np.float64) * np.asarray(scale, dtype=np.float64)


@functools.cache
def _mesh_hull(path: str, scale: tuple[float, ...]) -> Any:
    """A mesh file's hull (:func:`_hull`), made once a process and shared
    by every model (the meshes ship with the package)."""
    import coal

    return _hull(coal, mesh_vertices(path, scale))


def _hull(coal: Any, vertices: np.ndarray) -> Any:
    """The convex hull of a mesh's vertices, with its hull vertices alone
    (qhull): GJK's support search climbs the hull's edges, and the mesh's
    inner vertices (kept by coal's own conversion) stopped it short,
    overstating the distance by up to 14 cm."""
    points = coal.StdVec_Vec3s()
    points.extend(vertices)
    return coal.Convex.convexHull(points, False, "")


class ClearanceWatch:
    """The measured arms' clearance, in every SSC cycle (see the module's text)."""

    def __init__(self, cfg: Config, robots: list[str], period_s: float) -> None:
        import pinocchio as pin

        self._pin = pin
        g = self.group = GroupGeometry(cfg, robots)
        self.slices = [slice(g.offsets[r], g.offsets[r] + 7) for r in robots]
        qd_max = np.asarray(cfg.esc.safety.qd_max_rad_s, dtype=np.float64)
        speed = [_link_speed(g.model, go, qd_max) for go in g.geom.geometryObjects]
        pairs = list(g.geom.collisionPairs)
        # each pair's closing speed bound [m/s], last measured distance [m]
        # and when it was measured (task time) [s] (Python floats: a cycle
        # touches a few)
        self.v = [speed[p.first] + speed[p.second] + 1e-9 for p in pairs]
        n = len(pairs)
        # each pair's share of its time to come due, early by 0-EARLY
        # (spread by the golden ratio: never late, and not all at once)
        self.share = [1.0 - EARLY * ((k * 0.6180339887) % 1.0) for k in range(n)]
        self.d = [math.inf] * n
        self.at = [-math.inf] * n
        self.rate = [0.0] * n  # each pair's closing speed, as last measured [m/s]
        self.due = np.full(n, -np.inf)  # when each must be measured again (task time) [s]
        self.period = period_s
        self.measured = 0  # pair measurements made
        self.cycles = 0  # cycles that measured any
        self.closest = math.inf  # the least distance measured [m]
        # as last measured, the nearest two arms' links and the nearest link
        # to the work-cell [m], and which pair each is
        self.arms_m = self.cell_m = math.inf
        self.arms_k = self.cell_k = -1
        # once at the configured postures, in Initialization: the first
        # measurement's one-time costs (about 0.6 ms) stay out of the cycles
        self.check([np.asarray(cfg.robots[r].initial_q_rad, dtype=np.float64) for r in robots], 0.0)
        self.d[:], self.at[:], self.due[:] = [math.inf] * n, [-math.inf] * n, -np.inf
        self.rate[:] = [0.0] * n
        self.measured, self.cycles, self.closest = 0, 0, math.inf
        self.arms_m = self.cell_m = math.inf
        self.arms_k = self.cell_k = -1

    def check(self, qs: list[np.ndarray], t: float) -> Closest | None:
        """The arms at ``qs`` (each robot's measured joints), sampled at task
        time ``t`` [s]: the pair that is, or at the speed it closes will be
        once the group has stopped (``STOP_S`` on), under TRIP_M; else None."""
        due = np.flatnonzero(self.due <= t)
        if due.size == 0:
            return None
        g, pin = self.group, self._pin
        for sl, q in zip(self.slices, qs, strict=True):
            g.q[sl] = q
        pin.updateGeometryPlacements(g.model, g.data, g.geom, g.gdata, g.q)
        d, at, v, when, share, rate = self.d, self.at, self.v, self.due, self.share, self.rate
        results = None
        if due.size > ALL_AT:  # (the first cycle: every pair, in one call)
            pin.computeDistances(g.geom, g.gdata)
            results = g.gdata.distanceResults
        worst, hit, nearest = math.inf, -1, math.inf
        na, regrown = g.n_arms, False
        for k in due.tolist():
            res = results[k] if results is not None else pin.computeDistance(g.geom, g.gdata, k)
            now, since = res.min_distance, t - at[k]
            if since > 0:  # (at the same sample time, as when the plant's
                # clock stalls: the closing speed measured last holds, and
                # the next one is read from the sample before)
                rate[k] = max(0.0, d[k] - now) / since if since <= RATE_S else 0.0
                d[k], at[k] = now, t
            when[k] = t + share[k] * (now - TRIP_M) / v[k] - self.period
            nearest = min(nearest, now)
            # the nearest of each kind: kept as pairs come in; looked for
            # again only when the pair that was nearest moved away
            if k < na:
                if now <= self.arms_m:
                    self.arms_m, self.arms_k = now, k
                elif k == self.arms_k:
                    regrown = True
            elif now <= self.cell_m:
                self.cell_m, self.cell_k = now, k
            elif k == self.cell_k:
                regrown = True
            # where it will be once the group has stopped, closing as it
            # did since it was last measured (if lately: a near pair)
            ahead = now - rate[k] * STOP_S
            if ahead < worst:
                worst, hit = ahead, k
        self.measured += due.size
        self.cycles += 1
        self.closest = min(self.closest, nearest)
        if regrown:
            self._regrow(na)
        if worst >= TRIP_M:
            return None
        pair = g.geom.collisionPairs[hit]
        objs = g.geom.geometryObjects
        return Closest(float(d[hit]), (objs[pair.first].name, objs[pair.second].name), worst)

    def _regrow(self, na: int) -> None:
        """The nearest pairs looked for again over every pair's last measure."""
        self.arms_m, self.arms_k = _nearest(self.d, 0, na)
        self.cell_m, self.cell_k = _nearest(self.d, na, len(self.d))


def _nearest(d: list[float], lo: int, hi: int) -> tuple[float, int]:
    """The least of d[lo:hi] and its index (inf, -1: none)."""
    if hi <= lo:
        return math.inf, -1
    m = min(d[lo:hi])
    return m, d.index(m, lo, hi)


def _link_speed(model: Any, go: Any, qd_max: np.ndarray) -> float:
    """The fastest any point of ``go`` can move at the joints' speed limits
    [m/s]: over the joints before it, each limit times the point's reach
    from that joint (its link's bound from the joint's origin, plus the
    joint offsets between)."""
    geo = go.geometry
    geo.computeLocalAABB()
    centre = go.placement.translation + go.placement.rotation @ np.asarray(geo.aabb_center)
    reach = float(np.linalg.norm(centre)) + float(geo.aabb_radius)
    speed, j = 0.0, int(go.parentJoint)
    while j > 0:
        speed += float(qd_max[model.joints[j].idx_v % 7]) * reach
        reach += float(np.linalg.norm(model.jointPlacements[j].translation))
        j = int(model.parents[j])
    return speed

"""What the SSC needs from a task: per segment, the robots it moves, each with a
scheme and its goal in numbers."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from redistro.config.loader import resolved
from redistro.config.model import Config, controller_view
from redistro.config.skills import skill_of
from redistro.config.task import Carry, Move, MoveSegment, Search, Task, move_s, segment_moves
from redistro.errors import ConfigError
from redistro.process.plan import worker_specs
from redistro.process.spec import NodeParams, NodeSpec

SCHEMES = {"hold": 0, "joint": 1, "position": 2, "force": 3}
# Within an SSC cycle: the worker computes the commands, then the logger records them.
# The logger drains the log ring the manager fills at every tick, off the
# cycle on its own timer (log.drain_hz): nothing in the cycle waits for it.
SSC_WORKERS = (("worker", 0), ("logger", -1), ("ddm", -1))
# ssc.parallel_arms: a worker per robot ("arm.<robot>", each that robot's
# law, all in stage 0, in parallel), then the worker in stage 1: the task's
# clock (segments, end conditions, the arms' clearance) for the next cycle
PARALLEL_WORKERS = (("worker", 1), ("logger", -1), ("ddm", -1))


@dataclass(frozen=True)
class MovePlan:
    """One robot's move in a segment, its goal in numbers."""

    robot: str
    scheme: str
    move_s: float
    q_goal: np.ndarray[Any, Any]  # joint goal [rad] (joint scheme)
    pose: np.ndarray[Any, Any]  # TCP goal: position [m] + rotation vector [rad], world
    force: np.ndarray[Any, Any]  # goal wrench the tool applies, task axes
    selection: np.ndarray[Any, Any]
    frame: str
    pose_within_m: float
    rot_within_rad: float
    force_within_n: float
    hold_s: float
    search: Search
    mouth_z_m: float  # the TCP's height with the tool's tip at the hole's mouth, as believed [m]
    hole_depth_m: float  # the hole's depth as drawn [m]
    mouth_xy_m: tuple[float, float] = (0.0, 0.0)  # the mouth's centre, as believed [m, world]
    hole_half_m: float = 0.0  # half the hole's side [m]
    name: str = ""  # the segment's
    duration_s: float = 0.0  # the segment's
    skill: str = "move"  # (config/skills.py)
    contact_n: float = 0.0  # a guarded move's contact [N]: it ends there
    gripper: str = ""  # at the move's end the gripper closes ("close") or opens ("open")
    where: str = ""  # the task file's field, for messages
    # a goal relative to an object another hand holds (ssc/follow.py): that
    # robot, its pose goal and the goal's frame's origin, as planned
    follows: str = ""
    holder_pose: np.ndarray[Any, Any] | None = None
    follow_point: np.ndarray[Any, Any] | None = None
    stiffness: tuple[float, ...] = ()  # the impedance's for this move ((): ssc.impedance.k)

    @property
    def ends_early(self) -> bool:
        return self.hold_s > 0 or self.contact_n > 0


@dataclass(frozen=True)
class SegmentPlan:
    """A segment: the moves of the robots it moves (the others hold), one clock."""

    name: str
    duration_s: float
    move_s: float  # every move's (they start and end together)
    moves: tuple[MovePlan, ...]  # (a robot whose skill is hold has none)
    until: str = "all"  # its early end: every move's end conditions met, or any one's
    carry: Carry | None = None  # two carry moves: the held object's motion
    carry_mass_kg: float = 0.0  # (the object's, as drawn)

    def move_of(self, robot: str) -> MovePlan | None:
        for m in self.moves:
            if m.robot == robot:
                return m
        return None

    @property
    def robots(self) -> list[str]:
        return [m.robot for m in self.moves]


def segment_plans(task: Task, cfg: Config) -> list[SegmentPlan]:
    """The task's segments with goals resolved (relative poses made absolute)."""
    frames = frames_of(cfg)
    out = []
    last: dict[str, np.ndarray[Any, Any]] = {}  # each robot's last pose goal
    held = Held(frames, {n: o.size_xyz_m[2] for n, o in cfg.workcell.objects.items()})
    for i, s in enumerate(task.segments):
        listed = [m for m in segment_moves(s, i) if skill_of(m).name != "hold"]
        carry = s.carry if s.carry.object else None
        # a hand holding an object moves first: the goals relative to that
        # object are where this segment's move takes it
        listed.sort(key=lambda m: not held.holds(m.robot))
        plans: dict[str, MovePlan] = {}
        for m in listed:
            mv = _move(s, m, frames, _hole_of(cfg, m, frames, held))
            plans[m.robot] = mv = held.follow(m, mv)
            if mv.scheme != "joint" and not np.all(np.isfinite(mv.pose[:3])):
                raise ConfigError(
                    f"{task.source}: {m.where}.goal.relative_to: where "
                    f"{m.goal.relative_to} is, the plan does not know (the hand holding it "
                    "made a joint move since the grasp)"
                )
            if carry is None:
                held.moved(mv)
        moves = tuple(plans[m.robot] for m in segment_moves(s, i) if m.robot in plans)
        if carry is not None:
            moves = _carry_goals(carry, moves, last, f"{task.source}: segments[{i}]")
            for mv in moves:
                held.moved(mv)
        for m in listed:
            held.gripped(m, next(x for x in moves if x.robot == m.robot))
        for mv in moves:
            if mv.scheme == "joint":
                last.pop(mv.robot, None)
            else:
                last[mv.robot] = mv.pose
        move_s = moves[0].move_s if moves else 0.0  # (the same for every move)
        mass = cfg.workcell.objects[carry.object].mass_kg if carry is not None else 0.0
        out.append(SegmentPlan(s.name, s.duration_s, move_s, moves, s.until, carry, mass))
    return out


def carried(
    carry: Carry, p: list[np.ndarray[Any, Any]], R: list[np.ndarray[Any, Any]], s: float = 1.0
) -> tuple[list[np.ndarray[Any, Any]], list[np.ndarray[Any, Any]]]:
    """Where a carry takes the hands at ``p``, ``R`` (world), ``s`` of the way
    (0..1): the object moved by ``s`` of ``move_xyz_m`` and turned by ``s`` of
    ``turn_deg`` about the world's z through the point between the hands."""
    import math

    a = math.radians(carry.turn_deg) * s
    c, sn = math.cos(a), math.sin(a)
    Rz = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
    mid = (p[0] + p[1]) / 2
    d = np.asarray(carry.move_xyz_m, dtype=np.float64) * s
    return [mid + d + Rz @ (pi - mid) for pi in p], [Rz @ Ri for Ri in R]


def _carry_goals(
    carry: Carry,
    moves: tuple[MovePlan, ...],
    last: dict[str, np.ndarray[Any, Any]],
    at: str,
) -> tuple[MovePlan, ...]:
    """The carry's goals as planned: from the hands' last pose goals (where
    the grasps put them; the SSC takes them from the measured poses)."""
    from redistro.control.cartesian import matrix_to_rotvec, rotvec_to_matrix

    missing = [mv.robot for mv in moves if mv.robot not in last]
    if missing:
        raise ConfigError(
            f"{at}.carry: {', '.join(missing)} has no pose goal before it (a carry follows "
            "a grasp under scheme position)"
        )
    p = [last[mv.robot][:3] for mv in moves]
    R = [rotvec_to_matrix(last[mv.robot][3:]) for mv in moves]
    p2, R2 = carried(carry, p, R)
    grip = "open" if carry.release else ""
    return tuple(
        dataclasses.replace(mv, pose=np.concatenate([pi, matrix_to_rotvec(Ri)]), gripper=grip)
        for mv, pi, Ri in zip(moves, p2, R2, strict=True)
    )


def frames_of(cfg: Config) -> dict[str, np.ndarray[Any, Any]]:
    """The origins a goal may be relative to, as drawn: the world's, the
    hole's mouth centre, each object's top-face centre, and the mouth of
    an object's hole (``<object>.hole``)."""
    import math

    from redistro.config.model import table_top_m

    top = table_top_m(cfg.workcell.hole)
    out = {
        "world": np.zeros(3),
        "hole": np.asarray(cfg.workcell.hole.xyz_m, dtype=np.float64),
    }
    for name, o in cfg.workcell.objects.items():
        out[name] = np.array([o.xy_m[0], o.xy_m[1], top + o.size_xyz_m[2]], dtype=np.float64)
        if o.hole_side_m:
            c, s = math.cos(math.radians(o.yaw_deg)), math.sin(math.radians(o.yaw_deg))
            ax, ay = o.hole_at_xy_m
            out[f"{name}.hole"] = out[name] + np.array([c * ax - s * ay, s * ax + c * ay, 0.0])
    return out


class Held:
    """The objects the task's grasps put in a hand, as planned: once a move
    grasps an object (skill grasp, its goal relative to the object), the
    object's own frames (``<object>.hole``) go with that hand's later pose
    goals (kept in the tool's frame at the grasp), until a move of that
    hand opens the gripper; a joint move of the holding hand leaves them
    unknown to the plan. ``<object>`` itself stays the place drawn on the
    table."""

    def __init__(
        self, frames: dict[str, np.ndarray[Any, Any]], heights: dict[str, float] | None = None
    ) -> None:
        self.frames = frames
        self.heights = heights or {}  # each object's, as drawn [m]
        self.by: dict[str, tuple[str, dict[str, np.ndarray[Any, Any]]]] = {}  # object -> ...
        self.below: dict[str, float] = {}  # robot -> the held object's bottom under its TCP [m]
        self.pose_of: dict[str, np.ndarray[Any, Any]] = {}  # each hand's last pose goal

    def reach_below(self, robot: str) -> float:
        """How far under the robot's TCP the object its hand holds reaches
        (0: it holds none), as grasped with the tool pointing down."""
        return self.below.get(robot, 0.0)

    def holds(self, robot: str) -> bool:
        return any(r == robot for r, _ in self.by.values())

    def follow(self, m: Move, mv: MovePlan) -> MovePlan:
        """``mv`` made to follow the hand that holds the object its goal is
        relative to (another robot's), from that hand's pose goal."""
        obj = m.goal.relative_to.split(".")[0]
        holder = self.by.get(obj, ("", {}))[0]
        if not holder or holder == m.robot or holder not in self.pose_of:
            return mv
        point = self.frames[m.goal.relative_to].copy()
        return dataclasses.replace(
            mv, follows=holder, holder_pose=self.pose_of[holder].copy(), follow_point=point
        )

    def moved(self, mv: MovePlan) -> None:
        """``mv`` planned: the frames of what its hand holds follow it."""
        from redistro.control.cartesian import rotvec_to_matrix

        if mv.scheme == "joint":
            self.pose_of.pop(mv.robot, None)
        else:
            self.pose_of[mv.robot] = mv.pose.copy()

        for robot, local in self.by.values():
            if robot != mv.robot:
                continue
            for key, d in local.items():
                if mv.scheme == "joint":
                    self.frames[key] = np.full(3, np.nan)
                else:
                    self.frames[key] = mv.pose[:3] + rotvec_to_matrix(mv.pose[3:]) @ d

    def gripped(self, m: Move, mv: MovePlan) -> None:
        """After the segment: a grasp takes its object, an opening lets go."""
        from redistro.control.cartesian import rotvec_to_matrix

        if mv.gripper == "open":
            self.by = {o: v for o, v in self.by.items() if v[0] != mv.robot}
            self.below.pop(mv.robot, None)
        obj = m.goal.relative_to.split(".")[0]
        if mv.gripper != "close" or mv.scheme == "joint" or obj in ("world", "hole"):
            return  # (a grasp relative to no object: nothing known is taken)
        if obj in self.heights:  # (its top face is its frame; its bottom this far under)
            self.below[mv.robot] = float(mv.pose[2] - self.frames[obj][2] + self.heights[obj])
        R = rotvec_to_matrix(mv.pose[3:])
        keys = [k for k in self.frames if k.startswith(obj + ".")]
        self.by[obj] = (mv.robot, {k: R.T @ (self.frames[k] - mv.pose[:3]) for k in keys})


def _hole_of(
    cfg: Config, m: Move, frames: dict[str, np.ndarray[Any, Any]], held: Held
) -> tuple[np.ndarray[Any, Any], float, float]:
    """The hole a move works at: the mouth's centre as believed, its depth
    and half its side. An object's hole (goal relative to ``<object>.hole``)
    where the plan has it, else the fixture's; the mouth's height is the
    TCP's with the tool's tip there: below the TCP by the peg of a robot
    with one, or by the object its hand holds (to the object's bottom)."""
    rel = m.goal.relative_to
    if rel.endswith(".hole"):
        o = cfg.workcell.objects[rel.split(".")[0]]
        mouth, depth, half = frames[rel].copy(), o.hole_depth_m, o.hole_side_m / 2
    else:
        h = cfg.workcell.hole
        mouth, depth = frames["hole"].copy(), h.depth_m
        half = (cfg.workcell.peg.side_m + h.clearance_m) / 2
    mouth[2] += held.reach_below(m.robot)
    return mouth, depth, half


def _move(
    s: MoveSegment,
    m: Move,
    frames: dict[str, np.ndarray[Any, Any]],
    hole: tuple[np.ndarray[Any, Any], float, float],
) -> MovePlan:
    g = m.goal
    pose = np.zeros(6)
    if g.pos_xyz_rot_xyz:
        pose = np.asarray(g.pos_xyz_rot_xyz, dtype=np.float64).copy()
        pose[:3] += frames[g.relative_to]
    return MovePlan(
        robot=m.robot,
        scheme=m.scheme,
        move_s=move_s(s, m),
        q_goal=np.asarray(g.q_rad or [0.0] * 7, dtype=np.float64),
        pose=pose,
        force=np.asarray(g.force_xyz_torque_xyz, dtype=np.float64),
        selection=np.asarray(g.selection_vector, dtype=np.float64),
        frame=g.frame,
        pose_within_m=m.end.pose_within_m,
        rot_within_rad=m.end.rot_within_rad,
        force_within_n=m.end.force_within_n,
        hold_s=m.end.hold_s,
        search=m.search,
        mouth_z_m=float(hole[0][2]),
        hole_depth_m=hole[1],
        mouth_xy_m=(float(hole[0][0]), float(hole[0][1])),
        hole_half_m=hole[2],
        name=s.name,
        duration_s=s.duration_s,
        skill=skill_of(m).name,
        contact_n=m.end.contact_n,
        gripper=skill_of(m).gripper,
        where=m.where,
        stiffness=tuple(g.stiffness_xyz_rot_xyz),
    )


def ssc_spec(
    cfg: Config,
    task: Task,
    session_id: str,
    *,
    run_dir: str,
    messages_path: str = "",
    link: str = "",
) -> NodeSpec:
    """link: the id the DDMs meet on, for a node started alone (default: the session id)."""
    node_params = NodeParams(run_dir=run_dir, link=link, task_name=task.task)
    prio = cfg.scheduling.priorities
    if cfg.ssc.parallel_arms:
        arms = worker_specs(cfg, tuple(("worker", 0) for _ in task.robots), {}, cfg.ssc.rate_hz)
        for i, (w, r) in enumerate(zip(arms, task.robots, strict=True)):
            w.name, w.params = f"arm.{r}", {"arm": i}
        rest = worker_specs(cfg, PARALLEL_WORKERS, {}, cfg.ssc.rate_hz)
        rest[0].params = {"lead": True}
        workers = arms + rest
    else:
        workers = worker_specs(cfg, SSC_WORKERS, {}, cfg.ssc.rate_hz)
    return NodeSpec(
        session_id=session_id,
        node="ssc",
        kind="ssc",
        rate_hz=cfg.ssc.rate_hz,
        heartbeat_limit_cycles=cfg.ssc.heartbeat_limit_cycles,
        workers=workers,
        robots=list(task.robots),
        startup_timeout_s=cfg.session.startup_timeout_s,
        clock=cfg.session.clock,
        shutdown_timeout_s=cfg.session.shutdown_timeout_s,
        sched_policy=cfg.scheduling.policy,
        lock_memory=cfg.scheduling.lock_memory,
        cpu_latency_us=cfg.scheduling.cpu_latency_us,
        manager_priority=prio.get("manager", 20),
        cpus=list(cfg.ssc.cpus),
        messages_path=messages_path,
        config=resolved(controller_view(cfg)),
        task_data=resolved(task),
        node_params=node_params,
    )

"""Task files: what a session does (YAML, validated; errors name the field).

A task names its robots and its kind; each kind has its own section.

- ``self_calibration`` (paper Table 6.II), all joints of a robot together:
  segment 1 clockwise move to -range, segment 2 counter-clockwise to +range
  (both from the initial joint position), segment 3 final positioning to
  ``final_q_rad`` in the corrected (calibrated) frame; the home-switch edges
  met in segments 1 and 2 give each joint's zero offset.
- ``joint_move``: ESC-local positioning segments (quintic moves under the
  joint PID) to joint goals; needs known joint positions.
- ``strategy``: the SSC drives the group (paper Table 6.III): each segment
  moves one robot (``robot``), or several at once (``moves``: a goal per
  robot, all on the segment's clock), each a skill (``config/skills.py``)
  under a control scheme
  (``joint``: joint PID to ``goal.q_rad``; ``position``: Cartesian impedance
  to a TCP pose; ``force``: hybrid position/force control with a task-frame
  command) while the other robots hold their pose. Poses may be given
  relative to the hole fixture (``relative_to: hole``, the hole's pose from
  the config). A segment ends after ``duration_s``, or earlier once every
  moving robot's ``end`` conditions have held for its ``end.hold_s`` (a
  robot without any does not hold the segment back; ``until: any``: once
  one robot's have). Needs known joint
  positions: when they are unknown, a
  self-calibration runs first (``calibrate_if_needed``), as the task's own
  ``calibration`` section says (the defaults where it has none).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from redistro.config.loader import read_yaml
from redistro.config.model import Config
from redistro.config.validate import build
from redistro.errors import ConfigError

MAX_SEGMENTS = 254  # PLAN.segment and ESC_PLAN.segment are u1; 255 means past the last


@dataclass(frozen=True)
class CalibrationTask:
    """range_deg: the sweep either side of the initial position [deg] (paper:
    10-15); segment_s: durations of segments 1, 2, 3 [s] (paper: 10 each);
    order: calibrate the robots ``together`` (one ESC each, at once) or
    ``one_at_a_time``; final_q_rad: per robot, the goal of segment 3 in the
    corrected frame [rad] (default: the home angles of the sensor config);
    settle_s: hold at the goal before the session ends [s]."""

    range_deg: float = field(default=12.0, metadata={"ge": 5.0, "le": 20.0})
    segment_s: list[float] = field(
        default_factory=lambda: [10.0, 10.0, 10.0], metadata={"len": 3, "gt": 0, "le": 600}
    )
    order: Literal["together", "one_at_a_time"] = "together"
    final_q_rad: dict[str, list[float]] = field(default_factory=dict, metadata={"len": 7})
    settle_s: float = field(default=0.5, metadata={"ge": 0, "le": 60})


@dataclass(frozen=True)
class Goal:
    """A strategy segment's goal.

    q_rad: joint goal (scheme ``joint``) [rad];
    pos_xyz_rot_xyz: TCP goal pose: position [m] and rotation vector [rad]
        (world from tool; the rotation is always absolute);
    relative_to: ``world``, ``hole`` (the position is an offset from the
        hole's mouth centre as drawn, ``workcell.hole.xyz_m``), an object
        of ``workcell.objects`` (from the centre of its top face as drawn),
        or ``<object>.hole`` (from the mouth of the object's hole: as drawn,
        or, once a hand has grasped the object, where that hand's pose
        goals have taken it since; ssc/plan.py);
    force_xyz_torque_xyz: the wrench the tool applies [N, N m], task axes;
    selection_vector: per task axis, 1 force controlled, 0 position controlled;
    frame: the task frame's axes: ``world``, or ``tool`` (at segment start);
    move_s: time to reach the goal pose (default: 3/4 of the segment);
    stiffness_xyz_rot_xyz: the Cartesian impedance's stiffness for this move
        [N/m, N m/rad], world axes (default ``ssc.impedance.k``): a hand that
        holds an object against a push stiffer than the soft default; the
        rotation's damping scales with it (the same damping ratio).
    """

    q_rad: list[float] = field(default_factory=list, metadata={"len": 7})
    pos_xyz_rot_xyz: list[float] = field(default_factory=list, metadata={"len": 6})
    relative_to: str = "world"
    force_xyz_torque_xyz: list[float] = field(
        default_factory=lambda: [0.0] * 6, metadata={"len": 6}
    )
    selection_vector: list[int] = field(
        default_factory=lambda: [0] * 6, metadata={"len": 6, "ge": 0, "le": 1}
    )
    frame: Literal["world", "tool"] = "world"
    move_s: float = field(default=0.0, metadata={"ge": 0, "le": 3600})
    stiffness_xyz_rot_xyz: list[float] = field(
        default_factory=list, metadata={"len": 6, "gt": 0, "le": 3000}
    )


@dataclass(frozen=True)
class EndConditions:
    """End a segment early when every given tolerance holds for hold_s:
    pose_within_m (TCP position error), rot_within_rad, force_within_n (force
    error on the force axes); 0 means not checked. hold_s 0: no early end.
    contact_n (a guarded_move's): the wrist's force over this is contact,
    and the move ends there."""

    pose_within_m: float = field(default=0.0, metadata={"ge": 0})
    rot_within_rad: float = field(default=0.0, metadata={"ge": 0})
    force_within_n: float = field(default=0.0, metadata={"ge": 0})
    hold_s: float = field(default=0.0, metadata={"ge": 0, "le": 3600})
    contact_n: float = field(default=0.0, metadata={"ge": 0, "le": 100})


@dataclass(frozen=True)
class Search:
    """How a force segment finds a hole it does not meet where it believes
    it is (``pattern: spiral``; ``none``: no search, push where the goal
    says; ``control.search`` has the phases). The descent slows to
    ``touch_m_s`` 3 mm above the mouth as drawn. After contact off the hole the
    tool pushes ``force_n`` [N] along the force axis while its goal in the
    hole's plane runs an Archimedean spiral about the believed centre:
    ``pitch_m`` between turns, ``speed_m_s`` along the path, the plane's
    stiffness raised to ``stiffness_n_m`` [N/m] (against the sliding
    friction) and the goal never more than ``max_lateral_n`` [N] of that
    spring ahead of the tip (a peg caught on an edge is not loaded up until
    it snaps free and swings the wrist), the yaw softened to ``yaw_stiffness_nm_rad`` [N m/rad] (the
    walls may turn the peg) until the segment ends. (Not its damping: the
    flange's inertia about its axis is about 1e-3 kg m^2, and a damping d
    acts through a sampled loop, stable only while d T / I stays well
    under 1: 0.2 N m s/rad at 200 Hz spun the flange past the guard's
    1 rad/s.) A fall of ``drop_m`` below the contact height,
    or the push gone while the tip sinks, means the peg is in: the search
    stops where the tip is, the peg goes down at the force law's own speed
    until it is three ``drop_m`` in, then at ``descent_m_s`` to
    ``slow_above_m`` above the bottom as drawn, then at the law's own speed
    again, and the segment's goal wrench pushes it home. Beyond
    ``max_radius_m`` or after ``timeout_s`` of search the segment ends as a
    clean failure: the hole was not found, the tool lifts off.

    The defaults find a hole up to 3 mm off and turned up to 2 degrees in
    about 8 s (docs/PERFORMANCE.md, "Peg insertion under uncertainty")."""

    pattern: Literal["none", "spiral"] = "none"
    touch_m_s: float = field(default=0.004, metadata={"gt": 0, "le": 0.1})
    force_n: float = field(default=6.0, metadata={"gt": 0, "le": 50})
    pitch_m: float = field(default=0.0008, metadata={"gt": 0, "le": 0.01})
    speed_m_s: float = field(default=0.006, metadata={"gt": 0, "le": 0.05})
    max_radius_m: float = field(default=0.005, metadata={"gt": 0, "le": 0.02})
    timeout_s: float = field(default=25.0, metadata={"gt": 0, "le": 600})
    drop_m: float = field(default=0.001, metadata={"gt": 0, "le": 0.02})
    stiffness_n_m: float = field(default=1500.0, metadata={"gt": 0, "le": 5000})
    max_lateral_n: float = field(default=6.0, metadata={"gt": 0, "le": 50})
    yaw_stiffness_nm_rad: float = field(default=1.0, metadata={"ge": 0, "le": 100})
    descent_m_s: float = field(default=0.02, metadata={"gt": 0, "le": 0.1})
    slow_above_m: float = field(default=0.012, metadata={"ge": 0, "le": 0.1})
    settle_s: float = field(default=0.3, metadata={"ge": 0, "le": 10})


@dataclass(frozen=True)
class Carry:
    """What a segment of two ``carry`` moves does with the object both hands
    hold (a closed chain): it moves the object by ``move_xyz_m`` [m, world]
    and turns it by ``turn_deg`` about the world's z through the point between
    the hands, in the moves' ``move_s``, squeezing it between them with
    ``squeeze_n`` [N] along the line from hand to hand; with ``release``,
    both grippers open as the segment ends (the object set down)."""

    object: str = ""
    move_xyz_m: list[float] = field(
        default_factory=lambda: [0.0, 0.0, 0.0], metadata={"len": 3, "ge": -1, "le": 1}
    )
    turn_deg: float = field(default=0.0, metadata={"ge": -90, "le": 90})
    squeeze_n: float = field(default=10.0, metadata={"ge": 0, "le": 40})
    release: bool = False


@dataclass(frozen=True)
class RobotMove:
    """One robot's part of a segment that moves several (``moves``): its
    scheme, goal, end conditions and search, as a one-robot segment gives
    them."""

    scheme: Literal["joint", "position", "force"] = "joint"
    goal: Goal = field(default_factory=Goal)
    end: EndConditions = field(default_factory=EndConditions)
    search: Search = field(default_factory=Search)
    skill: Literal[
        "", "move", "guarded_move", "push", "search_insert", "grasp", "release", "carry", "hold"
    ] = ""


@dataclass(frozen=True)
class MoveSegment:
    """One segment. joint_move: per robot a joint goal (q_rad), reached in
    duration_s. strategy: ``robot`` moves under ``scheme`` to ``goal``; or
    several robots at once, each with its own (``moves``, by robot), on one
    clock: their moves start together and take the same ``move_s``."""

    name: str
    duration_s: float = field(metadata={"gt": 0, "le": 3600})
    q_rad: dict[str, list[float]] = field(default_factory=dict, metadata={"len": 7})
    robot: str = ""
    scheme: Literal["joint", "position", "force"] = "joint"
    goal: Goal = field(default_factory=Goal)
    end: EndConditions = field(default_factory=EndConditions)
    search: Search = field(default_factory=Search)
    moves: dict[str, RobotMove] = field(default_factory=dict)
    skill: Literal[
        "", "move", "guarded_move", "push", "search_insert", "grasp", "release", "carry", "hold"
    ] = ""
    until: Literal["all", "any"] = "all"  # (moves) it ends early when all, or any, end
    carry: Carry = field(default_factory=Carry)  # (moves: skill carry)


@dataclass(frozen=True)
class Move:
    """A robot's move in a strategy segment, from either form (not a task
    file's: :func:`segment_moves` makes them)."""

    robot: str
    scheme: str
    goal: Goal
    end: EndConditions
    search: Search
    where: str  # the task file's field it came from, for messages
    skill: str = ""  # (config/skills.py; "": its scheme's)


def segment_moves(seg: MoveSegment, i: int) -> list[Move]:
    """The robots a strategy segment moves, in the order the task gives them."""
    if seg.moves:
        return [
            Move(r, m.scheme, m.goal, m.end, m.search, f"segments[{i}].moves.{r}", m.skill)
            for r, m in seg.moves.items()
        ]
    where = f"segments[{i}]"
    return [Move(seg.robot, seg.scheme, seg.goal, seg.end, seg.search, where, seg.skill)]


def insertion_object(task: Task) -> str:
    """The object whose hole the task inserts into: its first force move's,
    relative to ``<object>.hole`` ("": the fixture's hole, or no force move)."""
    forces = [m for i, s in enumerate(task.segments) for m in segment_moves(s, i)
              if m.scheme == "force"]  # fmt: skip
    rel = forces[0].goal.relative_to if forces else ""
    return rel.split(".")[0] if rel.endswith(".hole") else ""


def move_s(seg: MoveSegment, m: Move) -> float:
    """How long a move takes to its goal (3/4 of its segment unless given)."""
    return m.goal.move_s or 0.75 * seg.duration_s


@dataclass(frozen=True)
class Task:
    task: str
    kind: Literal["self_calibration", "joint_move", "strategy"]
    robots: list[str] = field(metadata={"min_len": 1})
    calibration: CalibrationTask = field(default_factory=CalibrationTask)
    segments: list[MoveSegment] = field(default_factory=list)
    settle_s: float = field(default=0.5, metadata={"ge": 0, "le": 60})
    calibrate_if_needed: bool = True
    source: str = field(default="", compare=False, metadata={"internal": True})


def load_task(path: Path | str, cfg: Config) -> Task:
    """Read and check a task file against the config (robots must exist)."""
    path = Path(path)
    data = read_yaml(path, "task")
    task = build(Task, data, origin=str(path))
    where = str(path)
    if len(task.segments) > MAX_SEGMENTS:
        raise ConfigError(
            f"{where}: segments: at most {MAX_SEGMENTS} segments (the Local Data layout's "
            f"one-byte segment index; 255 means past the last), got {len(task.segments)}"
        )
    seen: set[str] = set()
    for i, r in enumerate(task.robots):
        if r not in cfg.robots:
            known = ", ".join(cfg.robots)
            raise ConfigError(f"{where}: robots[{i}]: no robot named {r!r} (known: {known})")
        if r in seen:
            raise ConfigError(f"{where}: robots[{i}]: robot {r!r} listed twice")
        seen.add(r)
    for r in task.calibration.final_q_rad:
        if r not in seen:
            raise ConfigError(f"{where}: calibration.final_q_rad.{r}: {r!r} is not in robots")
    if task.kind == "joint_move":
        if not task.segments:
            raise ConfigError(f"{where}: segments: a joint_move task needs at least one segment")
        for i, seg in enumerate(task.segments):
            for r in seg.q_rad:
                if r not in seen:
                    raise ConfigError(f"{where}: segments[{i}].q_rad.{r}: {r!r} is not in robots")
            for r in task.robots:
                if r not in seg.q_rad:
                    raise ConfigError(f"{where}: segments[{i}].q_rad: no goal for robot {r!r}")
    elif task.kind == "strategy":
        holes = (f"{n}.hole" for n, o in cfg.workcell.objects.items() if o.hole_side_m)
        _check_strategy(task, where, ("world", "hole", *cfg.workcell.objects, *holes))
    elif task.segments:
        raise ConfigError(f"{where}: segments: not used by a {task.kind} task")
    return Task(
        task.task,
        task.kind,
        task.robots,
        task.calibration,
        task.segments,
        task.settle_s,
        task.calibrate_if_needed,
        source=where,
    )


def _check_strategy(task: Task, where: str, frames: tuple[str, ...]) -> None:
    if not task.segments:
        raise ConfigError(f"{where}: segments: a strategy task needs at least one segment")
    for i, seg in enumerate(task.segments):
        at = f"{where}: segments[{i}]"
        if seg.q_rad:
            raise ConfigError(f"{at}.q_rad: not used by a strategy task (goal.q_rad is)")
        if seg.moves:
            _check_moves_form(task, seg, at)
        elif seg.until != "all":
            raise ConfigError(f"{at}.until: for a segment of several robots (moves)")
        elif seg.carry != Carry():
            raise ConfigError(f"{at}.carry: for a segment of two carry moves (moves)")
        elif seg.robot not in task.robots:
            raise ConfigError(
                f"{at}.robot: {seg.robot!r} is not in robots ({', '.join(task.robots)})"
            )
        for m in segment_moves(seg, i):
            _check_move(seg, m, f"{where}: {m.where}")
            if seg.carry.object and seg.carry.object not in frames[2:]:
                raise ConfigError(
                    f"{where}: segments[{i}].carry.object: no object named "
                    f"{seg.carry.object!r} in workcell.objects"
                )
            if m.goal.relative_to not in frames:
                raise ConfigError(
                    f"{where}: {m.where}.goal.relative_to: no frame named "
                    f"{m.goal.relative_to!r} (known: {', '.join(frames)})"
                )


def _check_moves_form(task: Task, seg: MoveSegment, at: str) -> None:
    """A segment of several robots: its moves only, each robot once, in one time."""
    one = MoveSegment(seg.name, seg.duration_s)
    carrying = [r for r, m in seg.moves.items() if m.skill == "carry"]
    if carrying and (len(carrying) != 2 or len(seg.moves) != 2):
        raise ConfigError(f"{at}.moves: a carry is two hands' moves, both skill: carry")
    if bool(carrying) != bool(seg.carry.object):
        raise ConfigError(
            f"{at}.carry.object: "
            + ("name the object the hands carry" if carrying else "only for two carry moves")
        )
    for key in ("robot", "scheme", "goal", "end", "search", "skill"):
        if getattr(seg, key) != getattr(one, key):
            per = "moves.<robot>" if key == "robot" else f"moves.<robot>.{key}"
            raise ConfigError(f"{at}.{key}: a segment with moves gives it per robot ({per})")
    for r in seg.moves:
        if r not in task.robots:
            raise ConfigError(f"{at}.moves.{r}: {r!r} is not in robots ({', '.join(task.robots)})")
    times = {r: m.goal.move_s or 0.75 * seg.duration_s for r, m in seg.moves.items()}
    if len(set(times.values())) > 1:
        given = ", ".join(f"{r} {v:g} s" for r, v in times.items())
        raise ConfigError(
            f"{at}.moves: the robots of one segment move on one clock: give them the same "
            f"goal.move_s (got {given})"
        )


def _check_move(seg: MoveSegment, m: Move, at: str) -> None:
    from redistro.config.skills import check_skill

    skill = check_skill(m, at)
    if skill.name == "hold":
        return
    g = m.goal
    if g.move_s > seg.duration_s:
        raise ConfigError(f"{at}.goal.move_s: {g.move_s} is longer than duration_s")
    if skill.carry:
        return  # (its goal: the segment's carry)
    if m.scheme == "joint":
        if not g.q_rad:
            raise ConfigError(f"{at}.goal.q_rad: a joint segment needs a joint goal")
        return
    if not g.pos_xyz_rot_xyz:
        raise ConfigError(f"{at}.goal.pos_xyz_rot_xyz: a {m.scheme} segment needs a pose")
    if m.scheme == "position" and any(g.selection_vector):
        raise ConfigError(
            f"{at}.goal.selection_vector: a position segment has no force axes (use scheme: force)"
        )
    if m.search.pattern != "none":
        if m.scheme != "force" or list(g.selection_vector[:3]) != [0, 0, 1] or g.frame != "world":
            raise ConfigError(
                f"{at}.search: a search needs a force segment pushing along the world's "
                "z only (selection_vector [0, 0, 1, ...], frame: world)"
            )
        if g.force_xyz_torque_xyz[2] >= 0:
            raise ConfigError(f"{at}.search: a search needs a goal force down (negative z)")
    if m.scheme == "force" and not any(g.selection_vector):
        raise ConfigError(
            f"{at}.goal.selection_vector: a force segment needs at least one force axis"
        )

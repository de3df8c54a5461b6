"""Task files: what a session does (YAML, validated; errors name the field).

A task names its robots and its kind; each kind has its own section.

- ``self_calibration`` (paper Table 6.II), all joints of a robot together:
  segment 1 clockwise move to -range, segment 2 counter-clockwise to +range
  (both from the initial joint position), segment 3 final positioning to
  ``final_q_rad`` in the corrected (calibrated) frame; the home-switch edges
  met in segments 1 and 2 give each joint's zero offset.
- ``joint_move``: ESC-local positioning segments (quintic moves under the
  joint PID) to joint goals; needs known joint positions.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from redistro.config.loader import read_yaml
from redistro.config.model import Config
from redistro.config.validate import build
from redistro.errors import ConfigError


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
class MoveSegment:
    """One positioning segment: per robot a joint goal [rad], reached in duration_s."""

    name: str
    duration_s: float = field(metadata={"gt": 0, "le": 3600})
    q_rad: dict[str, list[float]] = field(default_factory=dict, metadata={"len": 7})


@dataclass(frozen=True)
class Task:
    task: str
    kind: Literal["self_calibration", "joint_move"]
    robots: list[str] = field(metadata={"min_len": 1})
    calibration: CalibrationTask = field(default_factory=CalibrationTask)
    segments: list[MoveSegment] = field(default_factory=list)
    settle_s: float = field(default=0.5, metadata={"ge": 0, "le": 60})
    source: str = field(default="", compare=False, metadata={"internal": True})


def load_task(path: Path | str, cfg: Config) -> Task:
    """Read and check a task file against the config (robots must exist)."""
    path = Path(path)
    data = read_yaml(path)
    task = build(Task, data, origin=str(path))
    where = str(path)
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
    elif task.segments:
        raise ConfigError(f"{where}: segments: not used by a {task.kind} task")
    return Task(
        task.task,
        task.kind,
        task.robots,
        task.calibration,
        task.segments,
        task.settle_s,
        source=where,
    )

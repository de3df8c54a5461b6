"""``placed``: did a carried object end where the task put it? The plant's
truth, never the controller's: the object let go, resting upright on the
table where it started from, and moved from pick to place as the task's
carries command (each moves it by its ``move_xyz_m`` and turns it by its
``turn_deg`` about the point between the hands, which the object carries
along: in all, the sum of the turns about the hands' midpoint as the
grippers took it, then the sum of the moves)."""

from __future__ import annotations

import math
from typing import Any

from redistro.config.task import Task

PLACED_WITHIN_M = 0.002
PLACED_WITHIN_RAD = 0.01
RESTING_WITHIN_M = 0.001  # its centre's height as it started: on the table
UPRIGHT_DEG = 1.0


def placed(task: Task, plant: dict[str, Any]) -> dict[str, Any]:
    """summary.json's ``placed``, ``object_pose_error_m`` and
    ``object_pose_error_rad`` for the objects the task carries ({} when it
    carries none, or the plant has no record of them)."""
    carried: dict[str, tuple[list[float], float]] = {}
    for seg in task.segments:
        c = seg.carry
        if c.object:
            move, turn = carried.get(c.object, ([0.0, 0.0, 0.0], 0.0))
            carried[c.object] = (
                [a + b for a, b in zip(move, c.move_xyz_m, strict=True)],
                turn + c.turn_deg,
            )
    start, end = plant.get("objects_start") or {}, plant.get("objects") or {}
    if not carried or not all(n in start and n in end for n in carried):
        return {}
    ok, err_m, err_rad = True, 0.0, 0.0
    for name, (move, turn) in carried.items():
        took = [e["at_xyz_m"] for e in plant.get("grippers", []) if e.get("took") == name]
        if len(took) < 2:
            ok = False
            continue
        px, py = (took[0][0] + took[1][0]) / 2, (took[0][1] + took[1][1]) / 2
        (x0, y0, z0), (x1, y1, z1) = start[name]["xyz_m"], end[name]["xyz_m"]
        a = math.radians(turn)
        ex = px + move[0] + math.cos(a) * (x0 - px) - math.sin(a) * (y0 - py)
        ey = py + move[1] + math.sin(a) * (x0 - px) + math.cos(a) * (y0 - py)
        e_m = math.hypot(x1 - ex, y1 - ey)
        yaw = start[name]["yaw_deg"] + turn - end[name]["yaw_deg"]
        e_rad = abs(math.radians((yaw + 180.0) % 360.0 - 180.0))
        err_m, err_rad = max(err_m, e_m), max(err_rad, e_rad)
        ok = ok and (
            not end[name]["held_by"]
            and end[name]["tilt_deg"] < UPRIGHT_DEG
            and abs(z1 - z0) < RESTING_WITHIN_M
            and e_m <= PLACED_WITHIN_M
            and e_rad <= PLACED_WITHIN_RAD
        )
    return {
        "placed": ok,
        "object_pose_error_m": round(err_m, 6),
        "object_pose_error_rad": round(err_rad, 6),
    }

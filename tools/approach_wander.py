"""How still the tool holds at the end of a position segment, from session logs.

    python tools/approach_wander.py RUN_FOLDER... [--robot r2] [--segment 1] [--json FILE]

For each run folder (its ``session.mcap``), the segment's plan samples of
the robot: the tool's position error against the segment's goal at the
segment's last sample (the figure the summary gives), and over the hold,
from 1 s after the reference reached the goal to the segment's end: the
peak-to-peak error per axis, the RMS and the largest sideways (xy)
distance, and the share of the hold spent more than 0.2 mm off sideways.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from redistro.log.mcapfile import read_log

SETTLE_S = 1.0  # after the reference reached the goal
OFF_M = 0.0002


def wander(run: Path, robot: str, segment: int) -> dict[str, Any]:
    plan = read_log(run / "session.mcap").arrays[f"/{robot}/plan"]
    p = plan[plan["segment"] == segment]
    if not len(p):
        raise ValueError(f"{run}: no samples of segment {segment} for {robot}")
    t = p["segment_t_s"]
    e = p["tcp_xyz_m"] - p["goal_xyz_m"]
    moving = np.abs(p["ref_xyz_m"] - p["goal_xyz_m"]).max(axis=1) > 1e-9
    held = t > (t[moving].max() if moving.any() else 0.0) + SETTLE_S
    xy = np.hypot(e[:, 0], e[:, 1])
    h = e[held]
    return {
        "run": run.name,
        "final_xy_mm": round(float(xy[-1]) * 1e3, 3),
        "final_m": round(float(np.linalg.norm(e[-1])), 6),
        "hold_s": round(float(t[held].max() - t[held].min()), 2) if held.any() else 0.0,
        "hold_p2p_xyz_mm": [round(float(np.ptp(h[:, k])) * 1e3, 3) for k in range(3)]
        if held.any()
        else [],
        "hold_rms_xy_mm": round(math.sqrt(float((xy[held] ** 2).mean())) * 1e3, 3)
        if held.any()
        else 0.0,
        "hold_max_xy_mm": round(float(xy[held].max()) * 1e3, 3) if held.any() else 0.0,
        "hold_share_off": round(float((xy[held] > OFF_M).mean()), 3) if held.any() else 0.0,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="tools/approach_wander.py", description=__doc__.splitlines()[0]
    )
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--robot", default="r2")
    ap.add_argument("--segment", type=int, default=1, help="1-based, as in the log")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    rows = []
    for run in a.runs:
        try:
            rows.append(wander(run, a.robot, a.segment))
        except (OSError, ValueError, KeyError) as exc:
            print(f"tools/approach_wander.py: {run}: {exc}", file=sys.stderr)
            return 2
    for r in rows:
        print(
            f"{r['run']}: final {r['final_xy_mm']:.3f} mm sideways; hold {r['hold_s']} s: "
            f"p2p {r['hold_p2p_xyz_mm']} mm, rms {r['hold_rms_xy_mm']:.3f}, "
            f"max {r['hold_max_xy_mm']:.3f} mm, {100 * r['hold_share_off']:.0f} % beyond 0.2 mm"
        )
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

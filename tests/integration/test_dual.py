"""Several robots in one segment (tasks/dual_reach.yaml) over a real session:
both arms move at once on one clock, each under its own scheme."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tests.helpers import copy_runs, load_json, run_cli

TASK = "tasks/dual_reach.yaml"


def test_both_arms_move_in_one_segment_on_one_clock(calibrated: Path, tmp_path: Path) -> None:
    from redistro.log.mcapfile import read_log

    runs = copy_runs(calibrated, tmp_path)
    out = tmp_path / "run"
    done = run_cli(
        "--set", f"session.runs_dir={runs}", "session", TASK, "--out", str(out), timeout=180
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "segment 1/2 reach: r1 joint, r2 position" in (out / "messages.log").read_text()
    summary = load_json(out / "summary.json")
    assert summary["result"] == "ok", summary["reason"]
    # a figure per robot's move, each at its goal
    moves = [(s["name"], s["robot"], s["scheme"]) for s in summary["segments"]]
    assert moves == [
        ("reach", "r1", "joint"),
        ("reach", "r2", "position"),
        ("home", "r1", "joint"),
        ("home", "r2", "joint"),
    ], moves
    for s in summary["segments"]:  # (a joint move settles for 1 s after its quintic)
        bound = 0.001 if s["scheme"] == "position" else 0.003
        assert s["final_pose_error"]["position_m"] < bound, s
    # one clock: every logged cycle, both robots in the same segment, moving together
    sl = read_log(out / "session.mcap")
    p1, p2 = sl.arrays["/r1/plan"], sl.arrays["/r2/plan"]
    n = min(len(p1), len(p2))
    assert n > 0 and abs(len(p1) - len(p2)) <= 1
    assert np.array_equal(p1["segment"][:n], p2["segment"][:n])
    assert np.array_equal(p1["moving"][:n], p2["moving"][:n])
    for k in (1, 2):
        assert np.any((p1["segment"][:n] == k) & (p1["moving"][:n] == 1)), k
    # r1 really went somewhere: its goal 0.4 rad of joint 1 away, and back
    fb = sl.arrays["/r1/feedback"]
    assert float(np.max(fb["q_rad"][:, 0])) > 0.35
    # the plant: the arms never touched
    assert summary["plant"]["arms"]["touched"] is False, summary["plant"]["arms"]

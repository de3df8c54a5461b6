"""Joint limits: refused at load when a task or a file breaks them, enforced by
the guard every cycle when a joint heads for them (real sessions, the CLI)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from redistro.drivers import positions
from tests.helpers import LOCKSTEP, load_json, run_cli

SHORT = "tasks/self_calibration_short.yaml"
PARK = [0.0, 0.5, 0.0, -1.2, 0.0, 1.0, 0.0]


def _joint_task(tmp_path: Path, goal: list[float], seconds: float) -> Path:
    task = tmp_path / "move.yaml"
    task.write_text(
        yaml.safe_dump(
            {
                "task": "move",
                "kind": "joint_move",
                "robots": ["r1"],
                "segments": [{"name": "move", "duration_s": seconds, "q_rad": {"r1": goal}}],
            }
        )
    )
    return task


def _known(runs: Path, q: list[float]) -> None:
    positions.write(runs / "positions" / "r1.json", "test", {"r1": q}, clean=True)


def _refused(tmp_path: Path, *args: str) -> str:
    shm_before = {e for e in os.listdir("/dev/shm") if "redistro" in e}
    done = run_cli("--set", f"session.runs_dir={tmp_path / 'runs'}", *args)
    assert done.returncode == 2, done.stdout[-2000:] + done.stderr[-2000:]
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("redistro: error: "), done.stderr
    assert done.stdout == ""
    assert {e for e in os.listdir("/dev/shm") if "redistro" in e} == shm_before
    runs = tmp_path / "runs"
    assert not runs.exists() or sorted(p.name for p in runs.iterdir()) == ["positions"]
    return lines[0]


@pytest.mark.parametrize(
    ("goal", "seconds", "expect"),
    [
        ([3.0] * 7, 0.5, "joint 1 at 3 rad is outside its limits [-2.917, 2.917] rad"),
        ([1.0e300] * 7, 5.0, "joint 1 at 1e+300 rad is outside its limits"),
        ([0.0, 0.5, 0.0, -1.2, 0.0, 1.0, 2.5], 1.0, "joint 7 would move 2.5 rad in 1 s"),
    ],
)
def test_a_joint_goal_out_of_limits_or_too_fast_is_refused_at_load(
    tmp_path: Path, goal: list[float], seconds: float, expect: str
) -> None:
    _known(tmp_path / "runs", PARK)
    line = _refused(tmp_path, "session", str(_joint_task(tmp_path, goal, seconds)))
    assert expect in line and "segments[0].q_rad.r1" in line, line


def test_a_forged_positions_file_beyond_the_limits_is_refused(tmp_path: Path) -> None:
    # a well-formed file with its checksum recomputed: the range gives it away
    _known(tmp_path / "runs", [50.0] * 7)
    line = _refused(tmp_path, "session", str(_joint_task(tmp_path, PARK, 5.0)))
    assert "positions/r1.json: q_rad.r1: joint 1 at 50 rad is outside its limits" in line, line


@pytest.mark.parametrize(
    ("setting", "expect"),
    [
        (
            "esc.safety.tau_max_nm=[1.0e+300, 1, 1, 1, 1, 1, 1]",
            "--set: esc.safety.tau_max_nm[0]: 1e+300 N m is over r1's joint 1 rating 300 N m",
        ),
        (
            "esc.safety.force_max_n=9000",
            "--set: esc.safety.force_max_n: 9000 N is over r1's wrist sensor range 8389 N",
        ),
        (
            "esc.safety.qd_max_rad_s=[1, 1, 1, 1, 1, 1, 20]",
            "esc.safety.qd_max_rad_s[6]: 20 rad/s is over joint 7's rated speed 10 rad/s",
        ),
        (
            "esc.safety.q_max_rad=[3, 2, 2, 2, 2, 2, 2]",
            "esc.safety.q_max_rad[0]: 3 rad is wider than the arm model's limit 2.967 rad",
        ),
    ],
)
def test_a_safety_limit_over_the_hardware_rating_is_refused(
    tmp_path: Path, setting: str, expect: str
) -> None:
    line = _refused(tmp_path, "--set", setting, "session", SHORT)
    assert expect in line, line


def test_the_guard_stops_a_joint_heading_for_its_limit_inside_it(tmp_path: Path) -> None:
    """The self-calibration sweeps joint 1 by +-12 deg (0.21 rad) around 0;
    with joint 1's upper limit narrowed to 0.25 rad (0.20 with the margin) the
    guard must end the session unsafe, the joint frozen inside the limit."""
    out = tmp_path / "run"
    limit = 0.25
    done = run_cli(
        "--set",
        f"session.runs_dir={tmp_path / 'runs'}",
        "--set",
        f"esc.safety.q_max_rad=[{limit}, 2.0, 2.9, 2.0, 2.9, 2.0, 3.0]",
        "session",
        SHORT,
        "--out",
        str(out),
    )
    assert done.returncode == 1, done.stdout[-2000:] + done.stderr[-2000:]
    summary = load_json(out / "summary.json")
    assert summary["result"] == "unsafe", summary["reason"]
    robot = summary["reason"].split()[0]
    v = summary["violations"][robot]
    assert v["joint"] == 1 and v["quantity"] in ("position", "stopping position"), v
    assert v["limit"] == pytest.approx(limit - 0.05), v
    # the guard's view: the joint never passed the limit
    trace = json.loads((out / f"trip-{robot}.json").read_text())
    q = np.asarray(trace["q_rad"])[:, 0]
    assert q.max() < limit and np.all(q[:-1] <= limit - 0.05), q[-5:]
    # the arm itself (the plant's truth, up to the unknown encoder offset of at
    # most 0.05 rad before the calibration) stopped inside the limit too
    truth = json.loads((out / "plant.json").read_text())["final_q_rad"][robot][0]
    assert truth < limit + 0.05, truth


def test_a_robot_left_at_or_past_its_limit_is_brought_back_by_park(
    calibrated: Path, tmp_path: Path
) -> None:
    """Joint 4 sent exactly to its limit less the margin (the session may
    end unsafe on arrival: a hair past it): park brings it back. Sent there
    again, and the limit then narrowed past where it rests (a joint found
    past its limit): park brings it back all the same; moving back slowly
    is what the guard lets a joint outside its limits do."""
    import shutil

    from redistro.config.limits import model_limits

    runs = tmp_path / "runs"
    shutil.copytree(calibrated, runs)
    edge = model_limits().lower[3] + 0.05
    goal = [0.0, 0.5, 0.0, edge, 0.0, 1.0, 0.0]
    task = _joint_task(tmp_path, goal, 5.0)
    common = [*LOCKSTEP, "--set", f"session.runs_dir={runs}"]
    narrowed = edge + 0.03  # the joint rests 0.03 rad past this limit
    lows = ", ".join(repr(v) for v in (*model_limits().lower[:3], narrowed,
                                          *model_limits().lower[4:]))  # fmt: skip
    for k, extra in enumerate(([], ["--set", f"esc.safety.q_min_rad=[{lows}]"])):
        there = run_cli(*common, "session", str(task), "--out", str(tmp_path / f"edge{k}"))
        assert there.returncode in (0, 1), there.stdout[-2000:] + there.stderr[-2000:]
        left = load_json(tmp_path / f"edge{k}" / "summary.json")
        assert left["result"] in ("ok", "unsafe"), left["reason"]
        rest = positions.read(runs / "positions" / "r1.json", ["r1"]).q_rad["r1"][3]
        assert rest == pytest.approx(edge, abs=0.01)
        out = tmp_path / f"park{k}"
        done = run_cli(*common, *extra, "session", "tasks/park.yaml", "--out", str(out))
        summary = load_json(out / "summary.json")
        assert done.returncode == 0 and summary["result"] == "ok", (k, summary["reason"])
        truth = load_json(out / "plant.json")["final_q_rad"]["r1"]
        assert truth[3] == pytest.approx(PARK[3], abs=0.06), truth  # (encoder offsets: 0.05)

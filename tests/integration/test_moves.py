"""Segments of several robots and named skills over a real session
(tests/data/moves_and_skills.yaml): both arms move at once on one clock, each
under its own scheme; a guarded move stops at the first contact."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.helpers import LOCKSTEP, ROOT, copy_runs, load_json, run_cli

TASK = str(ROOT / "tests/data/moves_and_skills.yaml")
CONTACT_N = 2.0  # the task's guarded move ends at this wrist force
PEAK_N = 60.0  # the impact's peak, sampled (the peg campaign's bound on contact)


def _session(calibrated: Path, tmp_path: Path, task: str, *options: str) -> Path:
    """A session of ``task`` from the calibrated runs folder, ended with
    exit 0; its run folder."""
    runs = copy_runs(calibrated, tmp_path)
    out = tmp_path / "run"
    done = run_cli(
        *LOCKSTEP, *options, "--set", f"session.runs_dir={runs}",
        "session", task, "--out", str(out), timeout=180,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return out


def test_two_arms_on_one_clock_and_a_guarded_move(calibrated: Path, tmp_path: Path) -> None:
    from redistro.config.loader import load_config
    from redistro.log.mcapfile import read_log

    out = _session(calibrated, tmp_path, TASK)
    messages = (out / "messages.log").read_text()
    assert "segment 1/4 reach: r1 joint, r2 position" in messages
    assert "segment 2/4 touch: r1 joint, r2 position" in messages
    assert "r2 guarded_move: contact at t=" in messages
    assert "segment 3/4 wait: every robot holds" in messages
    summary = load_json(out / "summary.json")
    assert summary["result"] == "ok", summary["reason"]
    # a figure per robot's move (a hold has none)
    segs = summary["segments"]
    assert [(s["name"], s["robot"], s["scheme"]) for s in segs] == [
        ("reach", "r1", "joint"),
        ("reach", "r2", "position"),
        ("touch", "r1", "joint"),
        ("touch", "r2", "position"),
        ("home", "r1", "joint"),
        ("home", "r2", "joint"),
    ], segs
    for s in segs[:2] + segs[4:]:  # (a joint move settles for 1 s after its quintic)
        bound = 0.001 if s["scheme"] == "position" else 0.003
        assert s["final_pose_error"]["position_m"] < bound, s
    # the guarded move ended early, 2 cm short of its goal inside the block,
    # and with it the segment (until: any): r1's move cut short on the way
    r1_touch, touch = segs[2], segs[3]
    assert touch["duration_s"] < 3.5, touch
    assert 0.015 < touch["final_pose_error"]["position_m"] < 0.025, touch
    assert abs(r1_touch["duration_s"] - touch["duration_s"]) < 0.02, (r1_touch, touch)
    assert r1_touch["final_pose_error"]["position_m"] > 0.005, r1_touch
    sl = read_log(out / "session.mcap")
    p1, p2 = sl.arrays["/r1/plan"], sl.arrays["/r2/plan"]
    n = min(len(p1), len(p2))
    assert n > 0 and abs(len(p1) - len(p2)) <= 1
    # one clock: every logged cycle both robots in the same segment, and in
    # the two-robot segments moving together
    assert np.array_equal(p1["segment"][:n], p2["segment"][:n])
    for k in (1, 4):
        at = p1["segment"][:n] == k
        assert at.any() and np.array_equal(p1["moving"][:n][at], p2["moving"][:n][at]), k
        assert p1["moving"][:n][at].all(), k
    # the contact: on the fixture's top as drawn, the wrist's force past the
    # threshold and bounded (the wrist sensor, r2's feedback)
    top = load_config(None).workcell.hole.xyz_m[2]
    at = p2["segment"][:n] == 2
    assert abs(float(p2["tcp_xyz_m"][:n][at][-1, 2]) - top) < 0.003
    fb = sl.arrays["/r2/feedback"]
    m = min(len(fb), n)
    force = np.linalg.norm(fb["wrench"][:m, :3], axis=1)
    assert CONTACT_N < float(force[at[:m]].max()) < PEAK_N
    # r1 really went somewhere: its goal 0.4 rad of joint 1 away, and back
    assert float(np.max(sl.arrays["/r1/feedback"]["q_rad"][:, 0])) > 0.35
    # the plant: the arms never touched
    assert summary["plant"]["arms"]["touched"] is False, summary["plant"]["arms"]
    # the SSC's watch, in every cycle's plan and in the summary: the arms'
    # nearest links and the nearest to the work-cell (the guarded move's
    # flange comes down to 10 cm over the fixture's top)
    seen = summary["clearance"]
    assert 0.03 < seen["arms_min_m"] < 1.0 and 0.03 < seen["cell_min_m"] < 0.2, seen
    arms = p1["arms_clearance_m"][:n][p1["stamp_ns"][:n] != 0]  # (since the task's start)
    assert np.isfinite(arms).all() and float(arms.min()) == pytest.approx(
        seen["arms_min_m"], abs=1e-4
    )
    truth = summary["plant"]["arms"]["min_distance_m"]  # (PyBullet's, within 0.3 m)
    if truth is not None:
        assert abs(truth - seen["arms_min_m"]) < 0.02, (truth, seen)
    # and its plot
    import matplotlib

    from redistro.log.inspect import _Plots

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plots = _Plots(plt, tmp_path)
    plots.clearance(p1)
    assert (tmp_path / "arms-clearance.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_two_arm_task_passes_the_load_check(calibrated: Path, tmp_path: Path) -> None:
    runs = copy_runs(calibrated, tmp_path)
    done = run_cli("--set", f"session.runs_dir={runs}", "check", "tasks/dual_reach.yaml")
    assert done.returncode == 0, done.stdout + done.stderr


DUAL = ["--config", str(ROOT / "config/dual_arm.yaml")]  # (the objects, no peg on r2)
GRASP_TASK = str(ROOT / "tasks/grasp_lift.yaml")


def test_a_gripper_picks_the_block_up_and_sets_it_down(calibrated: Path, tmp_path: Path) -> None:
    """r1's gripper, through its I/O board's DIO output: closed on the block
    the plant welds it where it really is; lifted, the wrist feels its
    weight; set down 5 cm further on and let go, it rests there upright."""
    from redistro.config.loader import load_config
    from redistro.config.model import table_top_m
    from redistro.log.mcapfile import read_log

    out = _session(calibrated, tmp_path, GRASP_TASK, *DUAL)
    messages = (out / "messages.log").read_text()
    assert "r1 grasp: gripper closed at t=" in messages
    assert "r1 release: gripper opened at t=" in messages
    plant = load_json(out / "summary.json")["plant"]
    # the plant's truth: the DIO output closed r1's gripper on the block, then opened it
    assert [(e["robot"], e["closed"], e["took"]) for e in plant["grippers"]] == [
        ("r1", True, "block"),
        ("r1", False, ""),
    ], plant["grippers"]
    block = plant["objects"]["block"]
    cfg = load_config(ROOT / "config/dual_arm.yaml")
    top = table_top_m(cfg.workcell.hole)
    drawn, truth = cfg.workcell.objects["block"], cfg.plant.objects["block"]
    x0, y0 = (a + b for a, b in zip(drawn.xy_m, truth.offset_xy_m, strict=True))
    assert block["held_by"] == [], block
    assert block["tilt_deg"] < 1.0 and abs(block["yaw_deg"] - truth.yaw_deg) < 1.0, block
    assert abs(block["xyz_m"][2] - (top + 0.03)) < 0.001, block  # on the table
    # moved by what the task commanded (0, 5 cm) from where it really was
    assert abs(block["xyz_m"][0] - x0) < 0.003 and abs(block["xyz_m"][1] - (y0 + 0.05)) < 0.003
    # the controller's own sensor: its wrist carried the block's weight
    sl = read_log(out / "session.mcap")
    plan, fb = sl.arrays["/r1/plan"], sl.arrays["/r1/feedback"]
    n = min(len(plan), len(fb))
    force = np.linalg.norm(fb["wrench"][:n, :3], axis=1)

    def last(segment: int) -> float:  # the wrist's force over a segment's last 0.2 s
        at = np.flatnonzero(plan["segment"][:n] == segment)
        assert len(at) > 40, segment
        return float(np.median(force[at[-40:]]))

    weight = 0.2 * 9.81
    assert abs(last(3) - last(1) - weight) < 0.4 * weight, (last(1), last(3))
    assert abs(last(5) - last(1)) < 0.4 * weight, (last(1), last(5))


CARRY_TASK = str(ROOT / "tasks/dual_carry_short.yaml")


@pytest.mark.parametrize("parallel", [False, True], ids=["serial", "parallel"])
def test_two_hands_carry_one_bar(calibrated: Path, tmp_path: Path, parallel: bool) -> None:
    """A closed chain: both grippers on one 2 kg bar, lifted, carried 0.2 m
    while turned 30 degrees, set down: the plant's bar moved by what the
    task commanded from where it really was, squeezed at 10 N throughout.
    Parallel: each arm's law in a worker of its own (ssc.parallel_arms),
    the task's clock in a worker after them."""
    from redistro.log.mcapfile import read_log

    options = [*DUAL, "--set", f"ssc.parallel_arms={str(parallel).lower()}"]
    out = _session(calibrated, tmp_path, CARRY_TASK, *options)
    summary = load_json(out / "summary.json")
    workers = [w["name"] for w in summary["nodes"]["ssc"]["workers"]]
    want = ["arm.r1", "arm.r2", "worker"] if parallel else ["worker"]
    assert workers == [*want, "logger", "ddm"], workers
    messages = (out / "messages.log").read_text()
    assert messages.count("segment 4/") == 1, messages  # (said once, by the clock's worker)
    plant = summary["plant"]
    events = sorted((e["robot"], e["closed"], e["took"]) for e in plant["grippers"])
    assert events == [
        ("r1", False, ""), ("r1", True, "bar"), ("r2", False, ""), ("r2", True, "bar"),
    ], plant["grippers"]  # fmt: skip
    bar = plant["objects"]["bar"]
    assert bar["held_by"] == [] and bar["tilt_deg"] < 1.0, bar  # let go, resting upright
    # placed: moved from where it really was (the bar is 3 mm and 2 mm and 2
    # degrees off its drawing) by (0, 0.2 m) and 30 degrees about the hands'
    # midpoint, within 2 mm and 0.01 rad (the plant's truth)
    assert summary["placed"] is True, (summary["object_pose_error_m"], bar)
    assert summary["object_pose_error_m"] <= 0.002 and summary["object_pose_error_rad"] <= 0.01
    assert abs(bar["yaw_deg"] - 32.0) < 1.0, bar
    # the squeeze, at both wrists, on the line between the hands
    carried = [s for s in summary["segments"] if s["name"] in ("lift", "carry", "set_down")]
    assert len(carried) == 6
    for s in carried:
        assert s["squeeze_rms_error_n"] < 3.0 and 5.0 < s["squeeze_peak_n"] < 40.0, s
    sl = read_log(out / "session.mcap")
    for robot in ("r1", "r2"):
        plan = sl.arrays[f"/{robot}/plan"]
        at = plan["segment"] == 4  # the carry
        goal = np.linalg.norm(plan["wrench_goal"][at][:, :3], axis=1)
        assert np.allclose(goal, 10.0), robot
        f = np.einsum("ij,ij->i", plan["wrench_task"][at][:, :3], plan["wrench_goal"][at][:, :3])
        assert abs(float(np.median(f / goal)) - 10.0) < 2.0, robot


PEG_TASK = str(ROOT / "tasks/dual_peg_short.yaml")
DUAL_PEG = ["--config", str(ROOT / "config/dual_peg.yaml")]


def test_two_arms_insert_a_held_peg_into_a_held_block(calibrated: Path, tmp_path: Path) -> None:
    """r1 grasps the block with the hole (2 mm and 1.5 mm and 1 degree off
    its drawing: the hole 4-5 mm off in r1's hand) and presents it turned a
    quarter; r2 grasps the peg, finds the hole by its search while
    following r1's hand, pushes the peg to the bottom and lets go of it:
    inserted by the plant's truth, r1 yielding but holding."""
    out = _session(calibrated, tmp_path, PEG_TASK, *DUAL_PEG)
    summary = load_json(out / "summary.json")
    plant = summary["plant"]
    took = sorted((e["robot"], e["took"]) for e in plant["grippers"] if e["closed"])
    assert took == [("r1", "socket"), ("r2", "peg")], plant["grippers"]
    # the plant's truth: the peg's bottom went down the socket's hole to its floor
    assert plant["in_holes"]["peg"]["hole_of"] == "socket", plant["in_holes"]
    assert summary["inserted"] is True, (summary["plant_insertion_depth_m"], summary["search"])
    assert abs(summary["plant_insertion_depth_m"] - 0.04) < 0.002
    # the controller's belief beside it (followed through r1's measured hand)
    assert summary["inserted_belief"] is True
    assert abs(summary["insertion_depth_m"] - summary["plant_insertion_depth_m"]) < 0.002
    assert summary["search"]["phase"] == "in_hole" and summary["search"]["peak_force_n"] < 60
    assert not summary.get("violations")
    # r1 held the block where it presented it while r2 pushed (the law's
    # own error, a few mm at most), and the arms stayed apart
    insert = {s["robot"]: s for s in summary["segments"] if s["name"] == "insert"}
    assert insert["r1"]["final_pose_error"]["position_m"] < 0.005, insert["r1"]
    assert summary["clearance"]["arms_min_m"] > 0.03, summary["clearance"]

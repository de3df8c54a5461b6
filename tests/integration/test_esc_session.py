"""Real ESC sessions: plant, ESC managers and workers, the decision stage (CLI)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from redistro.config import load_config
from redistro.config.hardware import load_hardware
from tests.helpers import ROOT, attach_running, load_json, read_session_id, run_cli, start_cli

SHORT = "tasks/self_calibration_short.yaml"


@contextlib.contextmanager
def _session(tmp_path: Path, out: Path) -> Iterator[tuple[subprocess.Popen[str], str]]:
    """A short calibration session in the background: (process, session id).
    On the way out it is waited for (killed if still running), pipes closed."""
    proc = start_cli(
        "--set", f"session.runs_dir={tmp_path / 'runs'}", "session", SHORT, "--out", str(out)
    )
    try:
        yield proc, read_session_id(proc)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        assert proc.stdout is not None and proc.stderr is not None
        proc.stdout.close()
        proc.stderr.close()


def _summary(run: Path) -> dict[str, Any]:
    return load_json(run / "summary.json")


def _count_rad(robot: str) -> np.ndarray:
    """One encoder count of each joint, in joint radians."""
    hw = load_hardware(load_config(ROOT / "config/redistro.yaml"), ROOT / "config")[robot]
    s = hw.sensors
    return 2 * np.pi / (np.asarray(s.counts_per_rev, dtype=float) * np.asarray(s.gear_ratio))


def _check_calibrated(summary: dict[str, Any], robots: list[str]) -> None:
    assert summary["result"] == "ok", summary["reason"]
    for r in robots:
        rows = summary["calibration"][r]
        bound = np.maximum(0.001, _count_rad(r))
        for row, b in zip(rows, bound, strict=True):
            assert row["error_rad"] is not None, f"{r} joint {row['joint']}: no offset found"
            assert abs(row["error_rad"]) <= b, f"{r} joint {row['joint']}: {row}"
            assert abs(row["offset_true_rad"]) > 0.01  # the plant really was disturbed
        pos = summary["positions"][r]
        assert pos["known_at_end"], pos


def _positions_clean(runs: Path, robot: str) -> bool:
    from redistro.drivers import positions

    return positions.read(runs / "positions" / f"{robot}.json", [robot]).clean


def _plant_truth_final(run: Path) -> dict[str, list[float]]:
    data: dict[str, list[float]] = json.loads((run / "plant.json").read_text())["final_q_rad"]
    return data


def test_self_calibration_at_1khz_then_the_next_session_needs_none(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    # one robot at a time: two ESCs at 1 kHz and the plant do not fit in two vCPUs
    task = "tasks/self_calibration_short_serial.yaml"
    fast = ["--set", "esc.rate_hz=1000", "--set", "esc.heartbeat_limit_cycles=100"]
    sets = ["--set", f"session.runs_dir={runs}"]

    # before any calibration, motion is refused: the positions are unknown
    refused = run_cli(*sets, "session", "tasks/park.yaml", "--out", str(tmp_path / "r0"))
    assert refused.returncode == 2, refused.stderr
    assert "motion refused" in refused.stderr and "missing" in refused.stderr
    assert not (tmp_path / "r0").exists()

    done = run_cli(*sets, *fast, "session", task, "--out", str(tmp_path / "r1"), timeout=180)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    summary = _summary(tmp_path / "r1")
    _check_calibrated(summary, ["r1", "r2"])
    for node in ("esc.r1", "esc.r2"):
        n = summary["nodes"][node]
        assert n["rate_hz"] == 1000.0 and n["cycles"] > 3000, n
        assert set(n["lateness_us"]) == {"p50", "p99", "max"}
    truth = _plant_truth_final(tmp_path / "r1")
    frame = {}  # encoder frame vs the arm after the calibration: within its error
    for r in ("r1", "r2"):
        assert _positions_clean(runs, r)
        assert (tmp_path / "r1" / f"positions.{r}.json").exists()
        frame[r] = np.asarray(summary["positions"][r]["q_rad"]) - np.asarray(truth[r])
        assert np.all(np.abs(frame[r]) <= np.maximum(0.001, _count_rad(r))), frame[r]

    # the next session presets the counters from the recorded positions: no calibration
    park = run_cli(*sets, "session", "tasks/park.yaml", "--out", str(tmp_path / "r2"))
    assert park.returncode == 0, park.stdout[-3000:] + park.stderr[-3000:]
    summary = _summary(tmp_path / "r2")
    assert summary["result"] == "ok"
    truth = _plant_truth_final(tmp_path / "r2")
    for r in ("r1", "r2"):
        pos = summary["positions"][r]
        assert pos["at_start"].startswith("preset from"), pos
        # the encoders carry the calibrated frame over: the same offset from the arm
        again = np.asarray(pos["q_rad"]) - np.asarray(truth[r])
        err = np.abs(again - frame[r]) / _count_rad(r)
        assert np.all(err <= 2.0), f"{r}: the frame moved by {err} counts between sessions"


def test_a_slow_plant_is_no_fault(tmp_path: Path) -> None:
    """The task and its time budget count on the plant's clock: a plant at 0.17
    of real time (a loaded host's figure) takes longer than the budget would in
    wall time, and the calibration still ends ok."""
    from redistro.config.task import load_task
    from redistro.session.summary import budget_s

    startup_s = 5.0  # (the start-up margin the wall time must exceed, kept short)
    cfg = load_config(None)
    out = tmp_path / "r"
    done = run_cli(
        "--set", f"session.runs_dir={tmp_path / 'runs'}",
        "--set", "plant.real_time_factor=0.17",
        "--set", f"session.startup_timeout_s={startup_s}",
        "session", SHORT, "--out", str(out), timeout=180,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    summary = _summary(out)
    _check_calibrated(summary, ["r1", "r2"])
    plant = load_json(out / "plant.json")
    assert plant["rtf"] <= 0.18, plant["rtf"]  # paced: never faster than asked
    # longer than the budget and its start-up margin, had they counted wall time
    margin = startup_s + cfg.session.shutdown_timeout_s + 5.0
    assert plant["wall_s"] > budget_s(load_task(SHORT, cfg)) + margin, plant["wall_s"]


def test_a_velocity_limit_too_low_ends_unsafe_within_a_cycle(tmp_path: Path) -> None:
    out = tmp_path / "run"
    done = run_cli(
        "--set",
        f"session.runs_dir={tmp_path / 'runs'}",
        "--set",
        "esc.safety.qd_max_rad_s=[0.03, 0.03, 0.03, 0.03, 0.03, 0.03, 0.03]",
        "session",
        SHORT,
        "--out",
        str(out),
    )
    assert done.returncode == 1, done.stderr[-2000:]
    summary = _summary(out)
    assert summary["result"] == "unsafe", summary
    reason = summary["reason"]
    robot = reason.split()[0]
    assert robot in ("r1", "r2") and "joint" in reason and "velocity" in reason
    assert "over the limit 0.03 rad/s" in reason, reason
    v = summary["violations"][robot]
    assert v["quantity"] == "velocity" and abs(v["value"]) > v["limit"] == 0.03
    # the sample that showed the violation, and the plant's brakes: within one cycle
    rate = summary["nodes"][f"esc.{robot}"]["rate_hz"]
    steps_per_cycle = 1000.0 / rate
    freezes = [f for f in summary["plant"]["freezes"] if f["robot"] == robot]
    first = min(f["step"] for f in freezes if f["step"] >= v["sample_step"])
    print(f"unsafe: sample step {v['sample_step']}, brakes on at step {first}")
    assert first - v["sample_step"] <= steps_per_cycle + 1, (v, freezes)
    # the trace the guard wrote: the sample that tripped it is the first over the limit
    trace = json.loads((out / f"trip-{robot}.json").read_text())
    qd = np.abs(np.asarray(trace["qd_rad_s"]))
    assert trace["step"][-1] == v["sample_step"] and trace["cycle"][-1] == v["cycle"]
    assert qd[-1, v["joint"] - 1] > 0.03 and np.all(qd[:-1] <= 0.03), qd[-3:]
    # the whole group stopped: the other ESC was ended, its manager froze its robot too
    other = "r2" if robot == "r1" else "r1"
    node = summary["nodes"][f"esc.{other}"]
    # (its e-stop relayed by the session owner: ESC-only nodes have no DDM;
    # or tripped by the same low limit a moment later)
    assert node["result"] in ("estop", "unsafe"), node
    if node["result"] == "estop":
        assert f"e-stop from esc.{robot} (relayed by the session owner" in node["reason"], node
    assert any(t >= v["frozen_monotonic_ns"] for t in node["freeze_monotonic_ns"]), node
    assert "robot frozen" in (out / "messages.log").read_text()


def test_a_killed_pid_worker_ends_abnormal_with_the_robot_frozen(tmp_path: Path) -> None:
    out = tmp_path / "run"
    with _session(tmp_path, out) as (proc, sid):
        ld = attach_running(sid, "esc.r1", min_cycle=100, timeout=60)
        try:
            roles = ld.proc_roles()
            pid = int(ld.block("proc", roles.index("pid")).read()["pid"])
        finally:
            ld.close()
        # the clock before the kill: the test is not real-time, and once it got
        # the CPU back only after the robot was frozen
        killed_ns = time.monotonic_ns()
        os.kill(pid, signal.SIGKILL)
    assert proc.returncode == 1
    summary = _summary(out)
    assert summary["result"] == "abnormal"
    assert "worker pid" in summary["reason"] and "SIGKILL" in summary["reason"], summary["reason"]
    period_ns = 1e9 / summary["nodes"]["esc.r1"]["rate_hz"]
    # the manager's freeze (brakes on, DAC zero written to the boards) after the kill
    froze = [t for t in summary["nodes"]["esc.r1"]["freeze_monotonic_ns"] if t >= killed_ns]
    latency = min(froze) - killed_ns
    # and when the plant's next step applied it (the simulated hardware may lag)
    freezes = [f for f in summary["plant"]["freezes"] if f["robot"] == "r1"]
    applied = min(f["monotonic_ns"] for f in freezes if f["monotonic_ns"] >= killed_ns)
    print(
        f"pid worker killed: r1 frozen by its manager {latency / 1e6:.1f} ms later, "
        f"brakes on at the plant {(applied - killed_ns) / 1e6:.1f} ms later"
    )
    # target: 2 cycles (10 ms at 200 Hz), met in most runs here (0.8-7 ms); the
    # dying worker's own teardown, behind the other real-time processes on two
    # loaded vCPUs, once took 10.7 ms: the bound leaves the host that room
    assert latency <= 4 * period_ns, f"frozen {latency / 1e6:.1f} ms after the kill"
    assert summary["positions"]["r1"]["known_at_end"] is False  # calibration never finished


SESSION_BAD_INPUTS = [
    (["session", "tasks/no_such_task.yaml"], "tasks/no_such_task.yaml: cannot read"),
    (["session", "{task}"], "robots[1]: no robot named 'r7'"),
    (["--set", "esc.rate_hz=0", "session", SHORT], "esc.rate_hz: expected a number > 0"),
    (
        ["--set", "esc.safety.qd_max_rad_s=[1, 2]", "session", SHORT],
        "esc.safety.qd_max_rad_s: expected a list of exactly 7 items",
    ),
    (["--set", "esc.pid.kp=fast", "session", SHORT], "esc.pid.kp: expected a list of a number"),
    (["session"], "the following arguments are required: task"),
]


@pytest.mark.parametrize(("args", "expect"), SESSION_BAD_INPUTS)
def test_bad_session_input_is_one_line_exit_2_nothing_started(
    tmp_path: Path, args: list[str], expect: str
) -> None:
    from redistro.ipc import names

    task = tmp_path / "bad.yaml"
    task.write_text("task: t\nkind: self_calibration\nrobots: [r1, r7]\n")
    args = [a.replace("{task}", str(task)) for a in args]
    runtime = names.runtime_dir()
    before = set(os.listdir(runtime)) if runtime.exists() else set()
    shm_before = {e for e in os.listdir("/dev/shm") if "redistro" in e}
    done = run_cli("--set", f"session.runs_dir={tmp_path / 'runs'}", *args)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("redistro: error: "), done.stderr
    assert expect in lines[0], lines[0]
    assert done.stdout == ""
    assert {e for e in os.listdir("/dev/shm") if "redistro" in e} == shm_before
    assert (set(os.listdir(runtime)) if runtime.exists() else set()) == before
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_or_sigterm_freezes_and_ends_in_order(tmp_path: Path, sig: int) -> None:
    out = tmp_path / "run"
    with _session(tmp_path, out) as (proc, sid):
        attach_running(sid, "esc.r2", min_cycle=60, timeout=60).close()
        proc.send_signal(sig)
        sent_ns = time.monotonic_ns()
    assert proc.returncode == 1
    summary = _summary(out)
    assert summary["result"] == "abnormal"
    name = signal.Signals(sig).name
    for r in ("r1", "r2"):
        node = summary["nodes"][f"esc.{r}"]
        assert node["reason"] == f"interrupted by {name}", node["reason"]
        assert any(t >= sent_ns for t in node["freeze_monotonic_ns"]), node  # frozen on the way
        assert all(w["exit"] == "exited with code 0" for w in node["workers"]), node["workers"]
        # the calibration did not finish: the positions are recorded as unknown
        assert summary["positions"][r]["known_at_end"] is False


def test_a_plant_that_dies_starting_stops_the_nodes_started_beside_it(
    calibrated: Path, tmp_path: Path
) -> None:
    """The ESCs start beside the plant and wait for it before they open their
    drivers. A plant that dies in its start-up ends the session with its
    error (one line, exit 1); the waiting ESCs end without having touched a
    robot (their positions files stay clean), the SSC started beside them
    is stopped too, and nothing is left behind."""
    from tests.helpers import copy_runs, session_entries

    runs = copy_runs(calibrated, tmp_path)
    out = tmp_path / "run"
    done = run_cli(
        "--set", f"session.runs_dir={runs}", "session", "tasks/fault_drill.yaml",
        "--out", str(out), env={"REDISTRO_HOOKS": "tests.integration.plant_never_starts"},
    )  # fmt: skip
    assert done.returncode == 1, done.stdout + done.stderr
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("redistro: plant failed to start: RuntimeError: this plant never"), last
    assert "starting esc.r1, esc.r2" in done.stdout and "plant running" not in done.stdout
    messages = (out / "messages.log").read_text()
    for robot in ("r1", "r2"):  # started, and waiting for the plant
        assert f"[esc.{robot}/manager] abnormal: interrupted by SIGTERM during start-up" in messages
    assert "[ssc/manager] abnormal: interrupted by SIGTERM" in messages
    assert not (out / "summary.json").exists()
    for robot in ("r1", "r2"):
        assert _positions_clean(runs, robot)
    sid = done.stdout.split()[1]
    assert session_entries(sid) == []
    assert subprocess.run(["pgrep", "-f", sid], capture_output=True).stdout == b""

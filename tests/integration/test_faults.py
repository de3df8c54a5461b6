"""The fault harness against a real session (a few scenarios; `redistro faults`
runs the whole catalogue)."""

from __future__ import annotations

import shutil
from pathlib import Path

from redistro.faults.catalogue import CATALOGUE
from tests.helpers import load_json, run_cli


def test_the_harness_breaks_a_session_and_measures_the_outcome(
    calibrated: Path, tmp_path: Path
) -> None:
    runs = tmp_path / "runs"
    shutil.copytree(calibrated, runs)
    out = tmp_path / "faults.json"
    done = run_cli(
        "--set",
        f"session.runs_dir={runs}",
        "faults",
        "--only",
        "kill-esc.r2-sender",
        "--only",
        "stop-ssc-worker",
        "--json",
        str(out),
        timeout=600,
    )
    rows = {r["name"]: r for r in load_json(out)["scenarios"]}
    assert list(rows) == ["kill-esc.r2-sender", "stop-ssc-worker"], done.stdout
    kill, stop = rows["kill-esc.r2-sender"], rows["stop-ssc-worker"]
    # a dead worker: seen by its manager through its pidfd within 2 cycles
    assert kill["got"] == "abnormal" and "worker sender" in kill["cause"], kill
    assert kill["detected_by"] == "esc.r2" and kill["detection_cycles"] <= 2, kill
    # a hung worker: seen when its heartbeat is the limit (25 cycles) old
    assert stop["detected_by"] == "ssc" and "missed 25 heartbeats" in stop["cause"], stop
    assert 24 <= stop["detection_cycles"] <= 27, stop
    for row in rows.values():
        assert row["all_frozen"] and row["estop_every_node"], row
        assert row["processes_left"] == 0 and row["ipc_left"] == [], row
        assert row["passed"], row
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert "2 of 2 scenarios passed" in done.stdout


def test_an_unknown_scenario_is_refused_in_one_line() -> None:
    done = run_cli("faults", "--only", "kill-nothing", timeout=60)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "--only kill-nothing: no such scenario" in lines[0], done.stderr
    listed = run_cli("faults", "--list", timeout=60)
    assert listed.returncode == 0
    assert len(listed.stdout.strip().splitlines()) == len(CATALOGUE)

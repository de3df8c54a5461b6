"""Ctrl-C to the fault harness ends it in order: the session it is breaking
ends (its owner takes the SIGINT: the robots frozen, nothing left behind),
no further scenario starts, the table so far is written."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest

from tests.helpers import copy_runs, load_json, start_cli, wait_for

pytestmark = pytest.mark.slow


def test_ctrl_c_ends_the_harness_and_its_session_in_order(calibrated: Path, tmp_path: Path) -> None:
    runs = copy_runs(calibrated, tmp_path)
    out = tmp_path / "faults.json"
    harness = start_cli(
        "--set", f"session.runs_dir={runs}", "faults", "--only", "records-forged",
        "--only", "records-malformed", "--json", str(out),
    )  # fmt: skip
    try:
        # the first scenario's drill is running: its plant has written its config
        started = runs / "faults" / "records-forged" / "plant.config.json"
        wait_for(started.exists, 60, "the drill's session to start")
        harness.send_signal(signal.SIGINT)
        stdout, stderr = harness.communicate(timeout=60)
    finally:
        if harness.poll() is None:
            harness.kill()
            harness.communicate()
    assert harness.returncode == 128 + signal.SIGINT, stdout[-2000:] + stderr[-2000:]
    assert "stopped by SIGINT after 1 of 2 scenarios" in stdout, stdout[-2000:]
    assert "Traceback" not in stderr, stderr[-2000:]
    doc = load_json(out)
    assert doc["stopped_by"] == "SIGINT"
    (row,) = doc["scenarios"]
    assert row["name"] == "records-forged" and row["interrupted"], row
    assert row["processes_left"] == 0 and row["ipc_left"] == [], row
    summary = load_json(runs / "faults" / "records-forged" / "summary.json")
    assert summary["result"] != "ok", summary["result"]  # ended by the stop, not run out

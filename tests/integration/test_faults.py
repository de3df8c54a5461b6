"""The fault harness against real sessions: the scenarios whose verdict is a time.

One `redistro faults --json` run breaks real sessions (plant, ESCs, SSC,
DDMs) scenario by scenario, in real time: each scenario whose verdict is a
detection within its bound, or a session keeping time under load
(``Scenario.timed``). The others run in lockstep beside the unit tests
(`test_faults_lockstep.py`). Each test below checks one scenario's row.
The run takes a while (about 6 minutes on two vCPUs, the CPU-hog peg
insertion included), so it happens once per test session. A scenario that
fails is run again, twice at most (`--retries 2`: 10 ms bounds on a noisy
virtual machine); its row keeps the failed attempts, and the table test
prints them.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

from redistro.faults.catalogue import CATALOGUE, by_name
from redistro.faults.runner import reason_matches
from tests.helpers import load_json, run_cli

# the campaign runs in the first test's set-up (the module's fixture)
pytestmark = [pytest.mark.slow, pytest.mark.timeout(5400)]
TIMED = [s.name for s in CATALOGUE if s.timed]


def campaign(calibrated: Path, tmp: Path, *args: str, timeout: float) -> dict[str, Any]:
    """``redistro faults`` (``args`` before and after the command's name,
    split at ``faults``) from a copy of the calibrated runs folder: its
    rows by name, the finished process and the JSON document."""
    runs = tmp / "runs"
    shutil.copytree(calibrated, runs)
    out = tmp / "faults.json"
    at = args.index("faults")
    done = run_cli(
        *args[:at], "--set", f"session.runs_dir={runs}", *args[at:], "--json", str(out),
        "--seed", "1", "--retries", "2", timeout=timeout,
    )  # fmt: skip
    doc = load_json(out)
    return {"rows": {r["name"]: r for r in doc["scenarios"]}, "done": done, "doc": doc}


@pytest.fixture(scope="module")
def table(calibrated: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    only = [a for name in TIMED for a in ("--only", name)]
    tmp = tmp_path_factory.mktemp("faults")
    return campaign(calibrated, tmp, "faults", *only, timeout=4800)


def _row(table: dict[str, Any], name: str) -> dict[str, Any]:
    done: subprocess.CompletedProcess[str] = table["done"]
    assert name in table["rows"], done.stdout[-3000:] + done.stderr[-3000:]
    row: dict[str, Any] = table["rows"][name]
    return row


@pytest.mark.parametrize("name", TIMED)
def test_scenario(table: dict[str, Any], name: str) -> None:
    check_row(name, _row(table, name))


def check_row(name: str, row: dict[str, Any]) -> None:
    """The verdicts of one scenario's row, as its catalogue entry expects."""
    sc = by_name(name)
    # nothing is ever left behind
    assert row.get("processes_left", 0) == 0 and row.get("ipc_left", []) == [], row
    assert row["got"] in sc.expect, row
    # no manager fails on an error of its own (a stopped one continued included)
    assert not row.get("manager_errors"), row
    assert reason_matches(sc.reason, row.get("cause", "")), row
    fault = "ok" not in sc.expect and "refused" not in sc.expect and "failed" not in sc.expect
    if fault:
        # detected within its bound; every robot frozen (a dead plant freezes nothing)
        assert row["detected"], row
        if sc.limit in ("death", "guard"):  # in the detecting node's own cycles
            assert row.get("detection_node_cycles", row["detection_cycles"]) <= 2, row
        if sc.kind != "process" or sc.node != "plant":
            assert row["all_frozen"] and row["estop_every_node"], row
    if "refused" in sc.expect:
        assert row["exit_code"] == 2 and row["one_line"] and not row["plant_started"], row
    if sc.count:
        assert row["count"][sc.count] > 0, row
    assert row["passed"], row


def test_the_table_and_the_exit_code(table: dict[str, Any]) -> None:
    check_table(table, TIMED)


def check_table(table: dict[str, Any], names: list[str]) -> None:
    """Every scenario asked for has its row, with the table's fields, and passed."""
    done: subprocess.CompletedProcess[str] = table["done"]
    rows = table["rows"]
    assert list(rows) == names
    for row in rows.values():  # the fields the issue asks for, in every row
        for key in ("name", "passed", "expected", "got", "cause", "processes_left", "ipc_left"):
            assert key in row, (key, row)
    n = len(names)
    assert f"{n} of {n} scenarios passed" in done.stdout, done.stdout[-3000:]
    for row in rows.values():
        for bad in row.get("failed_attempts", []):  # shown with -s / -rA, not hidden
            print(f"{row['name']}: attempt failed first: got {bad['got']}, {bad.get('cause')}")
    assert done.returncode == 0


def test_a_dead_esc_manager_leaves_its_robot_frozen(table: dict[str, Any]) -> None:
    """The boards' watchdog: nobody writes r2's DAC any more, the chassis cuts it."""
    row = _row(table, "kill-esc.r2-manager")
    assert "r2" in row["frozen"] and "r2" in row["watchdog_trips"], row


def test_an_unknown_scenario_is_refused_in_one_line() -> None:
    done = run_cli("faults", "--only", "kill-nothing", timeout=60)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "--only kill-nothing: no such scenario" in lines[0], done.stderr
    listed = run_cli("faults", "--list", timeout=60)
    assert listed.returncode == 0
    assert len(listed.stdout.strip().splitlines()) == len(CATALOGUE)

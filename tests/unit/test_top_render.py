"""`redistro top`'s table: a busy node's figures fit an 80-column terminal."""

from __future__ import annotations

from typing import Any

from rich.console import Console

from redistro.top import render


def _doc() -> dict[str, Any]:
    procs = [
        {
            "name": name,
            "role": name,
            "pid": 4194303,
            "state": "routine",
            "sched": "rr/19",
            "heartbeat_age_cycles": 30,
            "late_us": 12345.6,
            "busy_us": 2345.6,
            "cycles": 1234567,
            "overruns": 12345,
            "skipped": 123,
        }
        for name in ("acquisition", "calibration", "pid", "sender", "recorder", "ddm")
    ]
    node = {
        "node": "esc.r1",
        "state": "routine",
        "cycle": 1234567,
        "measured_hz": 199.9,
        "rate_hz": 200.0,
        "manager_late_us": 50.1,
        "overruns": 12,
        "starving_index": 3,
        "estop": 0,
        "manager_pid": 4194302,
        "heartbeat_limit_cycles": 25,
        "processes": procs,
    }
    return {"sessions": [{"session": "s", "owner_pid": 1, "nodes": [node], "other_processes": []}]}


def test_the_process_table_fits_80_columns() -> None:
    console = Console(width=80, record=True, color_system=None)
    console.print(render(_doc()))
    text = console.export_text()
    assert "…" not in text, text
    rows = [line for line in text.splitlines() if line.startswith("calibration ")]
    assert len(rows) == 1 and "1234567" in rows[0] and "12345.6" in rows[0], text
    assert "hb age" in text and "overruns" in text


def test_the_scheduling_column_names_what_was_granted() -> None:
    from redistro.ipc.sched import POLICY_CODES
    from redistro.top import sched_text

    assert sched_text(POLICY_CODES["SCHED_RR"], 19, 0) == "rr/19"
    assert sched_text(POLICY_CODES["nice"], 0, -9) == "nice/-9"
    assert sched_text(POLICY_CODES["default"], 0, 0) == "default"
    assert sched_text(POLICY_CODES["SCHED_BATCH"], 0, 0) == "batch"


def test_names_and_fault_texts_are_printed_as_they_are() -> None:
    """A fault text quoting a segment named like markup is not markup."""
    doc = _doc()
    node = doc["sessions"][0]["nodes"][0]
    node["fault"], node["fault_text"] = "unsafe", "segment [/x] [bold]tilt[/bold] tripped"
    console = Console(width=300, record=True, color_system=None)
    console.print(render(doc))
    assert "segment [/x] [bold]tilt[/bold] tripped" in console.export_text()

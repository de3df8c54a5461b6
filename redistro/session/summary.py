"""The summary: ``summary.json`` of a session, built from its nodes' and
the plant's results, and the time budgets of a task."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from redistro.config.task import Task
from redistro.esc.plan import task_seconds
from redistro.process.manager import iso_time

RESULTS = ("ok", "unsafe", "starving", "estop", "abnormal")


# The slowest the simulated plant is expected to run beside a strategy
# session's nodes [share of real time]: on two vCPUs their real-time load
# leaves the plant 0.2-0.5 (0.35-0.50 over a whole peg insertion, 0.2 in contact).
MIN_STRATEGY_RTF = 0.15


def budget_s(task: Task) -> float:
    """How long a task's nodes may run [s of the plant's clock]: the task
    counts on the boards' sample clock, so its budget does too (a loaded host
    runs the simulated plant at 0.1-0.9 of real time, which is no fault)."""
    return 1.5 * task_seconds(task) + 10.0


def wall_budget_s(task: Task) -> float:
    """The same on the wall clock [s], for a node without the plant's clock
    (`redistro node`): the plant at 0.4-0.9 of real time beside the ESCs
    alone, 0.2-0.5 beside a whole robot group."""
    if task.kind == "strategy":
        return task_seconds(task) / MIN_STRATEGY_RTF + 30.0
    return 1.5 * task_seconds(task) + 10.0


def segment_line(seg: dict[str, Any]) -> str:
    text = f"  {seg['name']:<10} {seg['robot']} {seg['scheme']:<8} {seg['duration_s']:6.2f} s"
    e = seg.get("final_pose_error")
    if e:
        text += f"  pose error {e['position_m'] * 1e3:.2f} mm {e['orientation_rad']:.4f} rad"
    if seg.get("force_rms_error_n") is not None:
        text += (
            f"  force error mean {seg['force_mean_error_n']:.2f} N"
            f" rms {seg['force_rms_error_n']:.2f} N"
        )
    return text


def _first_fault(results: list[dict[str, Any]]) -> dict[str, Any] | None:
    faults = [r for r in results if r.get("result") != "ok"]
    if not faults:
        return None
    # the earliest fault is the cause; faults of nodes stopped because of it follow
    return min(faults, key=lambda r: r.get("fault_monotonic_ns", 2**63))


def build_summary(
    task: Task,
    results: list[dict[str, Any]],
    plant: dict[str, Any],
    started: float,
    ended: float,
    run_dir: Path,
) -> dict[str, Any]:
    fault = _first_fault(results)
    if not results:
        fault = {"result": "abnormal", "reason": "no node ran"}
    if fault is None and plant.get("state") == "failed":
        fault = {"result": "abnormal", "reason": f"plant failed: {plant.get('error', '')}"}
    result = fault["result"] if fault else "ok"
    if result not in RESULTS:
        result = "abnormal"
    nodes: dict[str, Any] = {}
    for r in results:
        nodes[str(r.get("node"))] = {
            "robot": r.get("robot"),
            "result": r.get("result"),
            "reason": r.get("reason", ""),
            "rate_hz": r.get("rate_hz"),
            "cycles": r.get("cycles", 0),
            "overruns": r.get("overrun_cycles", 0),
            "missed_ticks": r.get("missed_ticks", 0),
            "missed_heartbeats": r.get("missed_heartbeats", 0),
            "lateness_us": r.get("lateness_us", {}),
            "makespan_us": r.get("makespan_us", {}),
            "cpu_percent": r.get("cpu_percent"),
            "manager": r.get("manager", {}),
            "workers": [
                {
                    k: w.get(k)
                    for k in (
                        "name",
                        "pid",
                        "cycles",
                        "overruns",
                        "stage_timeouts",
                        "lateness_us",
                        "compute_us",
                        "step_cpu_us",
                        "cpu_s",
                        "cpu_percent",
                        "scheduling",
                        "exit",
                    )
                }
                for w in r.get("workers", [])
            ],
            "freeze_monotonic_ns": r.get("freeze_monotonic_ns", []),
            "fault_monotonic_ns": r.get("fault_monotonic_ns"),
            "fault_cycle": r.get("fault_cycle"),
            "messages": r.get("messages", []),
        }
    summary: dict[str, Any] = {
        "task": task.task,
        "task_file": task.source,
        "kind": task.kind,
        "robots": task.robots,
        "result": result,
        "reason": fault.get("reason", "") if fault else "",
        "started": iso_time(started),
        "ended": iso_time(ended),
        "run_dir": str(run_dir),
        "nodes": nodes,
    }
    violations = {str(r.get("robot")): r["violation"] for r in results if r.get("violation")}
    if violations:
        summary["violations"] = violations
    summary["positions"] = {str(r.get("robot")): r.get("positions") for r in results}
    if task.kind == "self_calibration":
        true = plant.get("encoder_offset_rad", {})
        cal: dict[str, Any] = {}
        for r in results:
            robot = str(r.get("robot"))
            c = r.get("calibration")
            if not c:
                continue
            rows = []
            for j in range(7):
                found = c["found"][j]
                off = c["offset_found_rad"][j] if found else None
                tru = true.get(robot, [None] * 7)[j]
                err = off - tru if off is not None and tru is not None else None
                rows.append(
                    {
                        "joint": j + 1,
                        "edges": c["edges"][j],
                        "offset_found_rad": off,
                        "offset_true_rad": tru,
                        "error_rad": err,
                    }
                )
            cal[robot] = rows
        summary["calibration"] = cal
    ssc = next((r for r in results if r.get("kind") == "ssc"), None)
    if task.kind == "strategy":
        segs = ssc.get("segments", []) if ssc else []
        summary["segments"] = segs
        depth = float(ssc.get("insertion_depth_m", 0.0)) if ssc else 0.0
        hole_depth = float(ssc.get("hole_depth_m", 0.0)) if ssc else 0.0
        summary["insertion_depth_m"] = depth
        summary["hole_depth_m"] = hole_depth
        summary["inserted"] = bool(ssc) and hole_depth > 0 and abs(depth - hole_depth) <= 0.002
        summary["ddm"] = {
            str(r.get("node")): r.get("ddm") for r in results if r.get("ddm") is not None
        }
    summary["plant"] = {
        k: plant.get(k)
        for k in (
            "state",
            "error",
            "steps",
            "rtf",
            "late_steps",
            "skipped_steps",
            "step_us",
            "physics_us",
            "chassis_us",
            "cpu_s",
            "cpu_percent",
            "max_step_gap_ms",
            "torn_outputs",
            "bad_frames",
            "freezes",
            "watchdog_trips",
        )
        if k in plant
    }
    return summary

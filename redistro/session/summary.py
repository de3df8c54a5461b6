"""The summary: ``summary.json`` of a session, built from its nodes' and
the plant's results, and the time budgets of a task."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from redistro.config.task import Task, insertion_object
from redistro.esc.plan import task_seconds
from redistro.process.manager import iso_time
from redistro.process.result import EscResult, NodeResult
from redistro.session.placed import placed

RESULTS = ("ok", "unsafe", "starving", "estop", "abnormal", "failed")


# The slowest the simulated plant is expected to run beside a strategy
# session's nodes [share of real time]: on two vCPUs their real-time load
# leaves the plant 0.2-0.5 (0.35-0.50 over a whole peg insertion, 0.2 in contact).
MIN_STRATEGY_RTF = 0.15


# what summary.json keeps of the plant's result
PLANT_KEYS = (
    "state",
    "error",
    "kernels",
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
    "grippers",
    "objects",
    "objects_start",
    "watchdog_trips",
    "hole",
    "arms",
    "pegs",
    "in_holes",
)

INSERTED_WITHIN_M = 0.002  # a peg this close to the hole's depth is in
DISAGREE_M = 0.001  # the controller's depth this far from the plant's is flagged


def _inserted(
    summary: dict[str, Any], ran: bool, depth: float, hole_depth: float, pegs: dict[str, Any]
) -> None:
    """``inserted`` from the plant's truth (the deepest a peg's tip went
    into the real hole), the controller's belief beside it
    (``inserted_belief``, from its own kinematics against the hole as
    drawn), and ``belief_disagrees`` when the two depths differ by more
    than DISAGREE_M. Without a plant's peg (a node started alone): the
    belief."""
    belief = ran and hole_depth > 0 and abs(depth - hole_depth) <= INSERTED_WITHIN_M
    truth = max((float(p["depth_m"]) for p in pegs.values()), default=None)
    if truth is None or not ran or hole_depth <= 0:
        summary["inserted"] = belief
        return
    summary["inserted"] = abs(truth - hole_depth) <= INSERTED_WITHIN_M
    summary["inserted_belief"] = belief
    summary["plant_insertion_depth_m"] = round(truth, 6)
    summary["belief_disagrees"] = abs(truth - depth) > DISAGREE_M


def _plant_depths(task: Task, plant: dict[str, Any]) -> dict[str, Any]:
    """The plant's depths for the task's insertion: into an object's hole
    (its first force move relative to ``<object>.hole``), the objects' that
    went into that hole; else the pegs' on the robots' flanges."""
    hole = insertion_object(task)
    if hole:
        got = plant.get("in_holes") or {}
        return {p: d for p, d in got.items() if d.get("hole_of") == hole}
    return dict(plant.get("pegs") or {})


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


def _first_fault(results: list[NodeResult]) -> NodeResult | None:
    faults = [r for r in results if not r.ok]
    if not faults:
        return None
    # the earliest fault is the cause; faults of nodes stopped because of it follow
    return min(faults, key=lambda r: r.fault_monotonic_ns or 2**63)


# The figures of a node's result that summary.json shows, under the result's
# own names, and those it leaves out. Adding a figure: a field on the result
# type (process/result.py), filled by the manager, and its name here.
NODE_FIGURES = (
    "result",
    "reason",
    "kernels",
    "rate_hz",
    "cycles",
    "overruns",
    "missed_ticks",
    "missed_heartbeats",
    "lateness_us",
    "makespan_us",
    "cpu_percent",
    "manager",
    "fault_monotonic_ns",
    "fault_cycle",
    "messages",
)
NODE_LEFT_OUT = frozenset(
    {
        "node",  # the entry's key
        "kind",
        "session_id",
        "started",
        "ended",
        "period_us",
        "routine_s",
        "manager_overruns",
        "worker_overruns",
        "worker_skipped",
        "late_heartbeats",
        "deadline_misses",
        "incomplete_cycles",
        "torn_ticks",
        "idle_slices",
        "manager_work_us",
        "cpu_s",
        "messages_lost",
        "stragglers_killed",
        "workers",  # each under WORKER_FIGURES
        "esc",  # the kinds' own figures: robot, freezes, and the sections below
        "ssc",
    }
)
WORKER_FIGURES = (
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


def node_entry(r: NodeResult) -> dict[str, Any]:
    """A node's entry in ``summary.json`` (its figures under the result's names)."""
    esc = r.esc
    entry: dict[str, Any] = {"robot": r.robot}
    entry.update((k, getattr(r, k)) for k in NODE_FIGURES)
    entry["workers"] = [{k: getattr(w, k) for k in WORKER_FIGURES} for w in r.workers]
    entry["freeze_monotonic_ns"] = esc.freeze_monotonic_ns if esc is not None else []
    return entry


def _calibration(escs: list[EscResult], plant: dict[str, Any]) -> dict[str, Any]:
    true = plant.get("encoder_offset_rad", {})
    cal: dict[str, Any] = {}
    for e in escs:
        c, robot = e.calibration, e.robot
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
    return cal


def _exchange(r: NodeResult) -> dict[str, Any] | None:
    """A node's DDM exchange figures (an ESC's one robot, the SSC's each)."""
    if r.esc is not None:
        return r.esc.ddm
    return r.ssc.ddm if r.ssc is not None else None


def build_summary(
    task: Task,
    results: list[NodeResult],
    plant: dict[str, Any],
    started: float,
    ended: float,
    run_dir: Path,
) -> dict[str, Any]:
    """``summary.json``: the one place the nodes' results become the session's."""
    first = _first_fault(results)
    result, reason = (first.result, first.reason) if first is not None else ("ok", "")
    if not results:
        result, reason = "abnormal", "no node ran"
    if result == "ok" and plant.get("state") == "failed":
        result, reason = "abnormal", f"plant failed: {plant.get('error', '')}"
    if result not in RESULTS:
        result = "abnormal"
    summary: dict[str, Any] = {
        "task": task.task,
        "task_file": task.source,
        "kind": task.kind,
        "robots": task.robots,
        "result": result,
        "reason": reason,
        "started": iso_time(started),
        "ended": iso_time(ended),
        "run_dir": str(run_dir),
        "nodes": {r.node: node_entry(r) for r in results},
    }
    escs = [r.esc for r in results if r.esc is not None]
    violations = {e.robot: e.violation for e in escs if e.violation}
    if violations:
        summary["violations"] = violations
    summary["positions"] = {e.robot: e.positions for e in escs}
    if task.kind == "self_calibration":
        summary["calibration"] = _calibration(escs, plant)
    ssc = next((r.ssc for r in results if r.ssc is not None), None)
    if task.kind == "strategy":
        summary["segments"] = ssc.segments if ssc else []
        depth = ssc.insertion_depth_m if ssc else 0.0
        hole_depth = ssc.hole_depth_m if ssc else 0.0
        summary["insertion_depth_m"] = depth
        summary["hole_depth_m"] = hole_depth
        if ssc is not None and ssc.search:
            summary["search"] = ssc.search
        if ssc is not None and ssc.clearance:
            summary["clearance"] = ssc.clearance  # the controller's; the plant's: plant.arms
        if ssc is not None and ssc.operator:
            summary["operator"] = ssc.operator  # redistro ctl: commands accepted, refused
        _inserted(summary, ssc is not None, depth, hole_depth, _plant_depths(task, plant))
        summary.update(placed(task, plant))  # (a task that carries an object)
        summary["ddm"] = {r.node: d for r in results if (d := _exchange(r))}
    summary["plant"] = {k: plant.get(k) for k in PLANT_KEYS if k in plant}
    return summary

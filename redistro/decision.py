"""The decision stage: ``redistro session TASK`` runs one task from power-on to power-off.

It checks the task against the config (bad input ends here: nothing has
started), starts the plant (system on), launches the nodes the task needs,
prints progress while they run, ends them, powers off, and writes the run
folder: ``summary.json``, ``messages.log``, ``plant.json`` and a copy of
the final positions files. Exit code 0 only when the result is ``ok``.
"""

from __future__ import annotations

import contextlib
import logging
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from redistro.config.hardware import load_hardware
from redistro.config.model import Config
from redistro.config.task import Task, load_task
from redistro.drivers import positions
from redistro.errors import IPCError, LayoutError, RedistroError
from redistro.esc.plan import esc_spec, task_seconds
from redistro.ipc import session as ipc_session
from redistro.process.manager import iso_time
from redistro.process.owner import run_nodes, write_json
from redistro.process.spec import NodeSpec

log = logging.getLogger(__name__)
RESULTS = ("ok", "unsafe", "starving", "abnormal")


def positions_file(cfg: Config, robot: str) -> Path:
    return Path(cfg.session.runs_dir) / cfg.session.positions_dir / f"{robot}.json"


def check_positions(cfg: Config, task: Task) -> None:
    """Motion needs known joint positions, unless the task is the self-calibration."""
    if task.kind == "self_calibration":
        return
    for r in task.robots:
        try:
            positions.read(positions_file(cfg, r), [r])
        except positions.PositionsUnknown as exc:
            raise RedistroError(
                f"motion refused: {exc}; run tasks/self_calibration.yaml first"
            ) from None


class _Progress:
    """Prints, about once a second, where each ESC is in its segments."""

    def __init__(self, session_id: str, specs: list[NodeSpec], out: Callable[[str], None]) -> None:
        self.session_id = session_id
        self.specs = specs
        self.out = out
        self.t0 = time.monotonic()
        self.next = self.t0 + 1.0
        self.lds: dict[str, Any] = {}
        self.blocks: dict[str, Any] = {}

    def __call__(self) -> None:
        now = time.monotonic()
        if now < self.next:
            return
        self.next = now + 1.0
        try:
            self._show(now)
        except Exception:  # progress is for people: it must never end a session
            log.debug("progress display failed", exc_info=True)

    def _show(self, now: float) -> None:
        from redistro.localdata import LocalData

        parts = []
        for spec in self.specs:
            ld = self.lds.get(spec.node)
            if ld is None:
                try:
                    ld = self.lds[spec.node] = LocalData.attach(self.session_id, spec.node)
                except (IPCError, LayoutError, OSError):
                    parts.append(f"{spec.node} starting")
                    continue
            blocks = self.blocks.get(spec.node)
            if blocks is None:
                blocks = self.blocks[spec.node] = (ld.block("setpoint", 0), ld.block("manager"))
            try:
                sp = blocks[0].read()
                mgr = blocks[1].read()
            except Exception:
                continue
            segs = spec.workers[0].params["segments"]
            k = int(sp["segment"])
            if int(sp["done"]):
                parts.append(f"{spec.node} done")
            elif k == 0:
                parts.append(f"{spec.node} cycle {int(mgr['cycle'])}")
            else:
                seg = segs[k - 1]
                parts.append(
                    f"{spec.node} {k}/{len(segs)} {seg['name']} "
                    f"{float(sp['segment_t_s']):5.1f}/{seg['duration_s']:g} s"
                )
        self.out(f"[{now - self.t0:6.1f} s] " + " | ".join(parts))

    def close(self) -> None:
        self.blocks.clear()
        for ld in self.lds.values():
            with contextlib.suppress(Exception):
                ld.close()
        self.lds.clear()


def run_session(
    cfg: Config,
    task_path: str,
    *,
    config_path: str | None,
    overrides: list[str],
    out_dir: str | None = None,
    say: Callable[[str], None] | None = None,
) -> int:
    from redistro.plant.launch import PlantProcess

    say = say or (lambda text: print(text, flush=True))
    task = load_task(task_path, cfg)
    hardware = load_hardware(cfg)
    check_positions(cfg, task)
    runs = Path(cfg.session.runs_dir)
    for name in ipc_session.reap():
        print(f"reaped {name} (left by a dead session)", file=sys.stderr)
    started = time.time()
    node_results: list[dict[str, Any]] = []
    plant_result: dict[str, Any] = {}
    with ipc_session.Session.create() as s:
        run_dir = Path(out_dir) if out_dir else runs / s.id
        run_dir.mkdir(parents=True, exist_ok=True)
        plant_overrides = list(overrides)
        if not cfg.plant.pose_file:
            plant_overrides.append(f"plant.pose_file={runs / cfg.session.plant_pose_file}")
        say(f"session {s.id}")
        say(f"task {task.task} ({task.kind}) on {', '.join(task.robots)}; run folder {run_dir}")
        plant = PlantProcess.start(s, run_dir, config=config_path, overrides=plant_overrides)
        say(f"plant running ({cfg.plant.backplane} backplane, {cfg.plant.physics_hz:g} Hz)")
        try:
            order = task.calibration.order if task.kind == "self_calibration" else "together"
            groups = [task.robots] if order == "together" else [[r] for r in task.robots]
            for group in groups:
                specs = [
                    esc_spec(
                        cfg,
                        task,
                        r,
                        hardware[r],
                        s.id,
                        config_path=config_path,
                        overrides=overrides,
                        positions_file=str(positions_file(cfg, r)),
                        messages_path=str(run_dir / "messages.log"),
                    )
                    for r in group
                ]
                say(f"starting {', '.join(sp.node for sp in specs)} at {cfg.esc.rate_hz:g} Hz")
                progress = _Progress(s.id, specs, say)
                try:
                    results = run_nodes(
                        specs,
                        s,
                        budget_s=1.5 * task_seconds(task) + 10.0,
                        on_wait=progress,
                        keep=frozenset({plant.pid}),
                    )
                finally:
                    progress.close()
                node_results += results
                for r in results:
                    say(f"{r.get('node')}: {r.get('result')} {r.get('reason', '')}".rstrip())
                if any(r.get("result") != "ok" for r in results):
                    break
        finally:
            plant.stop()
            plant_result = plant.result()
            say("plant powered off")
    summary = build_summary(task, node_results, plant_result, started, time.time(), run_dir)
    for robot in task.robots:
        src = positions_file(cfg, robot)
        if src.exists():
            shutil.copyfile(src, run_dir / f"positions.{robot}.json")
    write_json(run_dir / "summary.json", summary)
    say(f"result: {summary['result']}" + (f" ({summary['reason']})" if summary["reason"] else ""))
    if "calibration" in summary:
        for robot, joints in summary["calibration"].items():
            errs = [j["error_rad"] for j in joints if j["error_rad"] is not None]
            worst = max((abs(e) for e in errs), default=float("nan"))
            say(f"{robot}: {len(errs)}/7 zero offsets found, worst error {worst:.2e} rad")
    say(f"wrote {run_dir / 'summary.json'}")
    return 0 if summary["result"] == "ok" else 1


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
                        "scheduling",
                        "exit",
                    )
                }
                for w in r.get("workers", [])
            ],
            "freeze_monotonic_ns": r.get("freeze_monotonic_ns", []),
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
    summary["plant"] = {
        k: plant.get(k)
        for k in ("state", "error", "steps", "rtf", "late_steps", "skipped_steps", "freezes")
        if k in plant
    }
    return summary

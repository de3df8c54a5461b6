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
from redistro.errors import ConfigError, IPCError, LayoutError
from redistro.esc.plan import esc_spec, task_seconds
from redistro.ipc import session as ipc_session
from redistro.process.manager import iso_time
from redistro.process.owner import run_nodes, write_json
from redistro.process.spec import NodeSpec

log = logging.getLogger(__name__)
RESULTS = ("ok", "unsafe", "starving", "estop", "abnormal")


def positions_file(cfg: Config, robot: str) -> Path:
    return Path(cfg.session.runs_dir) / cfg.session.positions_dir / f"{robot}.json"


def plant_overrides(cfg: Config, overrides: list[str]) -> list[str]:
    """The plant's config overrides: the arms' pose is kept between power-offs
    in the runs folder (the positions files hold only while the arms stay put)."""
    out = list(overrides)
    if not cfg.plant.pose_file:
        out.append(f"plant.pose_file={Path(cfg.session.runs_dir) / cfg.session.plant_pose_file}")
    return out


def unknown_positions(cfg: Config, task: Task) -> dict[str, str]:
    """Robots of the task whose joint positions are not known, and why."""
    out: dict[str, str] = {}
    for r in task.robots:
        try:
            positions.read(positions_file(cfg, r), [r])
        except positions.PositionsUnknown as exc:
            out[r] = str(exc)
    return out


def check_positions(cfg: Config, task: Task) -> None:
    """Motion needs known joint positions, unless the task is the self-calibration
    (or a strategy task that runs one first when they are unknown)."""
    if task.kind == "self_calibration":
        return
    if task.kind == "strategy" and task.calibrate_if_needed:
        return
    for why in unknown_positions(cfg, task).values():
        raise ConfigError(f"motion refused: {why}; run tasks/self_calibration.yaml first")


def check_motion(cfg: Config, task: Task) -> None:
    """Every recorded position inside the joint limits (a positions file
    beyond them cannot be right), every joint goal inside them less the
    margin, every joint move within the speed limit (redistro/config/limits.py)."""
    from redistro.config.limits import joint_limits, task_motion_problems

    limits = joint_limits(cfg)
    start: dict[str, list[float]] = {}
    for r in task.robots:
        path = positions_file(cfg, r)
        try:
            q = positions.read(path, [r]).q_rad[r]
        except positions.PositionsUnknown:
            continue
        problem = limits.outside(q, margin=False)
        if problem:
            raise ConfigError(
                f"{path}: q_rad.{r}: {problem}; the file cannot be right "
                "(run tasks/self_calibration.yaml)"
            )
        start[r] = q
    for problem in task_motion_problems(cfg, task, start):
        raise ConfigError(problem)


class Progress:
    """Where each node is in its segments: a progress bar per node with the
    current segment on a terminal (rich), else a plain line about once a second."""

    def __init__(
        self,
        session_id: str,
        specs: list[NodeSpec],
        out: Callable[[str], None],
        live: bool | None = None,
    ) -> None:
        self.session_id = session_id
        self.specs = specs
        self.out = out
        self.t0 = time.monotonic()
        self.next = self.t0 + 1.0
        self.lds: dict[str, Any] = {}
        self.blocks: dict[str, Any] = {}
        self.ssc_segments: list[tuple[str, float]] = []
        self.live = sys.stdout.isatty() if live is None else live
        self.bars: Any = None
        self.tasks: dict[str, Any] = {}

    def __call__(self) -> None:
        now = time.monotonic()
        if now < self.next:
            return
        self.next = now + (0.25 if self.live else 1.0)
        try:
            self._show(now)
        except Exception:  # progress is for people: it must never end a session
            log.debug("progress display failed", exc_info=True)

    def _show(self, now: float) -> None:
        rows = [self._node(spec) for spec in self.specs]
        if not self.live:
            self.out(f"[{now - self.t0:6.1f} s] " + " | ".join(r[0] for r in rows))
            return
        if self.bars is None:
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

            self.bars = Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                TextColumn("{task.percentage:>3.0f}%"),
                TimeElapsedColumn(),
            )
            self.bars.start()
        for spec, (text, done_s, total_s) in zip(self.specs, rows, strict=True):
            task = self.tasks.get(spec.node)
            if task is None:
                task = self.tasks[spec.node] = self.bars.add_task(text, total=total_s or 1.0)
            self.bars.update(task, description=text, completed=done_s)

    def _node(self, spec: NodeSpec) -> tuple[str, float, float]:
        """(text, seconds of segments done, seconds of all segments)."""
        from redistro.localdata import LocalData

        segs: list[dict[str, Any]]
        if spec.kind == "ssc":
            segs = [{"name": n, "duration_s": d} for n, d in self.ssc_segments]
        else:
            segs = list(spec.workers[0].params.get("segments", []))
        total = float(sum(float(s["duration_s"]) for s in segs))
        ld = self.lds.get(spec.node)
        if ld is None:
            try:
                ld = self.lds[spec.node] = LocalData.attach(self.session_id, spec.node)
            except (IPCError, LayoutError, OSError):
                return f"{spec.node} starting", 0.0, total
        blocks = self.blocks.get(spec.node)
        if blocks is None:
            blocks = self.blocks[spec.node] = (ld.block("setpoint", 0), ld.block("manager"))
        try:
            sp = blocks[0].read()
            mgr = blocks[1].read()
        except Exception:
            return f"{spec.node}", 0.0, total
        if spec.kind == "ssc":
            return self._ssc(spec, ld, int(mgr["cycle"]), total)
        k = int(sp["segment"])
        if int(sp["done"]):
            return f"{spec.node} done", total, total
        if k == 0:
            return f"{spec.node} cycle {int(mgr['cycle'])}", 0.0, total
        seg = segs[k - 1]
        t = float(sp["segment_t_s"])
        dur = float(seg["duration_s"])
        done = sum(float(s["duration_s"]) for s in segs[: k - 1]) + min(t, dur)
        text = f"{spec.node} {k}/{len(segs)} {seg['name']} {t:5.1f}/{seg['duration_s']:g} s"
        if k == len(segs) and t > dur:
            text = f"{spec.node} {k}/{len(segs)} {seg['name']} done, settling"
        return text, done, total

    def _ssc(self, spec: NodeSpec, ld: Any, cycle: int, total: float) -> tuple[str, float, float]:
        names = self.ssc_segments
        for i in range(len(spec.robots)):
            pl = ld.block("plan", i).read()
            if not int(pl["moving"]) and not int(pl["done"]):
                continue
            k = int(pl["segment"])
            if int(pl["done"]):
                return "ssc done", total, total
            if 1 <= k <= len(names):
                name, dur = names[k - 1]
                t = float(pl["segment_t_s"])
                done = sum(d for _, d in names[: k - 1]) + min(t, dur)
                text = f"ssc {k}/{len(names)} {name} ({spec.robots[i]}) {t:5.1f}/{dur:g} s"
                return text, done, total
        return f"ssc cycle {cycle}", 0.0, total

    def close(self) -> None:
        if self.bars is not None:
            with contextlib.suppress(Exception):
                self.bars.stop()
            self.bars = None
        self.blocks.clear()
        for ld in self.lds.values():
            with contextlib.suppress(Exception):
                ld.close()
        self.lds.clear()


def check_key(cfg: Config, needed: bool = False) -> None:
    """``ddm.key_file`` readable and private (needed: nodes started alone
    share no session folder, so they need it)."""
    from redistro.ddm import record as wire

    if not cfg.ddm.key_file:
        if needed:
            raise ConfigError(
                f"{cfg.origin('ddm.key_file')}: ddm.key_file: nodes started alone need a "
                "shared key file (32 random bytes as hex, mode 0600, the same on every node; "
                "e.g. python3 -c 'import os; print(os.urandom(32).hex())' > link.key)"
            )
        return
    try:
        wire.load_key(cfg.ddm.key_file)
    except ValueError as exc:
        raise ConfigError(f"{cfg.origin('ddm.key_file')}: ddm.key_file: {exc}") from None


def preflight(cfg: Config, task_path: str) -> Task:
    """Every check a session makes before it reaps, creates or starts anything:
    the task against the config, the hardware files and their ratings, the
    recorded joint positions, joint goals and speeds against the limits, and
    the Cartesian goals' reach. ConfigError (one line) on the first problem."""
    task = load_task(task_path, cfg)
    load_hardware(cfg)
    check_key(cfg)
    check_positions(cfg, task)
    check_motion(cfg, task)
    from redistro.ssc.reach import unreachable_goals

    for problem in unreachable_goals(cfg, task):
        raise ConfigError(problem)
    return task


def run_session(
    cfg: Config,
    task_path: str,
    *,
    config_path: str | None,
    overrides: list[str],
    out_dir: str | None = None,
    say: Callable[[str], None] | None = None,
    around_task: Callable[[], contextlib.AbstractContextManager[Any]] | None = None,
) -> int:
    """around_task: a context the task itself runs in (not a self-calibration
    run first): what ``redistro bench group`` measures."""
    say = say or (lambda text: print(text, flush=True))
    task = preflight(cfg, task_path)
    for name in ipc_session.reap():
        print(f"reaped {name} (left by a dead session)", file=sys.stderr)
    if task.kind == "strategy" and task.calibrate_if_needed:
        unknown = unknown_positions(cfg, task)
        if unknown:
            robots = [r for r in task.robots if r in unknown]
            say(f"joint positions unknown ({'; '.join(unknown.values())})")
            say(f"self-calibration of {', '.join(robots)} first")
            cal = Task(
                task=f"self_calibration (before {task.task})",
                kind="self_calibration",
                robots=robots,
                source=task.source,
            )
            cal_dir = str(Path(out_dir) / "self_calibration") if out_dir else None
            rc = _run_task(
                cfg, cal, config_path=config_path, overrides=overrides, out_dir=cal_dir, say=say
            )
            if rc != 0:
                say(f"{task.task} not started: the self-calibration did not end ok")
                return rc
    with around_task() if around_task is not None else contextlib.nullcontext():
        return _run_task(
            cfg, task, config_path=config_path, overrides=overrides, out_dir=out_dir, say=say
        )


def ddm_pace(cfg: Config) -> str:
    """How the ddms run, for people."""
    return f"at {cfg.ddm.rate_hz:g} Hz" if cfg.ddm.rate_hz > 0 else "on data"


def _esc_ready(session_id: str, nodes: list[str]) -> Callable[[], bool]:
    """True once every ESC's acquisition has published its first feedback."""
    from redistro.localdata import LocalData

    seen: set[str] = set()

    def ready() -> bool:
        for node in nodes:
            if node in seen:
                continue
            try:
                ld = LocalData.attach(session_id, node)
            except (IPCError, LayoutError, OSError):
                return False
            try:
                if int(ld.block("feedback", 0).read()["seq_src"]) > 0:
                    seen.add(node)
            except Exception:
                return False
            finally:
                ld.close()
        return len(seen) == len(nodes)

    return ready


def _run_task(
    cfg: Config,
    task: Task,
    *,
    config_path: str | None,
    overrides: list[str],
    out_dir: str | None,
    say: Callable[[str], None],
) -> int:
    from redistro.plant.launch import PlantProcess
    from redistro.ssc.plan import ssc_spec

    hardware = load_hardware(cfg)
    runs = Path(cfg.session.runs_dir)
    started = time.time()
    node_results: list[dict[str, Any]] = []
    plant_result: dict[str, Any] = {}
    with ipc_session.Session.create() as s:
        if not cfg.ddm.key_file:  # the link's key: the session's own, in its 0700 folder
            from redistro.ddm import record as wire

            wire.new_key(s.directory / wire.SESSION_KEY)
        run_dir = Path(out_dir) if out_dir else runs / s.id
        run_dir.mkdir(parents=True, exist_ok=True)
        messages = str(run_dir / "messages.log")
        say(f"session {s.id}")
        say(f"task {task.task} ({task.kind}) on {', '.join(task.robots)}; run folder {run_dir}")
        plant = PlantProcess.start(
            s, run_dir, config=config_path, overrides=plant_overrides(cfg, overrides)
        )
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
                        messages_path=messages,
                        run_dir=str(run_dir),
                    )
                    for r in group
                ]
                later: list[NodeSpec] = []
                if task.kind == "strategy":
                    later = [
                        ssc_spec(
                            cfg,
                            task,
                            s.id,
                            config_path=config_path,
                            overrides=overrides,
                            run_dir=str(run_dir),
                            messages_path=messages,
                        )
                    ]
                    say(
                        f"starting {', '.join(sp.node for sp in specs)} at {cfg.esc.rate_hz:g} Hz; "
                        f"ssc at {cfg.ssc.rate_hz:g} Hz once every ESC has published its "
                        f"robot's state; ddm {cfg.ddm.transport} {ddm_pace(cfg)}"
                    )
                else:
                    say(f"starting {', '.join(sp.node for sp in specs)} at {cfg.esc.rate_hz:g} Hz")
                progress = Progress(s.id, specs + later, say)
                progress.ssc_segments = [(g.name, g.duration_s) for g in task.segments]
                try:
                    results = run_nodes(
                        specs,
                        s,
                        budget_s=budget_s(task),
                        clock=plant.clock_s,
                        on_wait=progress,
                        keep=frozenset({plant.pid}),
                        later=later,
                        later_ready=_esc_ready(s.id, [sp.node for sp in specs]) if later else None,
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
    cycles = {str(r.get("node")): int(r.get("cycles", 0)) for r in node_results}
    log_info = _finish_log(run_dir, say, cycles)
    if log_info:
        summary["log"] = log_info
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
    for seg in summary.get("segments", []):
        say(_segment_line(seg))
    if "inserted" in summary:
        say(
            f"inserted: {summary['inserted']} (depth {summary['insertion_depth_m'] * 1e3:.2f} mm "
            f"of {summary['hole_depth_m'] * 1e3:.1f} mm)"
        )
    say(f"wrote {run_dir / 'summary.json'}")
    return 0 if summary["result"] == "ok" else 1


def _finish_log(
    run_dir: Path, say: Callable[[str], None], cycles: dict[str, int]
) -> dict[str, Any]:
    """session.mcap from the nodes' parts, and its counters (never fails the session)."""
    from redistro.log.mcapfile import finish_run_log

    try:
        info = finish_run_log(run_dir, cycles)
    except Exception as exc:
        log.warning("session log not finished: %s", exc)
        return {"error": str(exc)}
    if info:
        say(
            f"session log {run_dir / info['file']}: {info['messages']} messages, "
            f"{info['dropped']} cycles dropped"
        )
    return info


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


def _segment_line(seg: dict[str, Any]) -> str:
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

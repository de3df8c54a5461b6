"""The decision stage: ``redistro session TASK`` runs one task from power-on to power-off.

It checks the task against the config (bad input ends here: nothing has
started), starts the plant (system on), launches the nodes the task needs,
prints progress while they run, ends them, powers off, and writes the run
folder: ``summary.json``, ``messages.log``, ``plant.json`` and a copy of
the final positions files. Exit code 0 only when the result is ``ok``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from redistro import files
from redistro.config.hardware import load_hardware
from redistro.config.model import Config
from redistro.config.task import Task
from redistro.esc.plan import esc_spec
from redistro.ipc import session as ipc_session
from redistro.process.result import NodeResult
from redistro.process.session_owner import run_nodes, write_json
from redistro.session.preflight import positions_file, preflight, unknown_positions
from redistro.session.progress import Progress, ddm_pace
from redistro.session.summary import budget_s, build_summary, segment_line

if TYPE_CHECKING:
    from redistro.plant.launch import PlantProcess

log = logging.getLogger(__name__)


def plant_config(cfg: Config) -> Config:
    """The plant's config: the arms' pose is kept between power-offs in the
    runs folder (the positions files hold only while the arms stay put)."""
    if cfg.plant.pose_file:
        return cfg
    pose = str(Path(cfg.session.runs_dir) / cfg.session.plant_pose_file)
    return dataclasses.replace(cfg, plant=dataclasses.replace(cfg.plant, pose_file=pose))


def run_session(
    cfg: Config,
    task_path: str,
    *,
    out_dir: str | None = None,
    say: Callable[[str], None] | None = None,
    around_task: Callable[[], contextlib.AbstractContextManager[Any]] | None = None,
) -> int:
    """around_task: a context the task itself runs in (not a self-calibration
    run first): what ``redistro bench group`` measures."""
    say = say or (lambda text: print(text, flush=True))
    task = preflight(cfg, task_path)
    if cfg.scheduling.policy == "batch":  # (every process it starts inherits it)
        from redistro.ipc import sched

        sched.batch()
    start = None
    if cfg.session.clock == "lockstep":  # what a replay starts from (redistro replay)
        from redistro.session.start import start_state

        start = start_state(cfg, task_path, list(task.robots))
    for name in ipc_session.reap():
        print(f"reaped {name} (left by a dead session)", file=sys.stderr)
    if task.kind == "strategy" and task.calibrate_if_needed:
        unknown = unknown_positions(cfg, task)
        if unknown:
            robots = [r for r in task.robots if r in unknown]
            say(f"joint positions unknown ({'; '.join(unknown.values())})")
            say(f"self-calibration of {', '.join(robots)} first")
            cal = calibration_first(task, robots)
            cal_dir = str(Path(out_dir) / "self_calibration") if out_dir else None
            rc = _run_task(cfg, cal, out_dir=cal_dir, say=say)
            if rc != 0:
                say(f"{task.task} not started: the self-calibration did not end ok")
                return rc
    with around_task() if around_task is not None else contextlib.nullcontext():
        return _run_task(cfg, task, out_dir=out_dir, say=say, start=start)


def calibration_first(task: Task, robots: list[str]) -> Task:
    """The self-calibration of ``robots`` a strategy task runs first: as its
    own ``calibration`` section says (the defaults where it has none)."""
    return Task(
        task=f"self_calibration (before {task.task})",
        kind="self_calibration",
        robots=robots,
        calibration=task.calibration,
        source=task.source,
    )


def _run_task(
    cfg: Config,
    task: Task,
    *,
    out_dir: str | None,
    say: Callable[[str], None],
    start: dict[str, Any] | None = None,
) -> int:
    """start: a lockstep session's start state, into the run folder."""
    from redistro.plant.launch import PlantProcess

    hardware = load_hardware(cfg)
    runs = Path(cfg.session.runs_dir)
    started = time.time()
    node_results: list[NodeResult] = []
    plant_result: dict[str, Any] = {}
    with ipc_session.Session.create() as s:
        _session_secrets(cfg, task, s)
        run_dir = Path(out_dir) if out_dir else runs / s.id
        files.make_folder(run_dir, "run folder")
        if start is not None:
            from redistro.session.start import write_start

            write_start(run_dir, start)
        messages = str(run_dir / "messages.log")
        os.close(files.create(messages))  # (new: the managers only append to it)
        say(f"session {s.id}")
        say(f"task {task.task} ({task.kind}) on {', '.join(task.robots)}; run folder {run_dir}")
        # the plant starts beside the first nodes (each waits for it before
        # it opens its driver): their start-ups overlap
        plant = PlantProcess.launch(s, run_dir, plant_config(cfg), hardware=hardware)
        bridge = _start_bridge(cfg, s, say)
        try:
            order = task.calibration.order if task.kind == "self_calibration" else "together"
            groups = [task.robots] if order == "together" else [[r] for r in task.robots]
            for group in groups:
                results = _run_group(cfg, task, hardware, s, plant, group, run_dir, messages, say)
                node_results += results
                if not all(r.ok for r in results):
                    break
        finally:
            _stop_bridge(bridge)
            plant.stop()
            plant_result = plant.result()
            say("plant powered off")
    summary = build_summary(task, node_results, plant_result, started, time.time(), run_dir)
    log_info = _finish_log(run_dir, say, {r.node: r.cycles for r in node_results})
    if log_info:
        summary["log"] = log_info
    for robot in task.robots:
        src = positions_file(cfg, robot)
        if src.exists():
            files.replace(run_dir / f"positions.{robot}.json", src.read_bytes())
    write_json(run_dir / "summary.json", summary)
    _say_summary(summary, say)
    say(f"wrote {run_dir / 'summary.json'}")
    return 0 if summary["result"] == "ok" else 1


def _session_secrets(cfg: Config, task: Task, s: ipc_session.Session) -> None:
    """The link's key (the session's own, in its 0700 folder, unless a key
    file is set) and, over zenoh, every node's user and password."""
    if not cfg.ddm.key_file:
        from redistro.ddm import record as wire

        wire.new_key(s.directory / wire.SESSION_KEY)
    if cfg.ddm.transport == "zenoh" and not cfg.ddm.zenoh.users_file:
        from redistro.ddm import zenoh_transport as zt

        nodes = ["ssc", *(f"esc.{r}" for r in task.robots)]
        zt.new_users_file(s.directory / zt.SESSION_USERS, zt.group_of(cfg, s.id), nodes)


def _run_group(
    cfg: Config,
    task: Task,
    hardware: Any,
    s: ipc_session.Session,
    plant: PlantProcess,
    group: list[str],
    run_dir: Path,
    messages: str,
    say: Callable[[str], None],
) -> list[NodeResult]:
    """One group of robots' nodes run to their end: their ESCs, and for a
    strategy task the SSC beside them."""
    from redistro.ssc.plan import ssc_spec

    specs = [
        esc_spec(
            cfg, task, r, hardware[r], s.id, positions_file=str(positions_file(cfg, r)),
            messages_path=messages, run_dir=str(run_dir),
        )
        for r in group
    ]  # fmt: skip
    if task.kind == "strategy":
        # the SSC starts beside the ESCs: its worker waits for every robot's
        # first feedback (the start-up datum) before its task starts, its
        # manager fails it as starving if that does not come within
        # ddm.connect_timeout_s, and its ddm connects until then
        specs.append(ssc_spec(cfg, task, s.id, run_dir=str(run_dir), messages_path=messages))
    say(
        f"starting {', '.join(sp.node for sp in specs)}: ESCs at {cfg.esc.rate_hz:g} Hz"
        + (f", ssc at {cfg.ssc.rate_hz:g} Hz; ddm {cfg.ddm.transport} {ddm_pace(cfg)}"
           if task.kind == "strategy" else "")
    )  # fmt: skip
    progress = Progress(s.id, specs, say)
    up = plant.up

    def plant_up() -> bool:
        nonlocal up
        if not up and plant.started():
            up = True
            say(f"plant running ({cfg.plant.backplane} backplane, {cfg.plant.physics_hz:g} Hz)")
        return up

    progress.ssc_segments = [(g.name, g.duration_s) for g in task.segments]
    if cfg.session.clock == "lockstep":  # the plant ticks this group's nodes
        from redistro.plant.lockstep import write_nodes

        write_nodes(s.directory, [sp.node for sp in specs], cfg.esc.rate_hz)
    try:
        results = run_nodes(
            specs,
            s,
            budget_s=budget_s(task),
            clock=plant.clock_s,
            on_wait=progress,
            keep=frozenset({plant.pid}),
            beside=plant_up,
        )
    finally:
        progress.close()
    for r in results:
        say(f"{r.node}: {r.result} {r.reason}".rstrip())
    return results


def _say_summary(summary: dict[str, Any], say: Callable[[str], None]) -> None:
    """The result, the calibration's offsets, each segment, the insertion."""
    say(f"result: {summary['result']}" + (f" ({summary['reason']})" if summary["reason"] else ""))
    if "calibration" in summary:
        for robot, joints in summary["calibration"].items():
            errs = [j["error_rad"] for j in joints if j["error_rad"] is not None]
            worst = max((abs(e) for e in errs), default=float("nan"))
            say(f"{robot}: {len(errs)}/7 zero offsets found, worst error {worst:.2e} rad")
    for seg in summary.get("segments", []):
        say(segment_line(seg))
    if "inserted" in summary:
        belief = f"{summary['insertion_depth_m'] * 1e3:.2f} mm"
        if "plant_insertion_depth_m" in summary:  # the plant's truth, the belief beside it
            flag = ", they disagree" if summary["belief_disagrees"] else ""
            belief = (
                f"{summary['plant_insertion_depth_m'] * 1e3:.2f} mm by the plant, "
                f"{belief} by the controller{flag}"
            )
        say(
            f"inserted: {summary['inserted']} (depth {belief} "
            f"of {summary['hole_depth_m'] * 1e3:.1f} mm)"
        )


def _start_bridge(cfg: Config, s: Any, say: Callable[[str], None]) -> Any:
    """``ros2.bridge``: the ROS 2 bridge beside the nodes (its own process,
    reading their Local Data from outside; ends with the session)."""
    if not cfg.ros2.bridge:
        return None
    from redistro.process.spawn import spawn

    say(f"ROS 2 bridge on {', '.join(cfg.ros2.listen)}")
    return spawn(["bridge", "--session", s.id], env=s.child_env())


def _stop_bridge(proc: Any) -> None:
    import signal
    import subprocess

    if proc is None:
        return
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(5.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


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

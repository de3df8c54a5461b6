"""The plant process: physics at ``plant.physics_hz`` paced to the wall clock.

Started as ``python -m redistro.process plant --session SID [--config F]
[--set k=v ...] [--result FILE] [--gui] [--seconds S]``. It creates the
register bank (the chassis' shared memory, also carrying the simulation's
ground truth), serves the backplane, and steps until SIGTERM/SIGINT, its
parent's death, or ``--seconds``. Steps taken more than one step late are
counted; when it falls more than CATCH_UP_STEPS behind it skips ahead
(counted) to stay on the wall clock. On the way out it engages every brake.
"""

from __future__ import annotations

import contextlib
import gc
import json
import logging
import os
import signal
import time
from pathlib import Path
from typing import Any

import numpy as np

from redistro.config.hardware import RobotHardware
from redistro.config.loader import from_resolved
from redistro.config.model import Config
from redistro.drivers.io.backplane import BoardPort
from redistro.drivers.io.bank import TRUTH, PlantState, RegisterBank
from redistro.drivers.io.registers import ENC_MODULO
from redistro.drivers.io.shm import ShmPort
from redistro.ipc import names, signals
from redistro.ipc.session import Manifest
from redistro.localdata.block import Record
from redistro.plant.truth import ArmsTruth, ObjectsInHoles, PegTruth
from redistro.process import hooks

log = logging.getLogger(__name__)
# How far behind the wall clock the plant still catches up, stepping flat
# out [steps]. Catching up runs steps back to back with no new command in
# between: 50 steps meant up to 50 ms of simulated time on one 200 Hz
# command (a 40 Hz loop in simulated time) whenever a starved plant got the
# CPU back, which jolted the force-controlled peg sideways. Five steps are
# one 200 Hz control cycle: further behind, the simulation skips ahead.
CATCH_UP_STEPS = 5
# A real-time plant whose steps take more than this share of the wall clock
# over a second (a slow machine, a heavy contact) leaves real time for nice
# -10 and slows its own clock instead of holding a CPU from the session's
# other processes (the owner's chores, the log writers).
DUTY_LIMIT = 0.5


def run_plant(
    session_id: str,
    resolved_path: str,
    *,
    result_path: str | None = None,
    gui: bool = False,
    seconds: float = 0.0,
) -> int:
    from redistro.plant.chassis import Chassis
    from redistro.plant.world import World

    signals.set_parent_death_signal(signal.SIGTERM)
    # the config and the hardware its starter loaded and checked, handed down resolved
    doc = json.loads(Path(resolved_path).read_text())
    cfg = from_resolved(Config, doc["config"])
    hardware = {r: from_resolved(RobotHardware, h) for r, h in doc["hardware"].items()}
    world: World | None = None
    bank: RegisterBank | None = None
    port: BoardPort | None = None
    result: dict[str, Any] = {"session": session_id, "backplane": cfg.plant.backplane}
    chassis = None
    try:
        start_q = read_pose(cfg.plant.pose_file, list(cfg.robots))
        result["started_from"] = "pose file" if start_q else "initial_q_rad"
        # the arms' URDF files in the session's runtime folder, which goes
        # with the session (and with a killed one, when the reaper takes it)
        folder = names.runtime_dir() / session_id
        urdf_dir = folder / "plant-urdf" if folder.is_dir() else None
        world = World(cfg, gui=gui or cfg.plant.gui, start_q=start_q, urdf_dir=urdf_dir)
        result["hole"] = world.hole.as_dict()  # where the hole really is
        # what disturbs the plant from outside (the fault harness; none normally)
        make = hooks.factory("plant_disturbance")
        chassis = Chassis(cfg, world, hardware, disturbance=make() if make else None)
        shm = cfg.plant.backplane == "shm"
        bank = RegisterBank.create(
            session_id,
            chassis.boards if shm else {},
            [r.name for r in chassis.rigs],
            cfg.plant.physics_hz,
            Manifest.for_session(session_id),
        )
        port = ShmPort(bank) if shm else _can_port(cfg, session_id, chassis)
        result["scheduling"] = _take_priority(cfg)
        result["clock"] = cfg.session.clock
        where = folder if folder.is_dir() else None
        result.update(_run_loop(cfg, session_id, where, seconds, chassis, bank, port))
        result["state"] = "stopped"
        return 0
    except Exception as exc:
        result["state"] = "failed"
        result["error"] = f"{type(exc).__name__}: {exc}"
        log.error("plant failed: %s", exc)
        return 1
    finally:
        if chassis is not None:
            _final_pose(cfg, chassis, result)
        if bank is not None:
            with bank.status.write() as d:
                d["state"] = (
                    PlantState.STOPPED if result.get("state") == "stopped" else PlantState.FAILED
                )
            if port is not None:
                port.close()
            bank.close()
            bank.unlink()
        if world is not None:
            world.close()
        if result_path:
            from redistro import files

            files.replace(result_path, json.dumps(result, indent=2) + "\n")


def _run_loop(
    cfg: Config,
    session_id: str,
    folder: Path | None,
    seconds: float,
    chassis: Any,
    bank: RegisterBank,
    port: BoardPort,
) -> dict[str, Any]:
    """The plant's loop for ``session.clock``, to its end; what it did."""
    # a developer's profile of the plant (tools/profile.py TASK plant/loop)
    profiled = hooks.profile("plant/loop")
    with profiled if profiled is not None else contextlib.nullcontext():
        if cfg.session.clock == "lockstep":
            from redistro.ipc import bell
            from redistro.plant.lockstep import Conductor

            at_most = cfg.session.lockstep_pace
            conductor = Conductor(session_id, folder, cfg.plant.physics_hz, at_most)
            if folder is not None:  # (a session's: the nodes ring it, plant/lockstep.py)
                conductor.bell = bell.create(session_id)
            boost = _step_priority(cfg.scheduling.priorities)
            try:
                return _loop_lockstep(cfg.plant.physics_hz, chassis, bank, port, conductor, boost)
            finally:
                if conductor.bell is not None:
                    conductor.bell.close()
                    conductor.bell.unlink()
        pace = cfg.plant.real_time_factor
        return _loop(cfg.plant.physics_hz, seconds, chassis, bank, port, pace)


def _can_port(cfg: Config, session_id: str, chassis: Any) -> BoardPort:
    """The boards on a CAN bus (python-can's, as the configuration says)."""
    from redistro.drivers.io.can import PLANT_RCVBUF, CanPort, open_bus, plant_key

    c = cfg.plant.can
    # (every frame on the bus comes in, the chassis' own replies among them:
    # a burst past the default buffer was lost, writes with it)
    bus = open_bus(c.interface, c.channel, c.port, session_id, c.loopback_only, PLANT_RCVBUF)
    return CanPort(chassis.boards, bus, key=plant_key(session_id))


def _take_priority(cfg: Config) -> dict[str, Any]:
    """The lowest real-time priority, below every controller process: the
    simulated chassis keeps its 1 kHz beside them and never delays them;
    where real time is refused, nice -10. What was granted."""
    from redistro.ipc import sched

    policy = cfg.scheduling.policy
    prio = cfg.scheduling.priorities.get("plant", 1)
    asked = "rr" if policy in ("auto", "rr") else "batch" if policy == "batch" else "none"
    granted = sched.apply(prio, None, asked)
    if granted.policy == "default" and policy in ("auto", "nice"):
        granted = sched.apply(20, None, "nice")
    return granted.as_dict()


def _final_pose(cfg: Config, chassis: Any, result: dict[str, Any]) -> None:
    """Where the arms ended (kept for the next power-up in the pose file),
    and the encoders' true offsets (what a calibration is judged by)."""
    result["final_q_rad"] = {r.name: [float(v) for v in r.q] for r in chassis.rigs}
    result["encoder_offset_rad"] = {
        r.name: [float(v) for v in _signed(r.encoder_offset) / r.counts_per_rad]
        for r in chassis.rigs
    }
    if cfg.plant.pose_file:
        write_pose(cfg.plant.pose_file, result["final_q_rad"])


def _signed(counts: np.ndarray) -> np.ndarray:
    d = np.mod(counts, ENC_MODULO)
    out: np.ndarray = np.where(d >= ENC_MODULO // 2, d - ENC_MODULO, d)
    return out


def read_pose(path: str, robots: list[str]) -> dict[str, list[float]]:
    """The arms' pose kept while powered off; {} when there is none (or it is unreadable)."""
    if not path:
        return {}
    try:
        data = json.loads(Path(path).read_text())
        pose = {r: [float(v) for v in data["q_rad"][r]] for r in robots if r in data["q_rad"]}
    except (OSError, ValueError, KeyError, TypeError):
        return {}
    return {r: q for r, q in pose.items() if len(q) == 7 and all(np.isfinite(q))}


def write_pose(path: str, q_rad: dict[str, list[float]]) -> None:
    from redistro import files

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    files.replace(p, json.dumps({"q_rad": q_rad}, indent=1) + "\n")


def _loop(
    physics_hz: float,
    seconds: float,
    chassis: Any,
    bank: RegisterBank,
    port: BoardPort,
    pace: float = 1.0,
) -> dict[str, Any]:
    """Step the physics, paced to ``pace`` x real time (1: real time).

    Each step's cost is timed in two parts, in this thread's CPU time (a
    real-time controller that preempts the plant mid-step does not count):
    PyBullet's ``stepSimulation`` (physics) and everything else the step does
    (chassis: the boards in and out, the device models, the truth, the bank)."""
    from redistro.ipc import sched
    from redistro.process.stats import Samples

    dt_ns = round(1e9 / physics_hz)
    period_ns = round(dt_ns / pace)  # wall time between steps
    status = Record(bank.status.data.dtype)
    status["state"] = PlantState.RUNNING
    read_outputs = port.outputs_reader(chassis.outputs_wanted, chassis.image)
    publish_boards = port.publisher(chassis.inp, chassis.image)
    publish_truth = _truth_publisher(bank, chassis)
    disturbance, physics, whole = chassis.disturbance, Samples(), Samples()
    late = skipped = 0
    max_gap_ns = max_gap_at_ns = 0  # the longest the plant went without a step (a stall)
    cpu0, t0 = time.process_time(), time.monotonic_ns()
    duty = _DutyWatch(sched.is_real_time(), t0)
    last_step_ns = next_ns = t0
    stop_set = set(signals.STOP_SIGNALS)
    steps_limit = int(seconds * physics_hz) if seconds > 0 else 0
    why = "signal"
    monotonic_ns = time.monotonic_ns
    gc.collect()
    gc.freeze()
    gc.disable()  # no collector pauses inside steps: a step allocates little
    io = (read_outputs, publish_truth, publish_boards)
    truth = (ArmsTruth(chassis.world), PegTruth(chassis.world), ObjectsInHoles(chassis.world))
    while True:
        _step(chassis, io, whole, physics, truth)
        now = monotonic_ns()
        if disturbance is not None:
            disturbance.on_boards(now)  # this step's disturbance is on the boards
        if now - last_step_ns > max_gap_ns:
            max_gap_ns, max_gap_at_ns = now - last_step_ns, last_step_ns
        last_step_ns = now
        steps = chassis.step_count
        _publish_status(bank, status, steps, dt_ns, now, t0, late, skipped)
        if steps_limit and steps >= steps_limit:
            why = "seconds"
            break
        if not steps & 7 and signal.sigpending() & stop_set:  # every 8 steps: it costs
            break
        if not steps & 1023 and duty.real_time:
            duty.check(steps, now)
        next_ns += period_ns
        if now > next_ns + period_ns:  # late: caught up, or skipped when far behind
            late += 1
            behind = (now - next_ns) // period_ns
            if behind > CATCH_UP_STEPS:
                skipped, next_ns = skipped + int(behind), now
        port.service(next_ns)
    gc.enable()
    counts: dict[str, Any] = {"late_steps": late, "skipped_steps": skipped}
    counts.update(arms=truth[0].report(), pegs=truth[1].report(), in_holes=truth[2].report())
    return _result(
        chassis,
        port,
        why,
        t0,
        cpu0,
        dt_ns,
        physics_hz,
        counts,
        (max_gap_ns, max_gap_at_ns),
        whole,
        physics,
        duty.demoted,
    )


def _step_priority(priorities: dict[str, int]) -> tuple[Any, Any] | None:
    """In lockstep, the plant's real-time priority while it steps the
    physics, above every node's, and its own for the rest (None: it does not
    run real time).

    A lockstep tick is the ESCs' cycle, then the physics and the SSC's cycle
    side by side. At the plant's own priority, the lowest, the SSC's
    processes and the log's writer took its CPU in the middle of the
    physics: the tick waited for the physics longer than the physics took.
    Raised for the physics alone, the plant runs it on one CPU unbroken,
    and the nodes share the other; while it waits on the nodes it is back
    below them."""
    try:
        from redistro.ipc import sched

        if not sched.is_real_time():
            return None
        own = os.sched_getparam(0)
        top = max(v for k, v in priorities.items() if k != "plant")
        return own, os.sched_param(min(99, max(top + 1, own.sched_priority)))
    except (OSError, ValueError):
        return None


def _loop_lockstep(
    physics_hz: float,
    chassis: Any,
    bank: RegisterBank,
    port: BoardPort,
    conductor: Any,
    boost: tuple[Any, Any] | None = None,
) -> dict[str, Any]:
    """Step the physics when the nodes have done their tick, then tick
    them (``redistro.plant.lockstep``); as fast as the CPUs allow. Until a
    group of nodes is up, the boards are served (the managers' freezes and
    presets) without a physics step. The amplifiers' watchdog runs on the
    simulated clock. ``boost``: the plant's priority while it steps, and
    its own (:func:`_step_priority`)."""
    from redistro.process.stats import Samples

    dt_ns = round(1e9 / physics_hz)
    status = Record(bank.status.data.dtype)
    status["state"] = PlantState.RUNNING
    read_outputs = port.outputs_reader(chassis.outputs_wanted, chassis.image)
    publish_boards = port.publisher(chassis.inp, chassis.image)
    publish_truth = _truth_publisher(bank, chassis)
    physics, whole = Samples(), Samples()
    cpu0, t0 = time.process_time(), time.monotonic_ns()
    stop_set = set(signals.STOP_SIGNALS)
    io = (read_outputs, publish_truth, publish_boards)
    truth = (ArmsTruth(chassis.world), PegTruth(chassis.world), ObjectsInHoles(chassis.world))
    groups = 0

    def step() -> None:  # one tick's physics
        if boost is not None:
            os.sched_setparam(0, boost[1])
        for _ in range(conductor.steps_per_tick):
            _step(chassis, io, whole, physics, truth, t0 + chassis.step_count * dt_ns)
        steps = chassis.step_count
        _publish_status(bank, status, steps, dt_ns, t0 + steps * dt_ns, t0, 0, 0)
        if boost is not None:
            os.sched_setparam(0, boost[0])

    if not isinstance(port, ShmPort):  # (CAN: the drivers' frames answered while waiting)
        conductor.pause = port.service  # (until a monotonic time [ns])
    _publish_status(bank, status, 0, dt_ns, t0 + 1, t0, 0, 0)
    gc.collect()
    gc.freeze()
    gc.enable()  # (off while the process started)
    try:
        while not signal.sigpending() & stop_set:
            sim_ns = t0 + chassis.step_count * dt_ns
            if not conductor.ready():
                read_outputs()  # served, not stepped
                chassis.apply_outputs(None, sim_ns)
                publish_boards()
                port.service(time.monotonic_ns())
                time.sleep(0.001)
                continue
            if conductor.groups != groups:  # a group's first tick, one tick's steps in
                groups = conductor.groups
                chassis.wrists.reseed(groups)
                step()
            conductor.tick(step)
    finally:
        conductor.close()
        # the boards' last outputs taken before the power goes: a freeze the
        # nodes made while a tick waited on them is the plant's too
        read_outputs()
        chassis.apply_outputs(None, t0 + chassis.step_count * dt_ns)
    counts: dict[str, Any] = {"late_steps": 0, "skipped_steps": 0, "lockstep": conductor.report()}
    counts.update(arms=truth[0].report(), pegs=truth[1].report(), in_holes=truth[2].report())
    gap = (0, 0)
    return _result(
        chassis, port, "signal", t0, cpu0, dt_ns, physics_hz, counts, gap, whole, physics, None
    )


def _step(
    chassis: Any,
    io: tuple[Any, Any, Any],
    whole: Any,
    physics: Any,
    truth: tuple[ArmsTruth, PegTruth, ObjectsInHoles],
    now_ns: int = 0,
) -> None:
    """One step: the controller's outputs applied, PyBullet's step, the
    joints sampled into the boards, the truth then the boards published
    (a reader that sees a board sample can find the truth of the same
    step), the truth's looks (the arms' contacts, the pegs' depth); its
    CPU time, and PyBullet's part, timed."""
    read_outputs, publish_truth, publish_boards = io
    cpu_ns = time.thread_time_ns
    c0 = cpu_ns()
    read_outputs()
    chassis.apply_outputs(None, now_ns or time.monotonic_ns())
    ph0 = cpu_ns()
    chassis.step_physics()
    ph1 = cpu_ns()
    chassis.sample()
    chassis.fill_truth()
    publish_truth()
    publish_boards()
    for t in truth:
        t.sample(chassis.step_count)
    whole.add(cpu_ns() - c0)
    physics.add(ph1 - ph0)


def _publish_status(
    bank: RegisterBank,
    status: Any,
    steps: int,
    dt_ns: int,
    now: int,
    t0: int,
    late: int,
    skipped: int,
) -> None:
    """The plant's status block, each step (what nodes and viewers read)."""
    status["step"] = steps
    status["sim_time_ns"] = steps * dt_ns
    status["wall_ns"] = now
    status["rtf"] = steps * dt_ns / max(1, now - t0)
    status["late_steps"] = late
    status["skipped_steps"] = skipped
    bank.status.publish(status.bytes)


def _result(
    chassis: Any,
    port: BoardPort,
    why: str,
    t0: int,
    cpu0: float,
    dt_ns: int,
    physics_hz: float,
    counts: dict[str, Any],
    gap: tuple[int, int],
    whole: Any,
    physics: Any,
    demoted: dict[str, Any] | None,
) -> dict[str, Any]:
    """What the plant's run did: its steps, pace, stalls, per-step costs."""
    wall = (time.monotonic_ns() - t0) / 1e9
    cpu_s = time.process_time() - cpu0
    chassis.brake_all()  # brakes on: the arms stay where they are
    return {
        "ended_by": why,
        "steps": chassis.step_count,
        "wall_s": round(wall, 3),
        "rtf": round(chassis.step_count * dt_ns / 1e9 / wall, 4) if wall > 0 else 0.0,
        **counts,
        "max_step_gap_ms": round(gap[0] / 1e6, 2),
        "max_step_gap_monotonic_ns": gap[1],
        "torn_outputs": int(getattr(port, "torn_outputs", 0)),
        "bad_frames": int(getattr(port, "bad_frames", 0)),
        "forged_writes": int(getattr(port, "forged", 0)),
        "taken_writes": int(getattr(port, "taken", 0)),
        "physics_hz": physics_hz,
        "pid": os.getpid(),
        "kernels": chassis.kernels,
        "cpu_s": round(cpu_s, 3),
        "cpu_percent": round(100 * cpu_s / wall, 1) if wall > 0 else 0.0,
        # per step [us of CPU]: the whole step, PyBullet's stepSimulation, the rest
        "step_us": whole.summary_us(),
        "physics_us": physics.summary_us(),
        "chassis_us": _difference(whole, physics),
        "freezes": chassis.freezes,
        "grippers": chassis.grippers.events,
        "objects": chassis.grippers.object_poses(),
        "objects_start": chassis.grippers.start,
        "watchdog_trips": chassis.watchdog_trips,
        "left_real_time": demoted,
    }


class _DutyWatch:
    """The plant's duty on its CPU, looked at every 1024 steps: above
    DUTY_LIMIT it leaves real time (it would starve the controller)."""

    def __init__(self, real_time: bool, t0: int) -> None:
        self.real_time = real_time
        self.demoted: dict[str, Any] | None = None  # when the plant left real time
        self.cpu0, self.wall0 = time.thread_time_ns(), t0

    def check(self, steps: int, now: int) -> None:
        from redistro.ipc import sched

        duty = (time.thread_time_ns() - self.cpu0) / max(1, now - self.wall0)
        if duty > DUTY_LIMIT:
            self.real_time = False
            self.demoted = {"step": steps, "duty": round(duty, 3)}
            sched.leave_real_time()
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, 0, -10)
        self.cpu0, self.wall0 = time.thread_time_ns(), now


def _truth_publisher(bank: RegisterBank, chassis: Any) -> Any:
    """A callable that publishes every robot's truth record into the bank."""
    from redistro import kernels

    n = len(chassis.rigs)
    if chassis.kernels:
        size = TRUTH.itemsize
        spans = [(*bank.truth_offsets(i)[:2], size, i * size) for i in range(n)]
        table = kernels.table("seq_write", "table", spans)
        p = kernels.plan("seq_write", dst=bank.raw, src=chassis.truth_image, table=table)
        write = kernels.KERNELS.seq_write
        return lambda: write(p)
    blocks = [bank.truth(i) for i in range(n)]
    rows = [memoryview(chassis.truth[i : i + 1].view(np.uint8)) for i in range(n)]

    def publish() -> None:
        for block, row in zip(blocks, rows, strict=True):
            block.publish(row)

    return publish


def _difference(whole: Any, part: Any) -> dict[str, float]:
    """p50/p99/max of (whole - part), step by step."""
    from redistro.process.stats import Samples

    n = min(whole.count, part.count)
    d = Samples(max(1, n))
    for v in (whole.values_ns()[:n] - part.values_ns()[:n]).tolist():
        d.add(v)
    return d.summary_us()

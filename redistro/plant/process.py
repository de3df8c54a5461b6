"""The plant process: physics at ``plant.physics_hz`` paced to the wall clock.

Started as ``python -m redistro.process plant --session SID [--config F]
[--set k=v ...] [--result FILE] [--gui] [--seconds S]``. It creates the
register bank (the chassis' shared memory, also carrying the simulation's
ground truth), serves the backplane, and steps until SIGTERM/SIGINT, its
parent's death, or ``--seconds``. Steps taken more than one step late are
counted; when it falls more than 50 steps behind it skips ahead (counted) to
stay on the wall clock. On the way out it engages every brake.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import time
from pathlib import Path
from typing import Any

import numpy as np

from redistro.config.hardware import load_hardware
from redistro.config.loader import load_config
from redistro.drivers.io.backplane import BoardPort, ShmPort
from redistro.drivers.io.bank import TRUTH, PlantState, RegisterBank
from redistro.ipc import signals
from redistro.ipc.session import Manifest
from redistro.localdata.block import Record

log = logging.getLogger(__name__)
CATCH_UP_STEPS = 50


def run_plant(
    session_id: str,
    config: str | None,
    overrides: list[str],
    *,
    result_path: str | None = None,
    gui: bool = False,
    seconds: float = 0.0,
) -> int:
    from redistro.plant.chassis import Chassis
    from redistro.plant.world import World

    signals.set_parent_death_signal(signal.SIGTERM)
    cfg = load_config(config, overrides)
    hardware = load_hardware(cfg)
    world: World | None = None
    bank: RegisterBank | None = None
    port: BoardPort | None = None
    result: dict[str, Any] = {"session": session_id, "backplane": cfg.plant.backplane}
    try:
        world = World(cfg, gui=gui or cfg.plant.gui)
        chassis = Chassis(cfg, world, hardware)
        shm = cfg.plant.backplane == "shm"
        bank = RegisterBank.create(
            session_id,
            chassis.boards if shm else {},
            [r.name for r in chassis.rigs],
            cfg.plant.physics_hz,
            Manifest.for_session(session_id),
        )
        if shm:
            port = ShmPort(bank)
        else:
            from redistro.drivers.io.can import CanPort, open_bus

            c = cfg.plant.can
            port = CanPort(chassis.boards, open_bus(c.interface, c.channel, c.port, session_id))
        result.update(_loop(cfg.plant.physics_hz, seconds, chassis, bank, port))
        result["state"] = "stopped"
        return 0
    except Exception as exc:
        result["state"] = "failed"
        result["error"] = f"{type(exc).__name__}: {exc}"
        log.error("plant failed: %s", exc)
        return 1
    finally:
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
            Path(result_path).write_text(json.dumps(result, indent=2) + "\n")


def _loop(
    physics_hz: float, seconds: float, chassis: Any, bank: RegisterBank, port: BoardPort
) -> dict[str, Any]:
    dt_ns = round(1e9 / physics_hz)
    truths = [bank.truth(i) for i in range(len(chassis.rigs))]
    truth = Record(TRUTH)
    status = Record(bank.status.data.dtype)
    status["state"] = PlantState.RUNNING
    boards = list(chassis.boards)
    late = skipped = 0
    t0 = time.monotonic_ns()
    next_ns = t0
    stop_set = set(signals.STOP_SIGNALS)
    steps_limit = int(seconds * physics_hz) if seconds > 0 else 0
    why = "signal"
    while True:
        outputs = {a: port.outputs(a) for a in boards}
        chassis.apply_outputs(outputs)
        chassis.step()
        # the truth of a step is out before its boards: a reader that sees a
        # board sample can find the truth of the same step
        for block, rig in zip(truths, chassis.rigs, strict=True):
            _fill_truth(truth, rig, chassis)
            block.publish(truth.bytes)
        for a in boards:
            port.publish(a, chassis.inp[a])
        now = time.monotonic_ns()
        steps = chassis.step_count
        status["step"] = steps
        status["sim_time_ns"] = steps * dt_ns
        status["wall_ns"] = now
        status["rtf"] = steps * dt_ns / max(1, now - t0)
        status["late_steps"] = late
        status["skipped_steps"] = skipped
        bank.status.publish(status.bytes)
        if steps_limit and steps >= steps_limit:
            why = "seconds"
            break
        if signal.sigpending() & stop_set:
            break
        next_ns += dt_ns
        if now > next_ns + dt_ns:
            late += 1
            behind = (now - next_ns) // dt_ns
            if behind > CATCH_UP_STEPS:
                skipped += int(behind)
                next_ns = now
        port.service(next_ns)
    wall = (time.monotonic_ns() - t0) / 1e9
    for rig in chassis.rigs:  # brakes on: the arms stay where they are
        chassis.world.set_brakes(rig.arm, np.ones(7, dtype=bool), rig.brake_torque_nm)
    return {
        "ended_by": why,
        "steps": chassis.step_count,
        "wall_s": round(wall, 3),
        "rtf": round(chassis.step_count * dt_ns / 1e9 / wall, 4) if wall > 0 else 0.0,
        "late_steps": late,
        "skipped_steps": skipped,
        "physics_hz": physics_hz,
        "pid": os.getpid(),
    }


def _fill_truth(truth: Record, rig: Any, chassis: Any) -> None:
    a = truth.array
    truth["step"] = chassis.step_count
    a["q_rad"] = rig.q
    a["qd_rad_s"] = rig.qd
    a["tau_nm"] = rig.tau
    a["braked"] = rig.arm.braked
    a["home"] = rig.homes.state
    a["wrench_sensor"] = rig.wrench
    if rig.wrist is not None:
        a["contact_world"] = chassis.world.contact_wrench_world(rig.arm, rig.tool_xyz)
        a["tool_xyz_m"] = rig.tool_xyz
        a["tool_rot"] = rig.tool_rot
    a["encoder_offset_counts"] = rig.encoders.offset

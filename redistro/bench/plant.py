"""``redistro bench plant``: the plant's real-time factor, and what one driver
cycle (read feedback + send torques) costs over a backplane.

Two phases in one session per backplane: the plant alone for ``seconds``
(its real-time factor at ``plant.physics_hz`` with both arms), then the plant
with both robots' drivers cycling at ``rate_hz`` (brakes on, zero torques),
timing each robot's ``read_feedback()`` + ``send_torques()``.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from redistro.config.hardware import load_hardware
from redistro.config.model import Config
from redistro.drivers.io.backplane import open_backplane
from redistro.drivers.robot import RobotDriver
from redistro.ipc import session as ipc_session
from redistro.plant.launch import PlantProcess


def _stats_us(values_s: list[float]) -> dict[str, float]:
    v = np.asarray(values_s) * 1e6
    return {
        "median": round(float(np.median(v)), 1),
        "p99": round(float(np.percentile(v, 99)), 1),
        "max": round(float(v.max()), 1),
        "samples": int(v.size),
    }


def _plant_window(plant: PlantProcess, seconds: float) -> dict[str, float]:
    a = plant.status()
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        time.sleep(0.05)  # the plant runs on its own; this only spaces two status reads
    b = plant.status()
    wall = (b["wall_ns"] - a["wall_ns"]) / 1e9
    sim = (b["sim_time_ns"] - a["sim_time_ns"]) / 1e9
    return {
        "rtf": round(sim / wall, 4) if wall > 0 else 0.0,
        "steps": int(b["step"] - a["step"]),
        "late_steps": int(b["late_steps"] - a["late_steps"]),
        "skipped_steps": int(b["skipped_steps"] - a["skipped_steps"]),
        "wall_s": round(wall, 3),
    }


def run(cfg: Config, seconds: float, rate_hz: float) -> dict[str, Any]:
    hardware = load_hardware(cfg)
    out: dict[str, Any] = {
        "backplane": cfg.plant.backplane,
        "physics_hz": cfg.plant.physics_hz,
        "driver_rate_hz": rate_hz,
    }
    if cfg.plant.backplane == "can":
        out["can"] = dataclasses.asdict(cfg.plant.can)
    with ipc_session.Session.create() as session:
        run_dir = Path(cfg.session.runs_dir) / session.id
        plant = PlantProcess.start(session, run_dir, cfg)
        drivers: list[RobotDriver] = []
        try:
            out["plant_alone"] = _plant_window(plant, seconds)
            for hw in hardware.values():
                bp = open_backplane(cfg.plant, session.id)
                d = RobotDriver(hw, bp, cfg.plant.physics_hz)
                d.open()
                drivers.append(d)
            costs: dict[str, list[float]] = {d.name: [] for d in drivers}
            zero = np.zeros(7)
            period = 1.0 / rate_hz
            a = plant.status()
            t_end = time.monotonic() + seconds
            next_t = time.monotonic()
            while time.monotonic() < t_end:
                for d in drivers:
                    t0 = time.perf_counter()
                    d.read_feedback()
                    d.send_torques(zero)
                    costs[d.name].append(time.perf_counter() - t0)
                next_t += period
                delay = next_t - time.monotonic()
                if delay > 0:
                    time.sleep(delay)  # pacing the driver loop, not synchronizing
            b = plant.status()
            wall = (b["wall_ns"] - a["wall_ns"]) / 1e9
            out["plant_with_drivers"] = {
                "rtf": round((b["sim_time_ns"] - a["sim_time_ns"]) / 1e9 / wall, 4),
                "late_steps": int(b["late_steps"] - a["late_steps"]),
                "skipped_steps": int(b["skipped_steps"] - a["skipped_steps"]),
            }
            out["driver_cycle_us"] = {name: _stats_us(v) for name, v in costs.items()}
        finally:
            for d in drivers:
                d.freeze()
                d.close()
            plant.stop()
        out["plant_result"] = plant.result()
    return out


def print_summary(s: dict[str, Any]) -> None:
    alone, loaded = s["plant_alone"], s["plant_with_drivers"]
    print(
        f"plant ({s['backplane']}, {s['physics_hz']} Hz physics): real-time factor "
        f"{alone['rtf']} alone, {loaded['rtf']} with drivers; late steps {alone['late_steps']}"
        f" of {alone['steps']}, skipped {alone['skipped_steps']}"
    )
    for name, c in s["driver_cycle_us"].items():
        print(
            f"driver {name} read_feedback + send_torques us: median {c['median']} "
            f"p99 {c['p99']} max {c['max']} ({c['samples']} cycles at {s['driver_rate_hz']} Hz)"
        )

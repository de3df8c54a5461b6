"""``redistro bench group TASK``: a whole robot group's session, measured.

It runs a real session of ``TASK`` (the plant, an ESC per robot, the SSC,
their ddms and the session log; a self-calibration first when the joint
positions are unknown, not measured) and gathers, in one document:

- per node and per process: cycles, overrun cycles, compute p50/p99/max,
  lateness p50/p99, CPU as a share of one vCPU and per node cycle (a
  recorder's step drains many cycles, a ddm wakes several times a cycle);
- the plant: real-time factor, step cost split into physics (PyBullet's
  step) and chassis (everything else a step does), late and skipped steps;
- DDM command latency per robot (and the transport);
- session-log cycles recorded and dropped;
- the whole group's CPU (every process of the session, the plant and the
  log writers included) as a share of one vCPU;
- cyclictest at the node rate, running beside the session for its whole
  length (the timer baseline of the same minutes);
- host steal and host busy time per vCPU during the run (from /proc/stat);
- the DDM floor right after the session (``redistro.bench.floor``): the
  command's path (an eventfd wake, a TCP loopback send, receive and reply)
  with nothing else to do, at the node rate: the kernel's and the
  interpreter's share of the command latency and of a ddm exchange on this
  host.

Every figure but the last three comes from the session's own ``summary.json``
(each process measures itself); this module only puts them side by side.
"""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from redistro.bench.baseline import (
    Cyclictest,
    busy_report,
    cpu_busy_ticks,
    cpu_steal_ticks,
    steal_report,
)
from redistro.config.model import Config


def _triple(d: dict[str, Any] | None, keys: tuple[str, ...] = ("p50", "p99", "max")) -> Any:
    d = d or {}
    return {k: round(float(d[k]), 1) if d.get(k) is not None else None for k in keys}


def _process(w: dict[str, Any]) -> dict[str, Any]:
    return {
        "cycles": w.get("cycles"),
        "overruns": w.get("overruns"),
        "compute_us": _triple(w.get("compute_us")),  # wall time per step
        "step_cpu_us": _triple(w.get("step_cpu_us")),  # CPU time per step: its cost
        "lateness_us": _triple(w.get("lateness_us"), ("p50", "p99")),
        "cpu_percent": w.get("cpu_percent"),
        "scheduling": w.get("scheduling"),
    }


def figures(summary: dict[str, Any]) -> dict[str, Any]:
    """The benchmark's figures from a session's summary.json."""
    nodes = {name: _node(n) for name, n in summary.get("nodes", {}).items()}
    p = summary.get("plant", {})
    plant = {k: p.get(k) for k in ("rtf", "steps", "late_steps", "skipped_steps", "cpu_percent")}
    for k in ("step_us", "physics_us", "chassis_us"):
        plant[k] = _triple(p.get(k))
    log = summary.get("log", {}) or {}
    keys = ("cycles", "recorded", "dropped", "overwritten", "pipe_full", "writer_cpu_percent")
    log_nodes = {
        node: {k: rec.get(k) for k in keys} for node, rec in (log.get("nodes") or {}).items()
    }
    writers = sum(float(rec.get("writer_cpu_percent") or 0.0) for rec in log_nodes.values())
    group_cpu = sum(n["cpu_percent"] for n in nodes.values())
    group_cpu += float(p.get("cpu_percent") or 0.0) + writers
    ddm: dict[str, Any] = {}
    for node, ex in (summary.get("ddm") or {}).items():
        if node.startswith("esc.") and isinstance(ex, dict):
            ddm[node[4:]] = {
                "command_latency_us": _triple(ex.get("command_latency_us")),
                "commands": ex.get("latency_n"),
                "dropped": ex.get("dropped"),
                "starving_index_max": ex.get("starving_index_max"),
            }
    return {
        "task": summary.get("task"),
        "result": summary.get("result"),
        "reason": summary.get("reason"),
        "inserted": summary.get("inserted"),
        # the task's own figures (per segment: final pose error, force error)
        "segments": summary.get("segments", []),
        "search": summary.get("search"),
        "run_dir": summary.get("run_dir"),
        "nodes": nodes,
        "plant": plant,
        "ddm": ddm,
        "log": {"dropped": log.get("dropped"), "nodes": log_nodes},
        "group_cpu_percent": round(group_cpu, 1),
    }


def _node(n: dict[str, Any]) -> dict[str, Any]:
    """One node's figures: its overruns, lateness, and each process's CPU."""
    periods = int(n.get("cycles") or 0) + int(n.get("missed_ticks") or 0)
    overruns = int(n.get("overruns") or 0)
    mgr = n.get("manager", {})
    procs = {
        "manager": {
            "cpu_percent": mgr.get("cpu_percent"),
            "tick_work_us": _triple(mgr.get("tick_work_us")),
        }
    }
    for w in n.get("workers", []):
        procs[str(w.get("name"))] = _process(w)
    rate = float(n.get("rate_hz") or 0.0)
    for proc in procs.values():
        # what a process costs per node cycle, wake-ups and all: a recorder
        # drains many cycles a step, a ddm wakes several times a cycle
        pct = proc.get("cpu_percent")
        proc["cpu_per_cycle_us"] = (
            round(float(pct) / 100 * 1e6 / rate, 1) if pct is not None and rate else None
        )
    node_cpu = sum(float(p.get("cpu_percent") or 0.0) for p in procs.values())
    return {
        "result": n.get("result"),
        "rate_hz": n.get("rate_hz"),
        "cycles": n.get("cycles"),
        "overrun_cycles": overruns,
        "overrun_percent": round(100 * overruns / periods, 4) if periods else None,
        "lateness_us": _triple(n.get("lateness_us")),
        "makespan_us": _triple(n.get("makespan_us")),
        "cpu_percent": round(node_cpu, 2),
        "processes": procs,
    }


@contextlib.contextmanager
def measured(out: dict[str, Any], rate_hz: float, priority: int) -> Iterator[None]:
    """cyclictest beside the task, and the host's steal and busy time over it."""
    ct = Cyclictest(rate_hz, priority)
    steal0, busy0, t0 = cpu_steal_ticks(), cpu_busy_ticks(), time.monotonic()
    try:
        yield
    finally:
        seconds = time.monotonic() - t0
        out["cyclictest_us"] = ct.stop()
        out["host_steal"] = steal_report(steal0, cpu_steal_ticks(), seconds)
        out["host_busy_percent"] = busy_report(busy0, cpu_busy_ticks())
        out["seconds"] = round(seconds, 2)


def run(cfg: Config, task_path: str, overrides: list[str]) -> dict[str, Any]:
    """overrides: the --set options, for the record (cfg holds them already)."""
    from redistro.session.run import run_session

    rate = max(cfg.esc.rate_hz, cfg.ssc.rate_hz)
    host: dict[str, Any] = {}
    out_dir = Path(cfg.session.runs_dir) / f"bench-group-{time.strftime('%Y%m%dT%H%M%S')}"
    rc = run_session(
        cfg,
        task_path,
        out_dir=str(out_dir),
        around_task=lambda: measured(host, rate, cfg.scheduling.priorities.get("manager", 20)),
    )
    import json

    summary = json.loads((out_dir / "summary.json").read_text())
    out = figures(summary)
    out.update(host)
    # the floor under a ddm exchange and the command latency on this host,
    # now: the wake-ups and the TCP loopback send, receive and reply alone, at
    # the node rate (after the session: beside it, it would be load)
    from redistro.bench import floor

    out["socket_floor"] = floor.measure(
        rate, 3.0, cfg.scheduling.priorities.get("ddm", 19), cfg.scheduling.cpu_latency_us
    )
    out["exit_code"] = rc
    out.update(pace(out_dir / "plant.json", cfg.session.clock, host.get("seconds")))
    out["transport"] = cfg.ddm.transport
    out["rates_hz"] = {"esc": cfg.esc.rate_hz, "ssc": cfg.ssc.rate_hz, "ddm": cfg.ddm.rate_hz}
    out["overrides"] = overrides
    return out


def pace(plant_json: Path, clock: str, seconds: float | None) -> dict[str, Any]:
    """The clock, the plant's simulated time, and how many times real time
    the task ran (simulated s over wall s, the start and the end included)."""
    import json

    try:
        plant = json.loads(plant_json.read_text())
        sim_s = float(plant["steps"]) / float(plant["physics_hz"])
    except (OSError, ValueError, KeyError, TypeError, ZeroDivisionError):
        return {"clock": clock}
    speed = round(sim_s / seconds, 2) if seconds else None
    return {"clock": clock, "sim_s": round(sim_s, 2), "speed_up": speed}


def print_figures(f: dict[str, Any], out: Any = sys.stdout) -> None:
    def p(text: str) -> None:
        print(text, file=out)

    p(f"bench group: {f['task']} over {f['transport']}: {f['result']} {f['reason'] or ''}")
    for name, n in f["nodes"].items():
        lat = n["lateness_us"]
        p(
            f"  {name:7s} {n['cycles']} cycles at {n['rate_hz']:g} Hz, overrun "
            f"{n['overrun_cycles']} ({n['overrun_percent']}%), lateness p50/p99 "
            f"{lat['p50']}/{lat['p99']} us, CPU {n['cpu_percent']}%"
        )
        for pname, pr in n["processes"].items():
            cpu = f"CPU {pr['cpu_percent']}% ({pr['cpu_per_cycle_us']} us a cycle)"
            if pname == "manager":
                p(f"      {'manager':12s} {cpu}")
                continue
            c, u = pr["compute_us"], pr["step_cpu_us"]
            p(
                f"      {pname:12s} step CPU p50/p99 {u['p50']}/{u['p99']} us, wall p50/p99/max "
                f"{c['p50']}/{c['p99']}/{c['max']} us, {cpu}"
            )
    pl = f["plant"]
    p(
        f"  plant   rtf {pl['rtf']}, step p50 {pl['step_us']['p50']} us (physics "
        f"{pl['physics_us']['p50']}, chassis {pl['chassis_us']['p50']}), late "
        f"{pl['late_steps']}, skipped {pl['skipped_steps']}, CPU {pl['cpu_percent']}%"
    )
    for robot, d in f["ddm"].items():
        c = d["command_latency_us"]
        p(f"  ddm {robot}  command latency p50/p99/max {c['p50']}/{c['p99']}/{c['max']} us")
    p(f"  log dropped {f['log']['dropped']} cycles")
    if f.get("speed_up") is not None:
        p(f"  {f['clock']}: {f['sim_s']} s simulated in {f['seconds']} s ({f['speed_up']}x)")
    p(f"  whole group CPU {f['group_cpu_percent']}% of one vCPU")
    ct = f.get("cyclictest_us") or {}
    if "p50" in ct:
        p(f"  cyclictest p50/p99/max {ct['p50']}/{ct['p99']}/{ct['max']} us")
    fl = (f.get("socket_floor") or {}).get("reply_cpu_us") or {}
    if "p50" in fl:
        p(f"  socket floor (receive + reply alone) CPU p50/p99 {fl['p50']}/{fl['p99']} us")
    fl = (f.get("socket_floor") or {}).get("latency_us") or {}
    if "p50" in fl:
        p(f"  socket floor latency (eventfd + TCP alone) p50/p99 {fl['p50']}/{fl['p99']} us")
    steal = (f.get("host_steal") or {}).get("ms")
    if steal:
        p("  host steal " + ", ".join(f"{c} {ms} ms" for c, ms in steal.items()))

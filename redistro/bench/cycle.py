"""``redistro bench cycle``: a real manager with N busy workers at a given rate."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

from redistro.config import Config
from redistro.errors import ConfigError
from redistro.ipc import session as ipc_session
from redistro.localdata import MAX_PROCS
from redistro.process.result import NodeResult
from redistro.process.session_owner import run_node
from redistro.process.spec import NodeSpec, WorkerSpec


def parse_stages(text: str | None, workers: int) -> list[int]:
    """``"1,1,1"`` (serial), ``"3"`` (one parallel stage of 3), ``"2,1"`` ... -> stage per worker.

    ``serial`` and ``parallel`` are shorthands. Sizes must add up to ``workers``.
    """
    if text is None or text == "serial":
        return list(range(workers))
    if text == "parallel":
        return [0] * workers
    try:
        sizes = [int(p) for p in text.split(",")]
    except ValueError:
        raise ConfigError(f"--stages {text}: expected sizes like 2,1 or serial|parallel") from None
    if any(s < 1 for s in sizes) or sum(sizes) != workers:
        raise ConfigError(f"--stages {text}: sizes must be >= 1 and add up to --workers {workers}")
    return [k for k, size in enumerate(sizes) for _ in range(size)]


def build_spec(
    cfg: Config,
    session_id: str,
    *,
    rate_hz: float,
    workers: int,
    seconds: float,
    work_us: float,
    stages: list[int],
    pin: bool,
    message_every: int = 0,
) -> NodeSpec:
    node = cfg.bench
    prio = cfg.scheduling.priorities
    cpus = node.cpus
    online = sorted(os.sched_getaffinity(0))
    specs = []
    for i in range(workers):
        pinned: list[int] = []
        if pin:
            same_stage = [j for j in range(workers) if stages[j] == stages[i]]
            pinned = [online[same_stage.index(i) % len(online)]]
        specs.append(
            WorkerSpec(
                name=f"busy{i}",
                role="busy",
                stage=stages[i],
                cpus=pinned,
                priority=prio.get("busy", 16),
                params={"work_us": work_us, "message_every": message_every},
            )
        )
    return NodeSpec(
        session_id=session_id,
        node="bench",
        kind="bench",
        rate_hz=rate_hz,
        heartbeat_limit_cycles=node.heartbeat_limit_cycles,
        workers=specs,
        robots=["r1", "r2"],
        cycles=max(1, round(seconds * rate_hz)),
        startup_timeout_s=cfg.session.startup_timeout_s,
        shutdown_timeout_s=cfg.session.shutdown_timeout_s,
        sched_policy=cfg.scheduling.policy,
        lock_memory=cfg.scheduling.lock_memory,
        cpu_latency_us=cfg.scheduling.cpu_latency_us,
        manager_priority=prio.get("manager", 20),
        cpus=list(cpus),
    )


def check_args(rate_hz: float, workers: int, seconds: float, work_us: float) -> None:
    if not rate_hz > 0 or rate_hz > 10000:
        raise ConfigError(f"--rate: expected a number in (0, 10000] Hz, got {rate_hz}")
    if not 1 <= workers <= MAX_PROCS:
        raise ConfigError(f"--workers: expected 1..{MAX_PROCS}, got {workers}")
    if not seconds > 0:
        raise ConfigError(f"--seconds: expected a number > 0, got {seconds}")
    if not work_us >= 0:
        raise ConfigError(f"--work-us: expected a number >= 0, got {work_us}")


def run_once(
    cfg: Config,
    *,
    rate_hz: float,
    workers: int,
    seconds: float,
    work_us: float,
    stages: list[int],
    pin: bool,
    message_every: int = 0,
    announce: bool = True,
) -> tuple[NodeResult, Path]:
    """One node run; its result and its run folder."""
    with ipc_session.Session.create() as session:
        if announce:
            print(f"session {session.id}", flush=True)
        spec = build_spec(
            cfg,
            session.id,
            rate_hz=rate_hz,
            workers=workers,
            seconds=seconds,
            work_us=work_us,
            stages=stages,
            pin=pin,
            message_every=message_every,
        )
        run_dir = Path(cfg.session.runs_dir) / session.id
        run_dir.mkdir(parents=True, exist_ok=True)
        spec.messages_path = str(run_dir / "messages.log")
        result = run_node(spec, session)
    return result, run_dir


def summarize(
    result: NodeResult, workers: int, work_us: float, run_dir: Path | None = None
) -> dict[str, Any]:
    """The benchmark's figures from a manager result."""
    cycles = result.cycles
    comp = [w.compute_us for w in result.workers]
    # An overrun cycle is a timer period in which the node did not complete a
    # cycle: its last stage finished after the period ended (deadline miss),
    # had not finished at the next tick (incomplete), or the tick was never
    # taken at all (missed tick: the manager itself was held off). Overrun
    # *events* count the processes instead: the manager taking a tick more
    # than one period late, or a worker waking to more than one queued sync;
    # one host stall is one event in every process it holds.
    overrun_cycles = result.overruns
    periods = cycles + result.missed_ticks
    overruns = result.manager_overruns + result.worker_overruns
    return {
        "result": result.result,
        "reason": result.reason,
        "rate_hz": result.rate_hz,
        "workers": workers,
        "work_us": work_us,
        "cycles": cycles,
        "overrun_cycles": overrun_cycles,
        "overrun_fraction": round(overrun_cycles / periods, 6) if periods else None,
        "overrun_events": overruns,
        "incomplete_cycles": result.incomplete_cycles,
        "manager_overruns": result.manager_overruns,
        "missed_ticks": result.missed_ticks,
        "worker_overruns": result.worker_overruns,
        "worker_skipped": result.worker_skipped,
        "late_heartbeats": result.late_heartbeats,
        "missed_heartbeats": result.missed_heartbeats,
        "deadline_misses": result.deadline_misses,
        "lateness_us": result.lateness_us,
        "worker_lateness_us": {
            "p50": max((w.lateness_us["p50"] for w in result.workers), default=0),
            "p99": max((w.lateness_us["p99"] for w in result.workers), default=0),
        },
        "compute_us": {
            "p50": max((c["p50"] for c in comp), default=0.0),
            "p99": max((c["p99"] for c in comp), default=0.0),
        },
        "makespan_us": result.makespan_us,
        "cpu_percent": result.cpu_percent,
        "scheduling": {
            "manager": result.manager.get("scheduling", {}),
            "workers": {w.name: w.scheduling for w in result.workers},
        },
        "session_id": result.session_id,
        "run_dir": str(run_dir) if run_dir is not None else None,
        "messages": result.messages[:20],
        "node_result": result.as_dict(),
    }


def print_summary(label: str, s: dict[str, Any], out: Any = sys.stdout) -> None:
    lat, comp, span = s["lateness_us"], s["compute_us"], s["makespan_us"]
    base = s.get("baseline_lateness_us")
    print(f"{label}: {s['result']} {s['reason']}".rstrip(), file=out)
    print(
        f"  {s['cycles']} cycles at {s['rate_hz']} Hz, {s['workers']} workers x "
        f"{s['work_us']} us; overrun cycles {s['overrun_cycles']} "
        f"({100 * (s['overrun_fraction'] or 0):.3f}% of periods), overrun events "
        f"{s['overrun_events']}, missed heartbeats {s['missed_heartbeats']}",
        file=out,
    )
    if lat:
        print(f"  timer lateness us p50 {lat['p50']} p99 {lat['p99']} max {lat['max']}", file=out)
    if base and "p99" in base:
        late = base.get("over_period_fraction", 0.0)
        print(
            f"  cyclictest     us p50 {base['p50']} p99 {base['p99']} max {base['max']}; "
            f"{100 * late:.3f}% of its wake-ups later than one period",
            file=out,
        )
    if span:
        print(
            f"  cycle makespan us p50 {span['p50']} p99 {span['p99']}; compute us p50 "
            f"{comp['p50']} p99 {comp['p99']}; cpu {s['cpu_percent']}% of one CPU",
            file=out,
        )
    steal = s.get("host_steal", {}).get("ms")
    if steal:
        cpus = ", ".join(f"{cpu} {ms} ms" for cpu, ms in steal.items())
        print(f"  host steal during the run: {cpus}", file=out)
    print(f"  scheduling: manager {s['scheduling']['manager'].get('policy')}", file=out)

"""``redistro faults``: run the fault scenarios and print (and write) the table."""

from __future__ import annotations

import random
import signal
import time
from pathlib import Path
from typing import Any

from redistro.config.model import Config
from redistro.errors import ConfigError
from redistro.faults.catalogue import CATALOGUE, Scenario, by_name


def run_faults(
    cfg: Config,
    only: list[str],
    json_path: str | None,
    seed: int,
    config_args: list[str],
    list_only: bool = False,
    retries: int = 0,
) -> int:
    lockstep = cfg.session.clock == "lockstep"
    chosen, timed = _chosen(only, lockstep)
    if list_only:
        for s in chosen:
            clock = "real time" if s.timed else "any clock"
            print(f"{s.name:30s} {s.kind:11s} {clock:9s} expect {'/'.join(s.expect):30s} {s.what}")
        return 0
    from redistro.faults.common import StopWatch
    from redistro.faults.runner import ensure_calibrated, run_scenario
    from redistro.session.baseline import Baseline

    stop = StopWatch()
    if lockstep:
        print(f"in lockstep: {len(chosen)} scenarios; {len(timed)} whose verdict is a time "
              f"run in real time only (without --clock lockstep)", flush=True)  # fmt: skip
    runs = Path(cfg.session.runs_dir).resolve()
    ensure_calibrated(runs, cfg, config_args, print)
    baseline = Baseline(runs)
    rng = random.Random(seed)
    rows: list[dict[str, Any]] = []
    for s in chosen:
        if stop.requested():
            break
        print(f"{s.name}: {s.what}", flush=True)
        baseline.restore()
        t0 = time.monotonic()
        row = run_scenario(s, runs, cfg, config_args, rng)
        earlier: list[dict[str, Any]] = []
        while not row["passed"] and len(earlier) < retries and not stop.requested():
            print("  " + _line(row) + "; once more", flush=True)
            earlier.append(row)
            baseline.restore()
            row = run_scenario(s, runs, cfg, config_args, rng)
        row["attempts"] = len(earlier) + 1
        row["took_s"] = round(time.monotonic() - t0, 1)  # (every attempt, on the wall clock)
        if earlier:
            row["failed_attempts"] = earlier
        if stop.requested():
            row["interrupted"] = True  # (its session was ended by the stop)
        rows.append(row)
        print("  " + _line(row), flush=True)
    baseline.restore()
    passed = sum(1 for r in rows if r["passed"])
    print(f"{passed} of {len(rows)} scenarios passed")
    stopped = stop.requested()
    if stopped:
        name = signal.Signals(stopped).name
        print(f"stopped by {name} after {len(rows)} of {len(chosen)} scenarios")
    if json_path:
        doc: dict[str, Any] = {"clock": cfg.session.clock, "scenarios": rows}
        if lockstep:
            doc["left_out"] = timed  # (their verdicts are times)
        if stopped:
            doc["stopped_by"] = name
        from redistro.process.session_owner import write_json

        write_json(Path(json_path), doc)
        print(f"wrote {json_path}")
    if stopped:
        return 128 + stopped
    return 0 if passed == len(rows) else 1


def _chosen(only: list[str], lockstep: bool) -> tuple[list[Scenario], list[str]]:
    """The scenarios to run, and the timed ones among those asked for
    (in lockstep they are left out; named with --only, refused)."""
    try:
        chosen: list[Scenario] = [by_name(n) for n in only] if only else list(CATALOGUE)
    except KeyError as exc:
        names = ", ".join(s.name for s in CATALOGUE)
        raise ConfigError(f"--only {exc.args[0]}: no such scenario (known: {names})") from None
    timed = [s.name for s in chosen if s.timed]
    if lockstep and only and timed:
        raise ConfigError(
            f"--only {timed[0]}: its verdict is a time, it runs in real time only "
            f"(without --clock lockstep)"
        )
    if lockstep:
        chosen = [s for s in chosen if not s.timed]
    return chosen, timed


def _line(r: dict[str, Any]) -> str:
    parts = [
        "PASS" if r["passed"] else "FAIL",
        f"got {r['got']} (expected {'/'.join(r['expected'])})",
    ]
    if "detection_ms" in r:
        parts.append(
            f"detected by {r['detected_by']} in {r['detection_ms']:.1f} ms "
            f"({r['detection_cycles']:.1f} cycles)"
        )
    elif "detection_node_cycles" in r:  # (lockstep: its cycles alone)
        parts.append(f"detected by {r['detected_by']} in {r['detection_node_cycles']} cycles")
    if "freeze_ms" in r:
        parts.append(f"frozen {r['freeze_ms']:.1f} ms after")
    if "estop_spread_ms" in r:
        parts.append(f"every node stopped within {r['estop_spread_ms']:.1f} ms")
    if r.get("count"):
        parts.append(", ".join(f"{k} {v}" for k, v in r["count"].items()))
    parts.append(f"left: {r.get('processes_left', 0)} processes, {len(r.get('ipc_left', []))} IPC")
    if r.get("error"):
        parts.append(f"error: {r['error']}")
    if r.get("cause"):
        parts.append(f"cause: {r['cause']}")
    return "; ".join(parts)

"""``redistro faults``: run the fault scenarios and print (and write) the table."""

from __future__ import annotations

import random
import signal
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
    try:
        chosen: list[Scenario] = [by_name(n) for n in only] if only else list(CATALOGUE)
    except KeyError as exc:
        names = ", ".join(s.name for s in CATALOGUE)
        raise ConfigError(f"--only {exc.args[0]}: no such scenario (known: {names})") from None
    if list_only:
        for s in chosen:
            print(f"{s.name:26s} {s.kind:11s} expect {'/'.join(s.expect):30s} {s.what}")
        return 0
    from redistro.faults.common import StopWatch
    from redistro.faults.runner import ensure_calibrated, run_scenario
    from redistro.session.baseline import Baseline

    stop = StopWatch()
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
        row = run_scenario(s, runs, cfg, config_args, rng)
        earlier: list[dict[str, Any]] = []
        while not row["passed"] and len(earlier) < retries and not stop.requested():
            print("  " + _line(row) + "; once more", flush=True)
            earlier.append(row)
            baseline.restore()
            row = run_scenario(s, runs, cfg, config_args, rng)
        row["attempts"] = len(earlier) + 1
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
        doc: dict[str, Any] = {"scenarios": rows}
        if stopped:
            doc["stopped_by"] = name
        from redistro.process.session_owner import write_json

        write_json(Path(json_path), doc)
        print(f"wrote {json_path}")
    if stopped:
        return 128 + stopped
    return 0 if passed == len(rows) else 1


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

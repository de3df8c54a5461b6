"""Every node at 1 kHz, both arms, the short peg insertion, N runs in a row.

    python tools/khz_runs.py [--runs 10] [--out docs/perf/khz] [--prefix after]

Each run is ``redistro bench group tasks/peg_insertion_short.yaml --set
esc.rate_hz=1000 --set ssc.rate_hz=1000`` (cyclictest at 1 kHz beside it)
in a fresh runs folder (a self-calibration first, not measured). From each
run's session log it reads how the workers started: for every process on a
node's cycle, the cycles it let pass before it first signed its heartbeat,
and the oldest its heartbeat got in the node's first 200 cycles (a worker
busy with a first-call cost misses heartbeats there: 25 ended a session).
The JSON goes to ``OUT/PREFIX-runN.json``; a Markdown table is printed.
Exit 0 only when every run ended ``ok``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

TASK = "tasks/peg_insertion_short.yaml"
SETS = ["esc.rate_hz=1000", "ssc.rate_hz=1000"]
FIRST = 200  # the node's first cycles looked at
OFF_CYCLE = ("ddm", "logger", "recorder")  # the workers off the node's cycle


def start_figures(run_dir: Path) -> dict[str, Any]:
    """Per node and process on the cycle: cycles before the first heartbeat,
    the oldest heartbeat age in the first FIRST cycles."""
    import numpy as np

    from redistro.log.mcapfile import read_log

    sl = read_log(run_dir / "session.mcap")
    nodes = sl.nodes()
    out: dict[str, Any] = {}
    for topic, tm in sorted(sl.arrays.items()):
        if not topic.endswith("/timing") or len(tm) == 0:
            continue
        node = topic.split("/")[1]
        procs = list(nodes.get(node, {}).get("processes", []))
        cycles = tm["log_cycle"][:FIRST].astype(np.int64)
        hb = tm["heartbeat_cycle"][:FIRST].astype(np.int64)
        for j, name in enumerate(procs):
            if name in OFF_CYCLE:
                continue  # they sign when they step: a ddm on data, a recorder at 50 Hz
            signed = np.flatnonzero(hb[:, j] > 0)
            first = int(cycles[signed[0]] - cycles[0]) if signed.size else FIRST
            age = int(np.max(cycles - hb[:, j])) if signed.size else FIRST
            out[f"{node}/{name}"] = {"first_heartbeat_after_cycles": first, "max_age_cycles": age}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--out", type=Path, default=Path("docs/perf/khz"))
    ap.add_argument("--prefix", default="after")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for k in range(1, args.runs + 1):
        runs = Path(tempfile.mkdtemp(prefix="redistro-khz-"))
        path = args.out / f"{args.prefix}-run{k}.json"
        cmd = [sys.executable, "-m", "redistro.cli", "--set", f"session.runs_dir={runs}"]
        for s in SETS:
            cmd += ["--set", s]
        subprocess.run([*cmd, "bench", "group", TASK, "--json", str(path)],
                       check=False, capture_output=True)  # fmt: skip
        doc: dict[str, Any] = json.loads(path.read_text()) if path.exists() else {}
        run_dir = Path(doc.get("run_dir") or "")
        if run_dir.is_dir() and (run_dir / "session.mcap").exists():
            doc["start"] = start_figures(run_dir)
            path.write_text(json.dumps(doc, indent=1) + "\n")
        rows.append(doc)
        shutil.rmtree(runs, ignore_errors=True)
        print(_row(k, doc), flush=True)
    ok = sum(1 for d in rows if d.get("result") == "ok")
    print(f"{ok} of {len(rows)} runs ended ok")
    return 0 if ok == len(rows) else 1


def _row(k: int, doc: dict[str, Any]) -> str:
    start: dict[str, dict[str, int]] = doc.get("start", {})
    worst: tuple[str, dict[str, int]] = max(
        start.items(), key=lambda kv: kv[1]["max_age_cycles"], default=("-", {})
    )
    ct = doc.get("cyclictest_us") or {}
    nodes = doc.get("nodes") or {}
    overruns = ", ".join(f"{n} {v.get('overrun_percent', '-')}" for n, v in sorted(nodes.items()))
    return (
        f"| {k} | {doc.get('result', 'no result')} {doc.get('reason', '')} | "
        f"{start.get('ssc/worker', {}).get('first_heartbeat_after_cycles', '-')} | "
        f"{worst[0]} {worst[1].get('max_age_cycles', '-')} | {overruns} | "
        f"{ct.get('p50', '-')}/{ct.get('p99', '-')}/{ct.get('max', '-')} |"
    )


if __name__ == "__main__":
    sys.exit(main())

"""Regenerate the robot-group figures of docs/PERFORMANCE.md (and the README's
peg figure) from fresh runs on this machine.

    python tools/perf_runs.py [--runs 3] [--prefix after] [--out docs/perf/group]
                              [--only main-socket,main-reflective,1khz] [--figure]

Each benchmark is ``redistro bench group`` with the command docs/PERFORMANCE.md
gives, run ``--runs`` times in turn, each in a fresh runs folder (a
self-calibration first, not measured); the JSON goes to
``OUT/PREFIX-NAME-runN.json`` and a Markdown table of the headline figures is
printed at the end. Run nothing else meanwhile: the figures are the
machine's. ``--figure`` also runs the short peg insertion and redraws
``docs/figures/peg-r2-wrench-world.png``.
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

BENCHES: dict[str, tuple[str, list[str]]] = {
    "main-socket": ("tasks/peg_insertion.yaml", ["ddm.transport=socket"]),
    "main-reflective": ("tasks/peg_insertion.yaml", ["ddm.transport=reflective"]),
    "1khz": ("tasks/peg_insertion_short.yaml", ["esc.rate_hz=1000", "ssc.rate_hz=1000"]),
}
FIGURE = Path("docs/figures/peg-r2-wrench-world.png")


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "redistro.cli", *args]


def _row(name: str, f: dict[str, Any]) -> str:
    nodes = f["nodes"]
    over = ", ".join(f"{n['overrun_percent']}" for n in nodes.values())
    lat = "; ".join(
        f"{d['command_latency_us']['p50']}/{d['command_latency_us']['p99']}"
        for d in f["ddm"].values()
    )
    ct = f.get("cyclictest_us") or {}
    result = f"{f['result']}{', inserted' if f.get('inserted') else ''}"
    return (
        f"| {name} | {result} | {over} | {f['plant']['rtf']} | {lat} | "
        f"{f['log']['dropped']} | {f['group_cpu_percent']} | "
        f"{ct.get('p50')}/{ct.get('p99')}/{ct.get('max')} |"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tools/perf_runs.py", description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--prefix", default="after")
    ap.add_argument("--out", type=Path, default=Path("docs/perf/group"))
    ap.add_argument("--only", default=",".join(BENCHES))
    ap.add_argument("--figure", action="store_true")
    a = ap.parse_args(argv)
    names = [n for n in a.only.split(",") if n]
    unknown = [n for n in names if n not in BENCHES]
    if unknown or a.runs < 1:
        print(f"tools/perf_runs.py: --only {','.join(unknown)}: known {', '.join(BENCHES)}; "
              f"--runs {a.runs}: at least 1", file=sys.stderr)  # fmt: skip
        return 2
    a.out.mkdir(parents=True, exist_ok=True)
    rows = []
    scratch = Path(tempfile.mkdtemp(prefix="redistro-perf-"))
    try:
        for n in range(1, a.runs + 1):
            for name in names:
                task, sets = BENCHES[name]
                path = a.out / f"{a.prefix}-{name}-run{n}.json"
                runs = scratch / f"{name}-{n}"
                args = [x for kv in [*sets, f"session.runs_dir={runs}"] for x in ("--set", kv)]
                print(f"== {name} run {n}: {path}", flush=True)
                subprocess.run(
                    _cli(*args, "bench", "group", task, "--json", str(path)), check=False
                )
                if path.exists():
                    rows.append(_row(f"{name} {n}", json.loads(path.read_text())))
        if a.figure:
            run = scratch / "figure"
            subprocess.run(
                _cli("--set", f"session.runs_dir={scratch / 'figure-runs'}", "session",
                     "tasks/peg_insertion_short.yaml", "--out", str(run)),
                check=False,
            )  # fmt: skip
            subprocess.run(_cli("log", "plot", str(run), "--out", str(run / "plots")), check=False)
            shutil.copy(run / "plots" / "r2-wrench-world.png", FIGURE)
            print(f"wrote {FIGURE}")
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    print("| run | result | overrun % per node | plant RTF | DDM latency p50/p99 µs per robot "
          "| log cycles dropped | group CPU % | cyclictest p50/p99/max µs |")  # fmt: skip
    print("| --- | --- | --- | ---: | --- | ---: | ---: | --- |")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())

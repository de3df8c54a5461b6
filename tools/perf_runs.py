"""Regenerate the robot-group figures of docs/PERFORMANCE.md (and the README's
peg figure) from fresh runs on this machine.

    python tools/perf_runs.py [--runs 3] [--prefix after] [--out docs/perf/group]
                              [--only main-socket,main-reflective,main-zenoh,1khz,selfcal-1khz]
                              [--figure]
    python tools/perf_runs.py --ddm-sweep [--runs 3] [--out DIR] [--transports zenoh]
                                                         # bench ddm, N = 1..16
    python tools/perf_runs.py --peg-campaigns            # docs/perf/peg: 20 trials per transport

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
    "main-zenoh": ("tasks/peg_insertion.yaml", ["ddm.transport=zenoh"]),
    "1khz": ("tasks/peg_insertion_short.yaml", ["esc.rate_hz=1000", "ssc.rate_hz=1000"]),
    "selfcal-1khz": ("tasks/self_calibration_short.yaml", ["esc.rate_hz=1000"]),
}
FIGURE = Path("docs/figures/peg-r2-wrench-world.png")
CAMPAIGN_FIGURE = Path("docs/figures/peg-campaign.png")
SWEEP = (1, 2, 4, 8, 16)
TRANSPORTS = ("socket", "reflective", "zenoh")


def ddm_sweep(runs: int, out: Path, transports: tuple[str, ...] = TRANSPORTS) -> int:
    """``redistro bench ddm`` for each transport and N in SWEEP, 200 Hz, 10 s."""
    out.mkdir(parents=True, exist_ok=True)
    print("| transport | N | run | command p50/p99/max µs | feedback p50/p99/max µs "
          "| commands/s | lost | SSC ddm CPU % | ESC ddm CPU % (max) |")  # fmt: skip
    print("| --- | ---: | ---: | --- | --- | ---: | ---: | ---: | ---: |")
    for k in range(1, runs + 1):
        for t in transports:
            for n in SWEEP:
                path = out / f"{t}-n{n}-run{k}.json"
                subprocess.run(
                    _cli("bench", "ddm", "--transport", t, "--robots", str(n), "--rate", "200",
                         "--seconds", "10", "--json", str(path)),
                    check=False, capture_output=True,
                )  # fmt: skip
                if not path.exists():
                    print(f"| {t} | {n} | {k} | (no figures) | | | | | |")
                    continue
                f = json.loads(path.read_text())
                c, b = f["command_latency_us"], f["feedback_latency_us"]
                print(
                    f"| {t} | {n} | {k} | {c['p50']}/{c['p99']}/{c['max']} | "
                    f"{b['p50']}/{b['p99']}/{b['max']} | {f['commands_per_s']} | "
                    f"{f['lost_commands']} | {f['ssc_cpu_percent']} | {f['esc_cpu_percent_max']} |",
                    flush=True,
                )
    return 0


def peg_campaigns(out: Path) -> int:
    """20 short insertions per transport, the hole within 3 mm and 2 degrees
    (seeds 0-19), and the README's campaign figure from the socket one."""
    out.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix="redistro-peg-"))
    try:
        for t in TRANSPORTS:
            path = out / f"campaign-{t}.json"
            plot = out / f"campaign-{t}.png"
            subprocess.run(
                _cli("--set", f"session.runs_dir={scratch / t}", "--set", f"ddm.transport={t}",
                     "bench", "peg", "--trials", "20", "--offset-radius-mm", "3", "--yaw-deg", "2",
                     "--seed", "0", "--json", str(path), "--plot", str(plot)),
                check=False,
            )  # fmt: skip
            if t == "socket" and plot.exists():
                shutil.copy(plot, CAMPAIGN_FIGURE)
                print(f"wrote {CAMPAIGN_FIGURE}")
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return 0


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
    ap.add_argument("--out", type=Path, default=None, help="(docs/perf/group; a sweep: .../ddm)")
    ap.add_argument("--only", default=",".join(BENCHES))
    ap.add_argument("--figure", action="store_true")
    ap.add_argument("--ddm-sweep", action="store_true", help="bench ddm, every transport and N")
    ap.add_argument("--transports", default=",".join(TRANSPORTS), help="(a sweep's)")
    ap.add_argument("--peg-campaigns", action="store_true", help="bench peg, every transport")
    a = ap.parse_args(argv)
    if a.ddm_sweep:
        chosen = tuple(t for t in a.transports.split(",") if t)
        if not chosen or any(t not in TRANSPORTS for t in chosen):
            print(f"tools/perf_runs.py: --transports {a.transports}: "
                  f"one or more of {', '.join(TRANSPORTS)}", file=sys.stderr)  # fmt: skip
            return 2
        return ddm_sweep(a.runs, a.out or Path("docs/perf/ddm"), chosen)
    if a.peg_campaigns:
        return peg_campaigns(Path("docs/perf/peg"))
    names = [n for n in a.only.split(",") if n]
    unknown = [n for n in names if n not in BENCHES]
    if unknown or a.runs < 1:
        print(f"tools/perf_runs.py: --only {','.join(unknown)}: known {', '.join(BENCHES)}; "
              f"--runs {a.runs}: at least 1", file=sys.stderr)  # fmt: skip
        return 2
    a.out = a.out or Path("docs/perf/group")
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

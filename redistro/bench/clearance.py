"""``redistro bench clearance``: the SSC's clearance watch, CPU per cycle.

The watch (:class:`redistro.ssc.clearance.ClearanceWatch`: both arms of the
config and the work-cell) is fed postures as the SSC feeds it measured ones, at the SSC's
rate, and each call is timed with ``thread_time``:

- ``rest``: both arms at their configured postures, ``seconds`` long;
- ``approach``: r1 steered at 0.4 rad/s per joint toward a posture that
  reaches into r2 (the ``arms-collide`` fault's), until the watch trips.

Per case: CPU per cycle (p50, p99, max, mean), pairs measured per cycle,
and for the approach where it tripped.
"""

from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np

from redistro.config.model import Config


def _figures(times_ns: list[int], pairs: list[int]) -> dict[str, Any]:
    us = np.asarray(times_ns, dtype=np.float64) / 1e3
    return {
        "cycles": len(times_ns),
        "cpu_us": {
            "p50": round(float(np.percentile(us, 50)), 2),
            "p99": round(float(np.percentile(us, 99)), 2),
            "max": round(float(us.max()), 2),
            "mean": round(float(us.mean()), 2),
        },
        "pairs_per_cycle": {"mean": round(float(np.mean(pairs)), 2), "max": int(max(pairs))},
    }


def _case(cfg: Config, rate_hz: float, cycles: int, steer: bool) -> dict[str, Any]:
    from redistro.faults.hooks import COLLIDE_RAD_S, INTO_R2
    from redistro.ssc.clearance import ClearanceWatch

    watch = ClearanceWatch(cfg, ["r1", "r2"], 1.0 / rate_hz)
    q1 = np.asarray(cfg.robots["r1"].initial_q_rad, dtype=np.float64).copy()
    q2 = np.asarray(cfg.robots["r2"].initial_q_rad, dtype=np.float64)
    step = COLLIDE_RAD_S / rate_hz
    clock = time.thread_time_ns
    times, pairs, hit = [], [], None
    for k in range(cycles):
        if steer:
            q1 += np.clip(INTO_R2 - q1, -step, step)
        before = watch.measured
        c0 = clock()
        hit = watch.check([q1, q2], k / rate_hz)
        times.append(clock() - c0)
        pairs.append(watch.measured - before)
        if hit is not None:
            break
    out = _figures(times[1:], pairs[1:])  # (the first cycle measures every pair)
    out["first_cycle_us"] = round(times[0] / 1e3, 1)
    out["pairs"] = len(watch.v)
    if hit is not None:
        out["tripped"] = {
            "t_s": round((len(times) - 1) / rate_hz, 3),
            "distance_m": round(hit.distance_m, 4),
            "once_stopped_m": round(hit.ahead_m, 4),
            "links": list(hit.links),
        }
    return out


def run(cfg: Config, rate_hz: float, seconds: float) -> dict[str, Any]:
    cycles = max(2, int(seconds * rate_hz))
    return {
        "rate_hz": rate_hz,
        "rest": _case(cfg, rate_hz, cycles, steer=False),
        "approach": _case(cfg, rate_hz, int(30 * rate_hz), steer=True),
    }


def print_figures(f: dict[str, Any], out: Any = sys.stdout) -> None:
    print(f"bench clearance: the SSC's clearance watch at {f['rate_hz']:g} Hz", file=out)
    for case in ("rest", "approach"):
        r = f[case]
        c = r["cpu_us"]
        line = (
            f"  {case:8s} {r['cycles']} cycles: CPU p50 {c['p50']} / p99 {c['p99']} / max "
            f"{c['max']} / mean {c['mean']} us; pairs per cycle {r['pairs_per_cycle']['mean']} "
            f"(max {r['pairs_per_cycle']['max']} of {r['pairs']})"
        )
        if "tripped" in r:
            t = r["tripped"]
            line += (
                f"; tripped at t={t['t_s']} s, {t['distance_m'] * 100:.1f} cm apart "
                f"({t['links'][0]}, {t['links'][1]})"
            )
        print(line, file=out)

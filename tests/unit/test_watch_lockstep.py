"""A worker off the cycle (the SSC's logger) in lockstep: its heartbeat
limit holds in wall time, not in the plant's ticks, which run as fast as the
CPUs allow (a paused task's ticks ran 200 past a logger that was on time)."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import pytest

from redistro.errors import NodeFault
from redistro.localdata.segment import LocalData
from redistro.process.watch import WorkerWatch, node_local_data

ROOT = Path(__file__).parents[2]


def _watch(clock: str) -> tuple[WorkerWatch, LocalData, int]:
    from redistro.config.loader import load_config
    from redistro.config.task import load_task
    from redistro.ssc.plan import ssc_spec

    cfg = load_config(ROOT / "config" / "redistro.yaml", [])
    task = load_task(ROOT / "tasks" / "peg_insertion_short.yaml", cfg)
    from redistro.ipc import names

    sid = names.new_session_id()
    spec = dataclasses.replace(ssc_spec(cfg, task, sid, run_dir=""), clock=clock)
    ld = node_local_data(spec, int(1e9 / spec.rate_hz), None, memory=True)
    watch = WorkerWatch(spec, None)
    watch.attach(ld)
    logger = next(j for j, w in enumerate(spec.workers) if w.role == "logger")
    return watch, ld, logger


def _sign_all(ld: LocalData, watch: WorkerWatch, cycle: int, but: int) -> None:
    """Every worker signs ``cycle`` but worker ``but``."""
    for j in range(len(watch.spec.workers)):
        if j == but:
            continue
        with ld.block("proc", j).write() as d:
            d["heartbeat_cycle"] = cycle


@pytest.mark.parametrize("clock", ["lockstep", "realtime"])
def test_a_logger_hundreds_of_ticks_behind_in_a_second_is_hung_only_in_real_time(
    clock: str,
) -> None:
    watch, ld, logger = _watch(clock)
    limit = watch.limits[logger]
    period = int(1e9 / watch.spec.rate_hz)
    cycle = limit + 5  # (ticks the logger did not sign, within a few ms of wall time)
    _sign_all(ld, watch, cycle, logger)
    if clock == "realtime":
        with pytest.raises(NodeFault, match=f"missed {cycle} heartbeats"):
            watch.check_heartbeats(cycle, time.monotonic_ns(), period)
        return
    watch.check_heartbeats(cycle, time.monotonic_ns(), period)  # (no fault: not a wall second)
    watch.signed_ns[logger] -= limit * period  # its limit in wall time gone by
    with pytest.raises(NodeFault, match=f"missed {cycle} heartbeats"):
        watch.check_heartbeats(cycle, time.monotonic_ns(), period)

"""The parts of lockstep that need no session: the tick source, the log's
digest runs, the run digest, and the replay's first difference."""

from __future__ import annotations

import numpy as np

from redistro.ipc.timer import IntervalTimer, LockstepTicks, tick_source
from redistro.localdata.layout import FEEDBACK, GUARD, PLAN
from redistro.log.mcapfile import run_digest
from redistro.log.recorder import digest_runs
from redistro.session.replay import _first_in


def test_the_tick_source_follows_the_clock() -> None:
    assert isinstance(tick_source(200.0, "realtime"), IntervalTimer)
    ticks = tick_source(200.0, "lockstep")
    assert isinstance(ticks, LockstepTicks)
    assert ticks.period_ns == IntervalTimer(200.0).period_ns == 5_000_000
    # a lockstep tick is never late nor missed: the plant sends it when due
    assert ticks.due(123_456) == (123_456, 0, 0)


def _logged(block: np.dtype) -> np.dtype:
    return np.dtype([("log_cycle", "<u8"), *[(n, block.fields[n][0]) for n in block.names]])


def test_the_digest_covers_every_byte_but_the_wall_clock_stamps() -> None:
    for block in (FEEDBACK, PLAN, GUARD):
        dtype = _logged(block)
        runs = digest_runs(dtype)
        covered = np.zeros(dtype.itemsize, dtype=bool)
        for a, b in runs:
            assert a < b
            covered[a:b] = True
        for name in dtype.names:
            ft, off = dtype.fields[name][:2]
            span = covered[off : off + ft.itemsize]
            assert (not span.any()) if name.endswith("_ns") else span.all(), name
        # (only fields: padding would be skipped too)
        assert covered.sum() == sum(
            dtype.fields[n][0].itemsize for n in dtype.names if not n.endswith("_ns")
        )


def test_the_run_digest_is_the_nodes_in_order_whatever_the_dict_order() -> None:
    a = {"ssc": {"digest": "aa"}, "esc.r1": {"digest": "bb"}}
    b = {"esc.r1": {"digest": "bb"}, "ssc": {"digest": "aa"}}
    assert run_digest(a) == run_digest(b)
    assert run_digest(a) != run_digest({"ssc": {"digest": "ab"}, "esc.r1": {"digest": "bb"}})


def test_the_first_difference_names_the_cycle_and_the_field() -> None:
    dtype = np.dtype([("log_cycle", "<u8"), ("stamp_ns", "<i8"), ("q", "<f8", (3,)), ("s", "u1")])
    x = np.zeros(10, dtype)
    x["log_cycle"] = np.arange(5, 15)
    x["stamp_ns"] = np.arange(10)  # the wall clock: never a difference
    y = x.copy()
    y["stamp_ns"] += 1000
    assert _first_in("/r1/feedback", x, y) is None
    y["s"][7] = 1
    y["q"][4, 2] = 1e-12
    found = _first_in("/r1/feedback", x, y)
    assert found is not None
    assert (found["cycle"], found["field"]) == (9, "q"), found
    assert found["replayed"][2] == 1e-12
    # a run that ends sooner: the first cycle it lacks
    assert _first_in("/r1/feedback", x, x[:6])["field"] == "(cycles)"  # type: ignore[index]

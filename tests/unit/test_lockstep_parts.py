"""The parts of lockstep that need no session: the tick source, the log's
digest runs, the run digest, the first difference, the cycles' digests."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from redistro.ipc.timer import IntervalTimer, LockstepTicks, tick_source
from redistro.localdata.layout import FEEDBACK, GUARD, PLAN
from redistro.log.diff import _digests, _first_in
from redistro.log.mcapfile import run_digest
from redistro.log.recorder import digest_runs


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


def test_the_cycles_digests_count_the_cycles_that_differ_and_find_the_first() -> None:
    dtype = np.dtype([("log_cycle", "<u8"), ("digest", "u1", (16,))])
    x = np.zeros(8, dtype)
    x["log_cycle"] = np.arange(1, 9)
    x["digest"] = np.arange(8 * 16).reshape(8, 16) % 251
    assert _digests(x, x.copy()) == {"cycles": [8, 8], "differing": 0}
    y = x.copy()
    y["digest"][3, 15] ^= 1
    y["digest"][6, 0] ^= 1
    assert _digests(x, y) == {"cycles": [8, 8], "differing": 2, "first_cycle": 4}
    # a log that ends sooner: its missing cycles differ, from the first it lacks
    assert _digests(x, x[:5]) == {"cycles": [8, 5], "differing": 3, "first_cycle": 6}
    # a node only one log has: every one of its cycles
    assert _digests(x, None) == {"cycles": [8, 0], "differing": 8, "first_cycle": 0}


def test_the_plant_steps_above_every_node_and_waits_below_them(monkeypatch: Any) -> None:
    """In lockstep the plant raises its real-time priority for the physics
    alone (the SSC's processes no longer break into it) and drops back to
    its own while it waits on the nodes; not real time, it leaves it alone."""
    import os

    from redistro.config.model import PAPER_PRIORITIES
    from redistro.ipc import sched
    from redistro.plant.process import _step_priority

    monkeypatch.setattr(sched, "is_real_time", lambda: True)
    monkeypatch.setattr(os, "sched_getparam", lambda pid: os.sched_param(1))
    own, stepping = _step_priority(dict(PAPER_PRIORITIES))  # type: ignore[misc]
    assert own.sched_priority == PAPER_PRIORITIES["plant"] == 1
    top = max(v for k, v in PAPER_PRIORITIES.items() if k != "plant")
    assert stepping.sched_priority == top + 1
    assert _step_priority({"manager": 99, "plant": 1})[1].sched_priority == 99  # type: ignore[index]
    monkeypatch.setattr(sched, "is_real_time", lambda: False)
    assert _step_priority(dict(PAPER_PRIORITIES)) is None


def test_a_wait_goes_on_for_a_node_starved_of_cpu_not_for_a_stopped_one() -> None:
    """Past its 2 s, a lockstep wait goes on while one of the nodes'
    processes is runnable (a loaded host starves it of CPU), and gives up
    on a stopped or blocked one (its heartbeat check then finds it)."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from types import SimpleNamespace

    from redistro.ipc.sched import runnable as _runnable
    from redistro.plant.lockstep import Group

    spin = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    nap = subprocess.Popen(["sleep", "30"])
    try:
        group = Group("sid")
        group.escs = [SimpleNamespace(live=True, log=None, pids=[spin.pid])]  # type: ignore[list-item]
        assert _runnable(os.getpid())  # (this one, reading)
        deadline = time.monotonic() + 10
        while not group._going("escs", None) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert group._going("escs", None), "the spinning process never showed runnable"
        os.kill(spin.pid, signal.SIGSTOP)
        while group._going("escs", None) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not group._going("escs", None), "a stopped process counted as runnable"
        while _runnable(nap.pid) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not _runnable(nap.pid)  # (asleep)
        assert not _runnable(2**22 + 7)  # (no such process)
    finally:
        for p in (spin, nap):
            p.kill()
            p.wait()


def test_a_process_whose_other_thread_spins_is_runnable() -> None:
    """A transport's own thread (zenoh's) carries records: a process whose
    main thread sleeps while another spins is runnable, not blocked."""
    import subprocess
    import sys
    import time

    from redistro.ipc.sched import runnable

    code = (
        "import threading, time\n"
        "threading.Thread(target=lambda: [0 for _ in iter(int, 1)]).start()\n"
        "time.sleep(60)"
    )
    p = subprocess.Popen([sys.executable, "-c", code])

    def main_thread() -> bytes:  # (its state alone: what /proc/PID/stat shows)
        with open(f"/proc/{p.pid}/stat", "rb") as f:
            return f.read().rsplit(b")", 1)[1].split()[0]

    try:
        deadline = time.monotonic() + 10
        while main_thread() != b"S" and time.monotonic() < deadline:
            time.sleep(0.005)  # (until it is in its sleep: past its start's R and D)
        assert main_thread() == b"S"
        seen = False
        while not seen and time.monotonic() < deadline:
            seen = runnable(p.pid)
            time.sleep(0.01)
        assert seen, "a process with a spinning thread never showed runnable"
    finally:
        p.kill()
        p.wait()


def test_a_later_stage_waits_on_for_a_starved_one_in_lockstep_alone() -> None:
    """A collecting point gives up at its deadline in real time; in
    lockstep it waits on while the previous stage's process is runnable
    (a loaded host: the run stays the same to the bit), not when it is
    stopped."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from redistro.ipc.sched import runnable
    from redistro.localdata.block import Record
    from redistro.localdata.layout import PROC_STATUS
    from redistro.process.worker import _Runner

    class Row:  # a previous stage's status row: its cycle signed from ``at`` on
        def __init__(self, pid: int, at: float) -> None:
            self.pid, self.at = pid, at

        def read_into(self, buf: Any) -> None:
            r = Record(PROC_STATUS, buf)
            r["pid"] = self.pid
            r["heartbeat_cycle"] = 7 if time.monotonic() >= self.at else 6

    class Go:
        def try_acquire(self) -> bool:
            return False

        def acquire(self, timeout: float) -> None:
            time.sleep(min(timeout, 0.005))

    spin = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        deadline = time.monotonic() + 10
        while not runnable(spin.pid) and time.monotonic() < deadline:
            time.sleep(0.01)

        def wait(lockstep: bool, signs_in_s: float) -> bool:
            preds = [(Row(spin.pid, time.monotonic() + signs_in_s), Record(PROC_STATUS))]
            due = time.monotonic_ns() + 50_000_000  # (50 ms)
            return _Runner._wait_stage(7, preds, Go(), due, lockstep)  # type: ignore[arg-type]

        assert not wait(False, 0.3)  # real time: the deadline is the deadline
        assert wait(True, 0.3)  # lockstep: starved, waited for
        os.kill(spin.pid, signal.SIGSTOP)
        while runnable(spin.pid) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not wait(True, 1.0)  # stopped: not waited for past the deadline
    finally:
        spin.kill()
        spin.wait()


def test_a_paused_task_ticks_on_the_wall_clock_and_a_running_one_at_once() -> None:
    """While the operator holds the task paused, a tick comes no sooner
    than a node period after the last (the group held still needs no CPU,
    and the operator's hand works in wall time); running, at once."""
    import time

    from redistro.plant.lockstep import Group

    group = Group("sid")  # (no nodes: a tick is the physics step alone)
    group.period_ns = 20_000_000
    flag = bytearray(1)
    group.paused_word = memoryview(flag)
    steps: list[int] = []

    def ticks(n: int) -> None:
        for _ in range(n):
            group.tick(lambda: steps.append(time.monotonic_ns()))

    ticks(1)
    flag[0] = 1
    first = group.last_ns
    ticks(5)  # paused: each tick a period after the last, at least
    assert group.last_ns - first >= 5 * group.period_ns
    assert group.paced == 5
    flag[0] = 0
    ticks(50)
    assert group.paced == 5 and len(steps) == 56  # running: no tick held back
    # with a pace (session.lockstep_pace 4: a 5 ms tick's time is 1.25 ms of
    # the wall clock), every tick no sooner than that after the last
    group.period_ns, group.pace_ns = 5_000_000, 1_250_000
    began = [group.last_ns]
    for _ in range(20):
        group.tick(lambda: None)
        began.append(group.last_ns)  # (when each tick began)
    gaps = np.diff(began)
    assert (gaps >= group.pace_ns).all() and group.paced == 25, gaps


def test_a_wait_sleeps_on_the_bell_and_looks_anyway_when_nobody_rings() -> None:
    """The plant's wait sleeps on the session's bell: a node's ring wakes
    it to look again; with no ring it looks anyway after LOOK_S. A ringer
    before the plant made its bell rings nothing."""
    from types import SimpleNamespace

    from redistro.ipc import bell
    from redistro.ipc.session import Session
    from redistro.plant.lockstep import LIVE, Group

    with Session.create() as s:
        sid = s.id
        ringer = bell.Ringer(sid)
        ringer.ring()  # (no bell yet: nothing, and no error)
        plant = bell.create(sid)
        try:
            group = Group(sid)
            group.bell = plant
            node = SimpleNamespace(live=True, log=None, pids=[], state=lambda: LIVE[0])
            group.escs = [node]  # type: ignore[list-item]
            looks = []

            def done() -> bool:
                looks.append(1)
                return len(looks) > 1

            ringer.ring()  # a node rang: the wait takes it, looks again, done
            group._wait(done, "escs")
            assert (group.rung, group.unrung, len(looks)) == (1, 0, 2)
            looks.clear()
            group._wait(done, "escs")  # nobody rings: one look after LOOK_S
            assert (group.rung, group.unrung, len(looks)) == (1, 1, 2)
        finally:
            ringer.close()
            plant.close()
            plant.unlink()


def test_in_lockstep_a_board_may_go_unpublished_as_long_as_a_start_may_take() -> None:
    """The drivers' I/O timeout: ``plant.io_timeout_ms`` in real time; in
    lockstep at least the start-up timeout (a plant starved of CPU is slow,
    not gone: it is the clock)."""
    from redistro.config import load_config
    from redistro.errors import ConfigError
    from redistro.esc.common import io_timeout_s
    from tests.helpers import ROOT

    path = ROOT / "config/redistro.yaml"
    cfg = load_config(path)
    assert io_timeout_s(cfg) == cfg.plant.io_timeout_ms / 1e3 == 0.5
    cfg = load_config(path, ["session.clock=lockstep", "session.startup_timeout_s=12"])
    assert io_timeout_s(cfg) == 12.0
    sets = ["session.clock=lockstep", "session.startup_timeout_s=2", "plant.io_timeout_ms=3000"]
    assert io_timeout_s(load_config(path, sets)) == 3.0  # (the longer of the two)
    with pytest.raises(ConfigError, match="io_timeout_ms"):  # (over its bound: refused)
        load_config(path, ["plant.io_timeout_ms=20000"])

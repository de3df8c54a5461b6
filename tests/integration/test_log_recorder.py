"""The recorder against real Local Data, a real log ring and a real writer
process: what goes in comes back out of the MCAP file, a recorder held off
catches up from the ring, and a writer that falls behind makes the recorder
drop and count, never wait."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from redistro.ipc.session import Session
from redistro.localdata import LocalData
from redistro.localdata.layout import BLOCKS
from redistro.log.mcapfile import SESSION_LOG, finish_run_log, read_log
from redistro.log.recorder import CycleRecorder
from redistro.log.ring import Capture, LogRing, Progress, RingLayout
from redistro.log.schema import dtype_from_msg, msg_definition, with_cycle
from redistro.process.spec import NodeSpec, WorkerSpec

ROLES = ["acquisition", "pid", "sender", "recorder"]


@pytest.fixture
def node() -> Iterator[tuple[LocalData, NodeSpec]]:
    with Session.create() as session:
        ld = LocalData.create(
            session.id,
            "esc.r1",
            node_kind="esc",
            proc_names=ROLES,
            proc_roles=ROLES,
            proc_stages=[0, 1, 2, 3],
            robot_names=["r1"],
            rate_hz=200.0,
            period_ns=5_000_000,
            heartbeat_limit_cycles=5,
            manifest=session.manifest,
        )
        spec = NodeSpec(
            session_id=session.id,
            node="esc.r1",
            kind="esc",
            rate_hz=200.0,
            heartbeat_limit_cycles=5,
            workers=[WorkerSpec(name=r, role=r, stage=i) for i, r in enumerate(ROLES)],
            robots=["r1"],
        )
        try:
            yield ld, spec
        finally:
            ld.close()
            ld.unlink()


META = {"physics_hz": 1000.0, "robots": {"r1": {"base_xyz_m": [0, 0.45, 0], "peg": None}}}
TOPICS: list[tuple[str, str, int | None]] = [
    ("/r1/feedback", "feedback", 0),
    ("/r1/guard", "guard", 0),
]


@pytest.fixture
def ring(node: tuple[LocalData, NodeSpec]) -> Iterator[Capture]:
    """The manager's part: the ring, and the capture at every tick."""
    ld, spec = node
    r = LogRing.create(spec.session_id, spec.node, RingLayout.of(TOPICS, len(ROLES)), slots=64)
    cap = Capture(r, ld)
    try:
        yield cap
    finally:
        del cap
        r.close()
        r.unlink()


def _started(node: tuple[LocalData, NodeSpec], tmp_path: Path) -> tuple[LocalData, CycleRecorder]:
    """A recorder on the node's Local Data with its writer process running."""
    ld, spec = node
    rec = CycleRecorder(ld, spec, TOPICS, str(tmp_path), META)
    rec.start()
    return ld, rec


def _drive(
    ld: LocalData, rec: CycleRecorder, cap: Capture, cycles: range, drain_every: int = 1
) -> None:
    """Cycles as a node runs them: the blocks written, the manager's capture
    at the next tick, the recorder draining (every ``drain_every`` cycles)."""
    mgr = ld.writer("manager", role="manager")
    fb = ld.writer("feedback", 0, role="acquisition")
    row = ld.writer("proc", 1, role="pid", proc_index=1)
    box = ld.msgbox(2)
    now = time.monotonic_ns()
    for c in cycles:
        due = now + c * 5_000_000
        with mgr.write() as d:
            d["cycle"] = c
            d["tick_due_ns"] = due
            d["tick_ns"] = due + 40_000
        with fb.write() as d:
            d["q_rad"][:] = np.arange(7) * 0.01 + c * 1e-4
            d["step"] = 5 * c
        with row.write() as d:
            d["heartbeat_cycle"] = c
            d["wake_ns"] = due + 100_000
            d["done_ns"] = due + 350_000
        if c == 3:
            box.post("a message from the sender", 40)
        cap(c, due, due + 40_000, False)
        if c % drain_every == 0:
            rec.drain()


def test_every_block_has_a_ros2_definition_that_reads_back() -> None:
    for name, (payload, _) in BLOCKS.items():
        dt = with_cycle(payload)
        back = dtype_from_msg(msg_definition(dt))
        assert back.itemsize == dt.itemsize, name
        assert back.names == dt.names, name


def test_recorded_cycles_read_back_exactly(
    node: tuple[LocalData, NodeSpec], ring: Capture, tmp_path: Path
) -> None:
    ld, rec = _started(node, tmp_path)
    _drive(ld, rec, ring, range(1, 401))
    rec.event("segments", 200, robot="r1", segment=2, name="counter_clockwise")
    stats = rec.close()
    assert stats["recorded"] == 400 and stats["dropped"] == 0
    info = finish_run_log(tmp_path)
    assert info["file"] == SESSION_LOG and info["nodes"]["esc.r1"]["complete"]
    sl = read_log(tmp_path / SESSION_LOG)
    for topic in ("/r1/feedback", "/r1/guard", "/esc.r1/timing"):
        assert sl.counts[topic] == 400, topic
        assert np.array_equal(sl.arrays[topic]["log_cycle"], np.arange(1, 401))
    fb = sl.arrays["/r1/feedback"]
    assert np.allclose(fb["q_rad"][-1], np.arange(7) * 0.01 + 400e-4)
    assert np.array_equal(fb["step"], 5 * np.arange(1, 401))
    tm = sl.arrays["/esc.r1/timing"]
    assert np.allclose(tm["late_us"][:, 1], 100.0) and np.allclose(tm["busy_us"][:, 1], 250.0)
    assert np.allclose(tm["tick_late_us"], 40.0)
    assert sl.events["/esc.r1/segments"][0]["name"] == "counter_clockwise"
    texts = [e["text"] for e in sl.events["/esc.r1/messages"]]
    assert texts == ["a message from the sender"]
    assert sl.meta("redistro.recording")["recorded"] == 400
    assert sl.robots()["r1"]["base_xyz_m"] == [0, 0.45, 0]


def test_a_recorder_held_off_catches_up_from_the_ring(
    node: tuple[LocalData, NodeSpec], ring: Capture, tmp_path: Path
) -> None:
    """Held off for 40 cycles of a 64-slot ring, the recorder records every
    cycle once it runs; held off for 100, it counts the 36 it lost."""
    ld, rec = _started(node, tmp_path)
    _drive(ld, rec, ring, range(1, 401), drain_every=40)
    assert rec.recorded == 400 and rec.overwritten == 0
    _drive(ld, rec, ring, range(401, 501), drain_every=100)
    assert rec.recorded == 464 and rec.overwritten == 36
    stats = rec.close()
    assert stats["dropped"] == 36
    finish_run_log(tmp_path)
    cycles = read_log(tmp_path / SESSION_LOG).arrays["/r1/feedback"]["log_cycle"]
    assert np.array_equal(cycles, np.r_[1:401, 437:501])


def test_a_stalled_writer_makes_the_recorder_wait_in_the_ring_then_count(
    node: tuple[LocalData, NodeSpec], ring: Capture, tmp_path: Path
) -> None:
    ld, rec = _started(node, tmp_path)
    assert rec.proc is not None
    os.kill(rec.proc.pid, signal.SIGSTOP)  # the writer stops draining the pipe
    try:
        t0 = time.monotonic()
        _drive(ld, rec, ring, range(1, 6001))
        spent = time.monotonic() - t0
    finally:
        os.kill(rec.proc.pid, signal.SIGCONT)
    assert rec.pipe_full > 0, "the pipe never filled"
    # recording went on at its own pace: not one cycle waited for the writer
    # (6000 cycles in well under the 30 s they would take at 200 Hz)
    assert spent < 30.0
    stats = rec.close()
    # the cycles waited in the 64-cycle ring; those overwritten meanwhile are lost
    assert stats["recorded"] + stats["overwritten"] == 6000
    assert stats["dropped"] == stats["overwritten"] > 0
    finish_run_log(tmp_path)
    sl = read_log(tmp_path / SESSION_LOG)
    cycles = sl.arrays["/r1/feedback"]["log_cycle"]
    assert len(cycles) == stats["recorded"]
    assert np.all(np.diff(cycles.astype(np.int64)) > 0)  # in order, none twice


def test_the_ring_shows_how_far_the_recorder_lags_and_its_last_drain_takes_every_cycle(
    node: tuple[LocalData, NodeSpec], ring: Capture, tmp_path: Path
) -> None:
    """The ring's header tells an outside reader (the lockstep plant) how
    many captured cycles the recorder has not taken; its last drain, at
    Cleanup, waits for a writer that had fallen behind and hands every
    cycle left to the worker's own figures (``on_cycle``), none dropped."""
    ld, spec = node
    ld, rec = _started(node, tmp_path)
    progress = Progress.attach(spec.session_id, spec.node)
    assert progress is not None and progress.slots == 64
    assert Progress.attach(spec.session_id, "esc.r9") is None  # (a node that logs nothing)
    assert rec.proc is not None
    os.kill(rec.proc.pid, signal.SIGSTOP)  # the writer stops draining the pipe
    try:
        c = 0
        while rec.pipe_full == 0 and c < 50_000:
            c += 1
            _drive(ld, rec, ring, range(c, c + 1))
            assert progress.lag() == c - (rec.next - 1)
        assert rec.pipe_full > 0, "the pipe never filled"
        waiting = c - (rec.next - 1)  # (the cycle that did not fit, at least)
        _drive(ld, rec, ring, range(c + 1, c + 31), drain_every=10**9)  # not drained
        assert progress.lag() == waiting + 30
    finally:
        os.kill(rec.proc.pid, signal.SIGCONT)
    seen: list[int] = []
    stats = rec.close(seen.append)
    assert seen == list(range(c - waiting + 1, c + 31))
    assert stats["dropped"] == 0 and stats["recorded"] == c + 30
    assert progress.lag() == 0
    progress.close()


def test_the_lockstep_plant_holds_its_tick_while_a_log_is_half_a_ring_behind(
    node: tuple[LocalData, NodeSpec], ring: Capture
) -> None:
    """A tick as fast as the CPUs allow could starve the log's writer until
    the ring overwrote cycles never logged; the plant waits for it first."""
    from types import SimpleNamespace

    from redistro.plant.lockstep import Group

    _, spec = node
    progress = Progress.attach(spec.session_id, spec.node)
    assert progress is not None
    group = Group(spec.session_id)
    group.escs = [SimpleNamespace(live=True, log=progress)]  # type: ignore[list-item]
    assert group.logging
    ring.ring._captured[0] = 100
    ring.ring.drained = 67  # 33 behind: over half the 64 slots
    assert not group._logs_kept()
    ring.ring.drained = 68
    assert group._logs_kept()
    group.escs[0].live = False  # (a node that ended is not waited for)
    ring.ring.drained = 0
    assert group._logs_kept()
    progress.close()

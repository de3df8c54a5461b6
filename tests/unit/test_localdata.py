"""Local Data in one process: layout, blocks, message boxes, writer rules;
the contract of both backings (POSIX shared memory, the in-process stand-in)."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest

from redistro.errors import IPCError, LayoutError, TornReadTimeout
from redistro.localdata import LocalData, segment_dtype
from redistro.localdata.layout import ALIGN, MSGBOX_SLOTS, layout_hash
from tests.helpers import esc_segment


@pytest.fixture(params=["shm", "memory"])
def ld(request: pytest.FixtureRequest) -> Iterator[LocalData]:
    procs = [("acquisition", "acquisition", 0), ("pid", "pid", 1), ("sender", "sender", 2)]
    with esc_segment(procs, memory=request.param == "memory") as (_, seg):
        yield seg


def test_blocks_sit_on_their_own_cache_lines() -> None:
    dt = segment_dtype(5, 2)
    assert dt.fields is not None
    for name, (_, offset, *_) in dt.fields.items():
        assert offset % ALIGN == 0, name
    assert dt.itemsize % ALIGN == 0
    assert layout_hash(5, 2) != layout_hash(5, 1)


def test_attach_checks_header_and_sees_static_data(ld: LocalData) -> None:
    sid = bytes(ld.header["session_id"]).decode()
    other = LocalData.attach(sid, "esc.r1", memory=ld.memory)
    try:
        assert other.proc_names() == ["acquisition", "pid", "sender"]
        assert other.node_kind == "esc"
        assert float(other.static["rate_hz"]) == 200.0
        assert int(other.static["proc_stage"][2]) == 2
    finally:
        other.close()
    with pytest.raises(IPCError, match="does not exist"):
        LocalData.attach(sid, "esc.r9", memory=ld.memory)


def test_attach_refuses_a_different_layout(ld: LocalData) -> None:
    sid = bytes(ld.header["session_id"]).decode()
    ld.view["header"]["layout_hash"] = 12345
    with pytest.raises(LayoutError, match="layout hash"):
        LocalData.attach(sid, "esc.r1", memory=ld.memory)


def test_only_the_declared_writer_gets_a_write_handle(ld: LocalData) -> None:
    ld.writer("feedback", 0, role="acquisition")
    ld.writer("command", 0, role="ddm")
    ld.writer("proc", 1, role="pid", proc_index=1)
    with pytest.raises(LayoutError, match="written by acquisition, not pid"):
        ld.writer("feedback", 0, role="pid")
    with pytest.raises(LayoutError, match="written only by process 1"):
        ld.writer("proc", 1, role="pid", proc_index=2)
    with pytest.raises(LayoutError, match="needs an index"):
        ld.block("feedback")
    with pytest.raises(LayoutError, match="no block named"):
        ld.block("nope")


def test_write_then_read_round_trips(ld: LocalData) -> None:
    w = ld.writer("feedback", 0, role="acquisition")
    with w.write() as d:
        d["q_rad"] = np.arange(7) * 0.1
        d["estop"] = 1
    r = ld.block("feedback", 0).read()
    assert np.allclose(r["q_rad"], np.arange(7) * 0.1)
    assert int(r["estop"]) == 1
    assert w.seq == 2  # even: no write in progress


def test_publish_and_read_into(ld: LocalData) -> None:
    w = ld.writer("feedback", 0, role="acquisition")
    rec = np.zeros((), w.data.dtype)
    rec["tau_nm"] = 3.0
    w.publish(rec)
    out = np.zeros((), w.data.dtype)
    ld.block("feedback", 0).read_into(out)
    assert np.all(out["tau_nm"] == 3.0)
    # byte memoryviews both ways (the polling fast path)
    rec["tau_nm"] = 4.0
    src = memoryview(rec.reshape(1).view(np.uint8))  # type: ignore[arg-type]
    w.publish(src)
    into = memoryview(out.reshape(1).view(np.uint8))  # type: ignore[arg-type]
    ld.block("feedback", 0).read_into(into)
    assert np.all(out["tau_nm"] == 4.0)
    assert w.seq == 4
    src.release()
    into.release()


def test_spin_until_changed(ld: LocalData) -> None:
    w = ld.writer("feedback", 0, role="acquisition")
    r = ld.block("feedback", 0)
    w.publish(np.zeros((), w.data.dtype))
    soon = time.monotonic_ns() + 2_000_000
    assert r.spin_until_changed(0, soon) == 2  # already changed: returns at once
    assert r.spin_until_changed(2, soon) == 2  # nothing new: gives up at the deadline
    assert time.monotonic_ns() >= soon
    w._seq[0] = 3  # mid-write: an odd count is not a change
    assert r.spin_until_changed(2, time.monotonic_ns() + 1_000_000) == 2


def test_a_block_left_mid_write_is_never_returned(ld: LocalData) -> None:
    w = ld.writer("feedback", 0, role="acquisition")
    r = ld.block("feedback", 0)
    w._seq[0] = 7  # a writer died inside its write
    with pytest.raises(TornReadTimeout):
        r.read(budget_s=0.001)
    assert r.torn > 0
    with w.write() as d:  # the next write repairs the count
        d["estop"] = 0
    assert w.seq % 2 == 0
    r.read()


def test_message_box_ring(ld: LocalData) -> None:
    box_w = ld.msgbox(1)
    box_r = ld.msgbox(1)
    box_w.post("hello")
    box_w.post("x" * 500)  # cut to fit, never overflowing the slot
    got = box_r.drain()
    assert got[0][2] == "hello"
    assert len(got[1][2]) < 500
    for i in range(MSGBOX_SLOTS + 5):
        box_w.post(f"m{i}")
    got = box_r.drain()
    assert len(got) == MSGBOX_SLOTS
    assert got[-1][2] == f"m{MSGBOX_SLOTS + 4}"
    assert box_r.lost == 5
    assert box_r.drain() == []


def test_a_name_is_created_once_and_attached_only_while_it_exists(ld: LocalData) -> None:
    sid = bytes(ld.header["session_id"]).decode()
    with pytest.raises(IPCError, match="already exists"):
        LocalData.create(
            sid,
            "esc.r1",
            node_kind="esc",
            proc_names=["a"],
            proc_roles=["acquisition"],
            proc_stages=[0],
            robot_names=["r1"],
            rate_hz=200.0,
            period_ns=5_000_000,
            heartbeat_limit_cycles=5,
            manifest=None,
            memory=ld.memory,
        )
    other = LocalData.attach(sid, "esc.r1", memory=ld.memory)
    seen = other.block("feedback", 0)
    ld.writer("feedback", 0, role="acquisition").publish(np.ones((), seen.data.dtype))
    assert float(seen.read()["q_rad"][0]) == 1.0  # one memory, two attachments
    other.close()


def test_after_the_unlink_no_one_attaches() -> None:
    for memory in (False, True):
        with esc_segment([("a", "acquisition", 0)], memory=memory) as (sid, seg):
            seg.unlink()
            with pytest.raises(IPCError, match="does not exist"):
                LocalData.attach(sid, "esc.r1", memory=memory)

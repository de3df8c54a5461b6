"""The Manager's loop and its bookkeeping in one process: the node's Local
Data in memory, fake workers that sign their rows when their sync comes.
No process, no signal, no timer: each tick is taken at a time the test
gives (``Manager.tick``)."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest

from redistro.errors import NodeFault
from redistro.ipc.names import new_session_id
from redistro.localdata.block import Record
from redistro.localdata.layout import MANAGER, PROC_STATUS
from redistro.process.manager import Manager
from redistro.process.spec import NodeSpec, WorkerSpec

PERIOD_NS = 10_000_000  # 100 Hz
LIMIT = 5


class FakeWorker:
    """What a worker process does with its sync, in this process: read the
    manager's cycle, do nothing for ``work_ns``, sign the row."""

    def __init__(self, m: Manager, j: int, work_ns: int = 1_000_000) -> None:
        assert m.ld is not None
        name = m.spec.workers[j].name
        self.row = m.ld.writer("proc", j, role=name, proc_index=j)
        self.box = m.ld.msgbox(j)
        self.manager = m.ld.block("manager")
        self.rec = Record(PROC_STATUS)
        self.mgr = Record(MANAGER)
        self.work_ns = work_ns
        self.hang = False
        self.estop = False
        self.synced = 0

    def sync(self) -> None:
        self.synced += 1
        if self.hang:
            return
        self.manager.read_into(self.mgr.bytes)
        self.rec["heartbeat_cycle"] = self.mgr["cycle"]
        self.rec["cycles"] = self.rec["cycles"] + 1
        self.rec["done_ns"] = self.mgr["tick_due_ns"] + self.work_ns
        self.rec["estop_request"] = 1 if self.estop else 0
        self.row.publish(self.rec.bytes)


def _spec(cycles: int = 0) -> NodeSpec:
    return NodeSpec(
        session_id=new_session_id(),
        node="bench",
        kind="bench",
        rate_hz=1e9 / PERIOD_NS,
        heartbeat_limit_cycles=LIMIT,
        workers=[WorkerSpec(name="a", role="busy", stage=0), WorkerSpec("b", "busy", stage=1)],
        cycles=cycles,
    )


@pytest.fixture
def node() -> Iterator[tuple[Manager, list[FakeWorker]]]:
    m = Manager(_spec(), spec_path="")
    ld = m.open_local_data(None, memory=True)
    workers = [FakeWorker(m, j) for j in range(2)]
    m.on_cycle = workers  # type: ignore[assignment]  # the children the sync goes to
    m.timer.start_ns = 0
    yield m, workers
    ld.close()
    ld.unlink()


def _ticks(m: Manager, first: int, last: int, late_ns: int = 50_000) -> None:
    for k in range(first, last + 1):
        assert m.tick(k * PERIOD_NS + late_ns) is False


def test_every_tick_publishes_the_cycle_and_syncs_every_worker(
    node: tuple[Manager, list[FakeWorker]],
) -> None:
    m, workers = node
    _ticks(m, 1, 20)
    assert m.cycle == 20 and [w.synced for w in workers] == [20, 20]
    assert m.ld is not None
    seen = m.ld.block("manager").read()
    assert int(seen["cycle"]) == 20 and int(seen["tick_due_ns"]) == 20 * PERIOD_NS
    watch = m.watch
    assert watch.late_heartbeats == watch.missed_heartbeats == 0
    assert watch.deadline_misses == watch.incomplete_cycles == 0
    assert watch.makespan.count == 19  # every cycle that ended, its last stage's span
    assert m.timing.lateness.summary_us()["p50"] == pytest.approx(50.0)
    assert m.timing.overruns == m.timing.missed_ticks == 0


def test_a_late_tick_counts_the_ticks_it_missed(node: tuple[Manager, list[FakeWorker]]) -> None:
    m, _ = node
    _ticks(m, 1, 3)
    m.tick(6 * PERIOD_NS + 1000)  # ticks 4 and 5 never came
    assert m.timing.missed_ticks == 2 and m.timing.overruns == 1 and m.cycle == 4


def test_a_hung_worker_ends_the_node_at_its_limit(node: tuple[Manager, list[FakeWorker]]) -> None:
    m, workers = node
    _ticks(m, 1, 5)
    workers[1].hang = True  # signed cycle 5, then nothing
    _ticks(m, 6, 5 + LIMIT)  # cycles 6..9 end unsigned; tick 10 checks cycle 9
    assert m.watch.missed_heartbeats > 0 and m.watch.incomplete_cycles == LIMIT - 1
    with pytest.raises(NodeFault, match=r"worker b \(pid 0\) missed 5 heartbeats \(limit 5\)"):
        m.tick((6 + LIMIT) * PERIOD_NS)  # cycle 10 ended: 5 cycles since b's last
    assert m.watch.hung == {1}


def test_a_worker_that_asks_for_an_e_stop_ends_the_node(
    node: tuple[Manager, list[FakeWorker]],
) -> None:
    m, workers = node
    _ticks(m, 1, 3)
    workers[0].estop = True
    _ticks(m, 4, 4)  # the request goes out with cycle 4's heartbeat ...
    with pytest.raises(NodeFault, match="e-stop requested by a") as fault:
        m.tick(5 * PERIOD_NS)  # ... and is seen when cycle 4 has ended
    assert fault.value.reason == "estop"


def test_a_late_last_stage_is_a_deadline_miss(node: tuple[Manager, list[FakeWorker]]) -> None:
    m, workers = node
    workers[1].work_ns = PERIOD_NS + 1  # the last stage ends after the period
    _ticks(m, 1, 4)
    assert m.watch.deadline_misses == 3


def test_the_node_ends_at_its_cycle_count() -> None:
    m = Manager(_spec(cycles=3), spec_path="")
    ld = m.open_local_data(None, memory=True)
    try:
        m.on_cycle = [FakeWorker(m, j) for j in range(2)]  # type: ignore[misc]
        m.timer.start_ns = 0
        assert [m.tick(k * PERIOD_NS) for k in range(1, 5)] == [False, False, False, True]
        assert m.cycle == 3
    finally:
        ld.close()
        ld.unlink()


def test_message_boxes_keep_the_last_error_and_a_failed_workers_reason(
    node: tuple[Manager, list[FakeWorker]],
) -> None:
    m, workers = node
    workers[0].box.post("starting")
    workers[1].box.post("link lost", logging.ERROR)
    m.watch.drain_messages()
    assert m.last_error == {"b": "link lost"}
    assert [x["text"] for x in m.watch.messages] == ["starting", "link lost"]
    workers[1].box.post("failed at cycle 3: boom", logging.CRITICAL)
    with pytest.raises(NodeFault, match=r"worker b \(pid 0\) failed at cycle 3: boom"):
        m.watch.check_failed()


def test_the_workers_figures_come_from_their_rows(node: tuple[Manager, list[FakeWorker]]) -> None:
    m, _ = node
    _ticks(m, 1, 7)
    got = m.watch.worker_results(routine_s=1.0, exits=["exited with code 0"] * 2)
    assert [(w.name, w.stage, w.cycles, w.exit) for w in got] == [
        ("a", 0, 7, "exited with code 0"),
        ("b", 1, 7, "exited with code 0"),
    ]

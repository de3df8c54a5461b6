"""The read-only view watchers take of a running node's Local Data (the
session's progress, the owner's e-stop relay, ``top``, the fault runner),
on a real segment."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from redistro.localdata import LocalData
from redistro.localdata.view import NodeView
from tests.helpers import esc_segment


@pytest.fixture
def node() -> Iterator[tuple[str, LocalData]]:
    with esc_segment(
        [("acquisition", "acquisition", 0), ("sender.main", "sender", 1), ("ddm", "ddm", -1)]
    ) as made:
        yield made


def test_a_view_reads_what_the_writers_published(node: tuple[str, LocalData]) -> None:
    sid, seg = node
    with seg.block("manager").write() as m:
        m["cycle"], m["estop"], m["pid"] = 42, 1, 4242
    with seg.block("proc", 1).write() as p:
        p["pid"], p["cycles"] = 777, 40
    with seg.block("feedback", 0).write() as f:
        f["seq_src"] = 9
    view = NodeView.open(sid, "esc.r1")
    assert view is not None
    with view:
        assert view.kind == "esc" and view.node == "esc.r1"
        assert view.cycle() == 42 and view.estop()
        assert view.pid("manager") == 4242
        # a worker by its name or, failing that, by its role
        assert view.pid("sender.main") == view.pid("sender") == 777
        assert int(view.proc("sender")["cycles"]) == 40
        assert int(view.read("feedback", 0)["seq_src"]) == 9
        assert view.procs()[1] == ("sender.main", "sender")
        # one handle per block, however often it is read
        assert view.block("manager") is view.block("manager")
        with seg.block("manager").write() as m:
            m["cycle"] = 43
        assert view.cycle() == 43
        with pytest.raises(ValueError):
            view.proc("pid")


def test_no_node_no_view(node: tuple[str, LocalData]) -> None:
    sid, _ = node
    assert NodeView.open(sid, "esc.r9") is None
    assert NodeView.open("20000101T000000-000000", "esc.r1") is None

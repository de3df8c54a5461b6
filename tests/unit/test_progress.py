"""The session's progress display: an ESC node's segments, bar and text."""

from __future__ import annotations

from typing import Any

from redistro.process.spec import NodeSpec, WorkerSpec
from redistro.session.progress import Progress


class FakeView:
    """A node's view with one robot's setpoint and the manager's cycle."""

    def __init__(self, setpoint: dict[str, Any], cycle: int) -> None:
        self.setpoint, self.cycle = setpoint, cycle

    def read(self, name: str, index: int | None = None) -> dict[str, Any]:
        assert (name, index) == ("setpoint", 0)
        return self.setpoint

    def manager(self) -> dict[str, Any]:
        return {"cycle": self.cycle}

    def close(self) -> None:
        pass


def _progress(segments: list[dict[str, Any]]) -> tuple[Progress, dict[str, Any]]:
    worker = WorkerSpec(name="calibration", role="calibration", stage=1)
    spec = NodeSpec("sid", "esc.r1", "esc", 200.0, 25, [worker])
    spec.node_params.segments = segments
    lines: list[str] = []
    p = Progress("sid", [spec], lines.append, live=False)
    sp = {"segment": 0, "done": 0, "segment_t_s": 0.0}
    p.views["esc.r1"] = FakeView(sp, 7)  # type: ignore[assignment]  # attached
    return p, sp


def test_the_bar_never_goes_back_while_the_last_segment_settles() -> None:
    segs = [{"name": "park", "duration_s": 3.0}]
    p, sp = _progress(segs)
    assert p._node(p.specs[0]) == ("esc.r1 cycle 7", 0.0, 3.0)
    sp.update(segment=1, segment_t_s=2.9)
    text, done, total = p._node(p.specs[0])
    assert "1/1 park" in text and done == 2.9 and total == 3.0
    # settling: the worker's segment clock runs on past the duration
    sp.update(segment_t_s=3.2)
    text, done, _ = p._node(p.specs[0])
    assert text == "esc.r1 1/1 park done, settling" and done == 3.0
    sp.update(done=1)
    assert p._node(p.specs[0]) == ("esc.r1 done", 3.0, 3.0)


def test_segments_add_up() -> None:
    segs = [{"name": "a", "duration_s": 2.0}, {"name": "b", "duration_s": 1.5}]
    p, sp = _progress(segs)
    sp.update(segment=2, segment_t_s=0.5)
    text, done, total = p._node(p.specs[0])
    assert text.startswith("esc.r1 2/2 b") and done == 2.5 and total == 3.5
    lines: list[str] = []
    p.out = lines.append
    p.next = 0.0  # due now: one plain line (no terminal here)
    p()
    p()  # not due again within a second
    assert len(lines) == 1 and lines[0].endswith("esc.r1 2/2 b   0.5/1.5 s"), lines

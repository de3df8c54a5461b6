"""Injection points: where the fault harness breaks a running session from inside.

A point is named ``where.what`` (e.g. ``plant.encoder-jump``,
``ddm.link-close``). The harness arms one point for one session through the
environment every process of the session inherits::

    REDISTRO_INJECT='{"point": "plant.encoder-jump", "node": "", "robot": "r2",
                      "trigger": "/run/folder/inject.trigger"}'

and fires it by creating the trigger file, at the moment it chooses (after
r2 started moving). A process that owns the point asks :func:`injection` once
(None when this session carries no such point: nothing to pay in normal
runs), then ``live()`` where the fault would act: it looks for the trigger at
most every 2 ms and, the first time it sees it, writes ``<trigger>.fired``
(``{"monotonic_ns": ..., "pid": ...}``): detection latencies count from
there (the plant writes it once the step that carries the fault is on the
boards).
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field

ENV = "REDISTRO_INJECT"
CHECK_EVERY_NS = 2_000_000


@dataclass
class Injection:
    point: str
    node: str = ""  # the node whose process acts ("" : whichever owns the point)
    robot: str = ""  # the robot the fault concerns ("" : every robot of the process)
    trigger: str = ""
    arg: float = 0.0
    fired_ns: int = 0
    defer_record: bool = False
    recorded: bool = False
    _next_ns: int = field(default=0, repr=False)

    def live(self) -> bool:
        """True from the moment the trigger file exists (checked at most every 2 ms)."""
        if self.fired_ns:
            return True
        now = time.monotonic_ns()
        if now < self._next_ns:
            return False
        self._next_ns = now + CHECK_EVERY_NS
        if not self.trigger or not os.path.exists(self.trigger):
            return False
        self.fired_ns = now
        if not self.defer_record:
            self.record(now)
        return True

    def record(self, when_ns: int) -> None:
        """Write ``<trigger>.fired``: when the fault took effect. The plant
        records after the step that put it on the boards (``defer_record``)."""
        if self.recorded:
            return
        self.recorded = True
        tmp = f"{self.trigger}.fired.{os.getpid()}"
        try:
            with open(tmp, "w", encoding="utf-8") as f:
                json.dump({"monotonic_ns": when_ns, "pid": os.getpid(), "point": self.point}, f)
            os.replace(tmp, f"{self.trigger}.fired")
        except OSError:
            pass  # the run folder went away: the fault still acts

    def concerns(self, robot: str) -> bool:
        return not self.robot or robot == self.robot


def injection(point: str, node: str = "") -> Injection | None:
    """The armed injection at ``point`` for ``node``, or None. A ``point``
    ending in ``.`` takes any point of that family (``plant.``)."""
    raw = os.environ.get(ENV)
    if not raw:
        return None
    try:
        d = json.loads(raw)
    except ValueError:
        return None
    armed = str(d.get("point", ""))
    if armed != point and not (point.endswith(".") and armed.startswith(point)):
        return None
    if d.get("node") and node and d["node"] != node:
        return None
    return Injection(
        point=armed,
        node=str(d.get("node", "")),
        robot=str(d.get("robot", "")),
        trigger=str(d.get("trigger", "")),
        arg=float(d.get("arg", 0.0)),
    )


def arm(point: str, trigger: str, *, node: str = "", robot: str = "", arg: float = 0.0) -> str:
    """The environment value that arms ``point`` (for the session's environment)."""
    return json.dumps(
        {"point": point, "node": node, "robot": robot, "trigger": trigger, "arg": arg}
    )

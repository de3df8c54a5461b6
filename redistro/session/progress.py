"""Progress: what a running session shows, read from its nodes' Local Data."""

from __future__ import annotations

import contextlib
import logging
import sys
import time
from collections.abc import Callable
from typing import Any

from redistro.config.model import Config
from redistro.localdata.view import NodeView
from redistro.process.spec import NodeSpec

log = logging.getLogger(__name__)


class Progress:
    """Where each node is in its segments: a progress bar per node with the
    current segment on a terminal (rich), else a plain line about once a second."""

    def __init__(
        self,
        session_id: str,
        specs: list[NodeSpec],
        out: Callable[[str], None],
        live: bool | None = None,
    ) -> None:
        self.session_id = session_id
        self.specs = specs
        self.out = out
        self.t0 = time.monotonic()
        self.next = self.t0 + 1.0
        self.views: dict[str, NodeView] = {}
        self.ssc_segments: list[tuple[str, float]] = []
        self.live = sys.stdout.isatty() if live is None else live
        self.bars: Any = None
        self.tasks: dict[str, Any] = {}

    def __call__(self) -> None:
        now = time.monotonic()
        if now < self.next:
            return
        self.next = now + (0.25 if self.live else 1.0)
        try:
            self._show(now)
        except Exception:  # progress is for people: it must never end a session
            log.debug("progress display failed", exc_info=True)

    def _show(self, now: float) -> None:
        rows = [self._node(spec) for spec in self.specs]
        if not self.live:
            self.out(f"[{now - self.t0:6.1f} s] " + " | ".join(r[0] for r in rows))
            return
        if self.bars is None:
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

            self.bars = Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                TextColumn("{task.percentage:>3.0f}%"),
                TimeElapsedColumn(),
            )
            self.bars.start()
        for spec, (text, done_s, total_s) in zip(self.specs, rows, strict=True):
            task = self.tasks.get(spec.node)
            if task is None:
                task = self.tasks[spec.node] = self.bars.add_task(text, total=total_s or 1.0)
            self.bars.update(task, description=text, completed=done_s)

    def _node(self, spec: NodeSpec) -> tuple[str, float, float]:
        """(text, seconds of segments done, seconds of all segments)."""
        segs: list[dict[str, Any]]
        if spec.kind == "ssc":
            segs = [{"name": n, "duration_s": d} for n, d in self.ssc_segments]
        else:
            segs = list(spec.node_params.segments)
        total = float(sum(float(s["duration_s"]) for s in segs))
        view = self.views.get(spec.node)
        if view is None:
            view = NodeView.open(self.session_id, spec.node)
            if view is None:
                return f"{spec.node} starting", 0.0, total
            self.views[spec.node] = view
        try:
            sp = view.read("setpoint", 0)
            mgr = view.manager()
        except Exception:
            return f"{spec.node}", 0.0, total
        if spec.kind == "ssc":
            return self._ssc(spec, view, int(mgr["cycle"]), total)
        k = int(sp["segment"])
        if int(sp["done"]):
            return f"{spec.node} done", total, total
        if k == 0:
            return f"{spec.node} cycle {int(mgr['cycle'])}", 0.0, total
        seg = segs[k - 1]
        t = float(sp["segment_t_s"])
        dur = float(seg["duration_s"])
        done = sum(float(s["duration_s"]) for s in segs[: k - 1]) + min(t, dur)
        text = f"{spec.node} {k}/{len(segs)} {seg['name']} {t:5.1f}/{seg['duration_s']:g} s"
        if k == len(segs) and t > dur:
            text = f"{spec.node} {k}/{len(segs)} {seg['name']} done, settling"
        return text, done, total

    def _ssc(
        self, spec: NodeSpec, view: NodeView, cycle: int, total: float
    ) -> tuple[str, float, float]:
        names = self.ssc_segments
        moving: list[str] = []
        k, t = 0, 0.0
        for i in range(len(spec.robots)):
            pl = view.read("plan", i)
            if int(pl["done"]):
                return "ssc done", total, total
            if int(pl["moving"]):
                moving.append(spec.robots[i])
                k, t = int(pl["segment"]), float(pl["segment_t_s"])
        if moving and 1 <= k <= len(names):
            name, dur = names[k - 1]
            done = sum(d for _, d in names[: k - 1]) + min(t, dur)
            who = "+".join(moving)
            return f"ssc {k}/{len(names)} {name} ({who}) {t:5.1f}/{dur:g} s", done, total
        return f"ssc cycle {cycle}", 0.0, total

    def close(self) -> None:
        if self.bars is not None:
            with contextlib.suppress(Exception):
                self.bars.stop()
            self.bars = None
        for view in self.views.values():
            view.close()
        self.views.clear()


def ddm_pace(cfg: Config) -> str:
    """How the ddms run, for people."""
    return f"at {cfg.ddm.rate_hz:g} Hz" if cfg.ddm.rate_hz > 0 else "on data"

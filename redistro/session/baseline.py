"""The saved state a series of sessions starts each run from.

Between power-offs the runs folder keeps what the robots' next session
starts from: the controller's positions files (``positions/<robot>.json``)
and the plant's pose of the arms (``plant-pose.json``). A series of runs
that must not depend on each other (the fault scenarios, a campaign of peg
insertions) takes them once and puts them back before each run: a run may
leave an arm anywhere, its positions unclean or a file broken on purpose.
"""

from __future__ import annotations

import contextlib
from pathlib import Path


class Baseline:
    """The positions files and the arms' pose, as they were when taken."""

    def __init__(self, runs: Path) -> None:
        self.runs = runs
        self.files: dict[Path, bytes] = {}
        for p in [*sorted((runs / "positions").glob("*.json")), runs / "plant-pose.json"]:
            with contextlib.suppress(OSError):
                self.files[p] = p.read_bytes()

    def restore(self) -> None:
        for p in (self.runs / "positions").glob("*.json"):
            if p not in self.files:
                p.unlink()
        from redistro import files

        for p, data in self.files.items():
            p.parent.mkdir(parents=True, exist_ok=True)
            files.replace(p, data)

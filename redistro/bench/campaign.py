"""A campaign of whole sessions of one task, each from the same saved
state (``bench peg``, ``bench dual``): known joint positions (a
self-calibration first when unknown), the arms where the last session left
them, the positions files and the pose put back before each trial."""

from __future__ import annotations

import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from redistro.config.model import Config
from redistro.errors import RedistroError

CALIBRATION_TASK = "tasks/self_calibration.yaml"


def median(rows: list[dict[str, Any]], key: str, digits: int = 3) -> float | None:
    """The median of ``key`` over the rows that have it (None when none do)."""
    vals = [float(r[key]) for r in rows if r.get(key) is not None]
    return round(statistics.median(vals), digits) if vals else None


def run_trials(
    cfg: Config,
    task_path: str,
    name: str,
    trials: int,
    trial_cfg: Callable[[int], Config],
    row_of: Callable[[int, int, dict[str, Any]], dict[str, Any]],
    on_trial: Callable[[dict[str, Any]], None] | None = None,
) -> tuple[list[dict[str, Any]], Path]:
    """Run ``trials`` sessions of ``task_path``, trial k under ``trial_cfg(k)``;
    each one's row from ``row_of(k, exit code, summary)``. Ctrl-C (or
    SIGTERM) ends the campaign, not only its trial. Returns the rows and the
    folder of their runs."""
    from redistro.config.task import load_task
    from redistro.session.baseline import Baseline
    from redistro.session.preflight import unknown_positions
    from redistro.session.run import plant_config, run_session

    runs = Path(cfg.session.runs_dir)
    out_root = runs / f"bench-{name}-{time.strftime('%Y%m%dT%H%M%S')}"
    if unknown_positions(cfg, load_task(task_path, cfg)):
        Path(plant_config(cfg).plant.pose_file).unlink(missing_ok=True)
        rc = run_session(
            cfg, CALIBRATION_TASK, out_dir=str(out_root / "self_calibration"), say=lambda _t: None
        )
        if rc != 0:
            raise RedistroError(f"the self-calibration before the trials ended {rc}")
    baseline = Baseline(runs)
    rows: list[dict[str, Any]] = []
    try:
        for k in range(trials):
            out_dir = out_root / f"trial-{k:02d}"
            baseline.restore()
            rc = run_session(trial_cfg(k), task_path, out_dir=str(out_dir), say=lambda _t: None)
            path = out_dir / "summary.json"
            summary = json.loads(path.read_text()) if path.exists() else {"result": "abnormal"}
            row = row_of(k, rc, summary)
            rows.append(row)
            if on_trial is not None:
                on_trial(row)
            if str(row.get("reason") or "").startswith("interrupted by"):
                break
    finally:
        baseline.restore()
    return rows, out_root

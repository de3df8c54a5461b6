"""What a lockstep session starts from (its run folder's ``replay.json``):
its config, its task file's text, and the state the arms were left in
(the joint positions files and the arms' pose kept between sessions).
``redistro replay`` (:mod:`redistro.session.replay`) restores it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from redistro import files
from redistro.config.model import Config

REPLAY_FILE = "replay.json"


def start_state(cfg: Config, task_path: str, robots: list[str]) -> dict[str, Any]:
    """The session's start, before anything runs (a self-calibration first included)."""
    from redistro.config.loader import resolved
    from redistro.session.preflight import positions_file

    def text(path: Path) -> str | None:
        try:
            return path.read_text()
        except OSError:
            return None

    pose = cfg.plant.pose_file or str(Path(cfg.session.runs_dir) / cfg.session.plant_pose_file)
    return {
        "clock": cfg.session.clock,
        "config": resolved(cfg),
        "task_name": Path(task_path).name,
        "task_text": Path(task_path).read_text(),
        "start": {
            "positions": {r: text(positions_file(cfg, r)) for r in robots},
            "plant_pose": text(Path(pose)),
        },
    }


def write_start(run_dir: Path, state: dict[str, Any]) -> None:
    files.replace(run_dir / REPLAY_FILE, json.dumps(state, indent=1) + "\n")

"""Invalid inputs: task files, configs and command lines the controller must
refuse before any process starts, in one line naming what is wrong."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

from redistro.faults.catalogue import Scenario
from redistro.faults.common import die_with_parent, one_line_refusal

TASK = Path("tasks/fault_drill.yaml")
CONFIG = Path("config/redistro.yaml")

# case -> (edit of the drill task's text, extra CLI arguments, what the line must name)
# Edits are (old, new) text replacements on the drill task.
EDITS: dict[str, tuple[tuple[str, str] | None, list[str], str]] = {
    "wrong-type": (("duration_s: 6\n", "duration_s: six\n"), [], "duration_s"),
    "unknown-key": (("    scheme: position\n", "    scheme: position\n    colour: red\n"), [],
                    "colour"),
    "unreachable-goal": (("pos_xyz_rot_xyz: [0, 0, 0.03,", "pos_xyz_rot_xyz: [0, 0, 3.0,"), [],
                         "goal"),
    "zero-duration": (("duration_s: 6\n", "duration_s: 0\n"), [], "duration_s"),
    "negative-duration": (("move_s: 5\n", "move_s: -5\n"), [], "move_s"),
    "unknown-robot": (("robots: [r1, r2]", "robots: [r1, r9]"), [], "r9"),
    "bad-config": (None, ["--set", "esc.rate_hz=-5"], "rate_hz"),
    "config-unknown-key": (None, [], "bogus_key"),
}  # fmt: skip


def run_input(sc: Scenario, out_dir: Path, config_args: list[str]) -> dict[str, Any]:
    edit, extra, names = EDITS[sc.action]
    task = TASK
    if edit is not None:
        text = TASK.read_text()
        if edit[0] not in text:
            raise ValueError(f"{sc.name}: the drill task no longer holds {edit[0]!r}")
        task = out_dir / f"{sc.action}.yaml"
        task.write_text(text.replace(edit[0], edit[1], 1))
    args = list(config_args)
    if sc.action == "config-unknown-key":
        cfg = out_dir / "redistro.yaml"
        cfg.write_text(CONFIG.read_text().replace("\nesc:", "\nesc:\n  bogus_key: 1\n ", 1))
        robots = out_dir / "robots"  # the robot files are found beside the config
        if not robots.exists():
            robots.symlink_to((CONFIG.parent / "robots").resolve())
        args = ["--config", str(cfg), *args]
    before = set(os.listdir("/dev/shm"))
    done = subprocess.run(
        [sys.executable, "-m", "redistro.cli", *args, *extra, "session", str(task),
         "--out", str(out_dir / "run")],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        preexec_fn=die_with_parent,
    )  # fmt: skip
    row: dict[str, Any] = one_line_refusal(done)
    row.update(
        {
            "names": names,
            "ipc_left": sorted(set(os.listdir("/dev/shm")) - before),
            "processes_left": 0,
            "plant_started": (out_dir / "run" / "plant.json").exists(),
        }
    )
    row["passed"] = bool(
        row["got"] == "refused"
        and row["one_line"]
        and names in row["cause"]
        and not row["ipc_left"]
        and not row["plant_started"]
    )
    return row

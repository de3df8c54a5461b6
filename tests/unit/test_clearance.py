"""The arms kept apart: the load-time check of every segment's motion
(redistro/ssc/clearance.py), on the real URDF through Pinocchio and coal."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from redistro.config.loader import load_config
from redistro.ssc.clearance import MIN_CLEARANCE_M, GroupGeometry, _time_at
from tests.helpers import run_cli

# r1 turned to face r2 (its base 0.9 m away along -y) and reaching out
INTO_R2 = [-1.5708, 1.3, 0.0, -0.4, 0.0, 0.3, 0.0]

SWING = """\
task: swing
kind: strategy
robots: [r1, r2]
segments:
  - name: reach over
    robot: r1
    scheme: joint
    duration_s: 6
    goal:
      q_rad: {q}
      move_s: 5
"""


@pytest.fixture(scope="module")
def group() -> GroupGeometry:
    return GroupGeometry(load_config(None), ["r1", "r2"])


def test_the_arms_at_their_initial_postures_are_far_apart(group: GroupGeometry) -> None:
    cfg = load_config(None)
    q = {r: np.asarray(cfg.robots[r].initial_q_rad) for r in ("r1", "r2")}
    c = group.closest(q)
    assert c.distance_m > 0.3, c
    assert c.links[0].startswith("r1 ") and c.links[1].startswith("r2 "), c


def test_an_arm_reaching_into_the_other_is_measured_in_contact(group: GroupGeometry) -> None:
    cfg = load_config(None)
    q = {"r1": np.asarray(INTO_R2), "r2": np.asarray(cfg.robots["r2"].initial_q_rad)}
    c = group.closest(q)
    assert c.distance_m < MIN_CLEARANCE_M, c


def test_a_task_that_swings_one_arm_into_the_other_is_refused_at_load(tmp_path: Path) -> None:
    task = tmp_path / "swing.yaml"
    task.write_text(SWING.format(q=INTO_R2))
    done = run_cli("--set", f"session.runs_dir={tmp_path / 'runs'}", "check", str(task))
    assert done.returncode == 2, done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    line = lines[0]
    assert (
        "segments[0] (reach over) at t=" in line
        and " (at least 3 cm apart)" in line
        and "come " in line
    ), line
    assert "r1 lbr_iiwa_link" in line and "r2 " in line, line
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())


def test_the_same_swing_kept_on_its_own_side_passes(tmp_path: Path) -> None:
    task = tmp_path / "swing.yaml"
    task.write_text(SWING.format(q=[0.3, 0.8, 0.0, -1.0, 0.0, 0.8, 0.0]))
    done = run_cli("--set", f"session.runs_dir={tmp_path / 'runs'}", "check", str(task))
    assert done.returncode == 0, done.stdout + done.stderr


def test_a_samples_time_is_where_the_quintic_profile_reaches_it() -> None:
    assert _time_at(0.5, 4.0) == pytest.approx(2.0, abs=1e-6)  # the profile's middle
    assert _time_at(1.0, 4.0) == pytest.approx(4.0, abs=1e-3)  # (flat at its end)
    s = 0.25**3 * (10 - 15 * 0.25 + 6 * 0.25**2)
    assert _time_at(s, 4.0) == pytest.approx(1.0, abs=1e-6)

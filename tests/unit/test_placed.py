"""``placed`` from the plant's truth: a carried object let go, upright on the
table, moved from pick to place as the task's carries command (the turns
about the hands' midpoint as the grippers took it, then the moves)."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import pytest

from redistro.config.loader import load_config
from redistro.config.task import load_task
from redistro.errors import ConfigError
from redistro.session.placed import placed

ROOT = Path(__file__).parents[2]


def _plant(x: float, y: float, yaw: float, **end: Any) -> dict[str, Any]:
    start = {"xyz_m": [0.503, -0.002, 0.13], "yaw_deg": 2.0, "tilt_deg": 0.0, "held_by": []}
    took = [{"robot": r, "took": "bar", "at_xyz_m": [0.5, s * 0.15, 0.165]} for r, s in
            (("r1", 1), ("r2", -1))]  # fmt: skip
    final = {"xyz_m": [x, y, 0.13], "yaw_deg": yaw, "tilt_deg": 0.0, "held_by": []}
    final.update(end)
    return {"objects_start": {"bar": start}, "objects": {"bar": final}, "grippers": took}


def test_a_carried_bar_is_placed_where_the_carries_put_it() -> None:
    cfg = load_config(ROOT / "config/dual_arm.yaml")
    task = load_task(ROOT / "tasks/dual_carry_short.yaml", cfg)
    # 30 degrees about the hands' midpoint (0.5, 0), then 0.2 m along y
    a = math.radians(30.0)
    x = 0.5 + math.cos(a) * 0.003 + math.sin(a) * 0.002
    y = 0.2 + math.sin(a) * 0.003 - math.cos(a) * 0.002
    got = placed(task, _plant(x, y, 32.0))
    assert got["placed"] is True and got["object_pose_error_m"] < 1e-6, got
    assert got["object_pose_error_rad"] < 1e-9, got
    near = placed(task, _plant(x + 0.0015, y, 32.4))
    assert near["placed"] is True and abs(near["object_pose_error_m"] - 0.0015) < 1e-6, near
    for bad in (
        _plant(x + 0.0025, y, 32.0),  # 2.5 mm off
        _plant(x, y, 32.8),  # 0.8 degrees: 0.014 rad
        _plant(x, y, 32.0, held_by=["r1"]),  # not let go
        _plant(x, y, 32.0, tilt_deg=5.0),  # not upright
        _plant(x, y, 32.0, xyz_m=[x, y, 0.14]),  # not on the table
    ):
        assert placed(task, bad)["placed"] is False, bad["objects"]
    # a task that carries nothing, or a plant without the objects: nothing said
    assert placed(load_task(ROOT / "tasks/grasp_lift.yaml", cfg), _plant(x, y, 32.0)) == {}
    bare = copy.deepcopy(_plant(x, y, 32.0))
    del bare["objects_start"]
    assert placed(task, bare) == {}


def test_bench_dual_draws_each_trials_object_truth_and_reads_its_verdict() -> None:
    from redistro.bench import dual

    cfg = load_config(ROOT / "config/dual_arm.yaml")
    task = load_task(ROOT / "tasks/dual_carry_short.yaml", cfg)
    assert dual.carried_object(task) == "bar"
    seen = set()
    for seed in range(50):
        t = dual.trial_config(cfg, "bar", 0.005, 3.0, seed).plant.objects["bar"]
        assert math.hypot(*t.offset_xy_m) <= 0.005 + 1e-9 and abs(t.yaw_deg) <= 3.0
        assert dual.trial_config(cfg, "bar", 0.005, 3.0, seed).plant.objects["bar"] == t
        seen.add(t.offset_xy_m[0])
    assert len(seen) == 50  # (a fresh draw per seed)
    # the block's truth untouched
    assert (
        dual.trial_config(cfg, "bar", 0.005, 3.0, 1).plant.objects["block"]
        == (cfg.plant.objects["block"])
    )
    summary = {
        "result": "ok", "reason": "", "placed": True, "object_pose_error_m": 0.0012,
        "object_pose_error_rad": 0.004, "clearance": {"arms_min_m": 0.21},
        "segments": [
            {"name": "grasp"},
            {"name": "lift", "squeeze_rms_error_n": 1.1, "squeeze_peak_n": 12.0},
            {"name": "carry", "squeeze_rms_error_n": 0.4, "squeeze_peak_n": 14.5},
        ],
    }  # fmt: skip
    truth = cfg.plant.objects["bar"]
    row = dual.trial_row(3, 7, truth, 0, summary)
    assert row["placed"] is True and row["squeeze_rms_error_n"] == 1.1
    assert row["squeeze_peak_n"] == 14.5 and row["min_arm_distance_m"] == 0.21
    assert row["offset_xy_mm"] == [3.0, -2.0] and row["yaw_deg"] == 2.0
    grasp = load_task(ROOT / "tasks/grasp_lift.yaml", cfg)
    with pytest.raises(ConfigError, match="carries one object"):
        dual.carried_object(grasp)

"""ESC pieces that are pure: zero offsets from home edges, the safety checks,
the segments a task gives, and task-file validation."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from redistro.config import load_config
from redistro.config.hardware import load_hardware
from redistro.config.task import load_task
from redistro.errors import ConfigError
from redistro.esc.calibration import zero_offsets
from redistro.esc.plan import esc_segments, task_seconds
from redistro.esc.sender import Violation, check

ROOT = Path(__file__).resolve().parents[2]
HALF, HYST = 0.05, 0.005  # half window, half hysteresis


def _edges(centre: float) -> tuple[list[float], list[float]]:
    """The four edges a sweep down then up meets (switch on inside the window)."""
    rising = [centre + HALF - HYST, centre - HALF + HYST]
    falling = [centre - HALF - HYST, centre + HALF + HYST]
    return rising, falling


def test_zero_offsets_cancel_the_hysteresis() -> None:
    home = np.array([0.5, -1.2])
    true_offset = np.array([0.031, -0.022])
    r0, f0 = _edges(home[0] + true_offset[0])
    r1, f1 = _edges(home[1] + true_offset[1])
    offset, found = zero_offsets([r0, r1], [f0, f1], home, np.full(2, 2 * HALF))
    assert found.all()
    assert np.allclose(offset, true_offset, atol=1e-12)


def test_zero_offsets_from_one_pair_and_none() -> None:
    home = np.zeros(3)
    rising, falling = _edges(0.01)
    offset, found = zero_offsets(
        [[rising[1]], [], [rising[0], rising[0] + 1e-4]],  # one rising edge only, ...
        [falling, falling, []],
        home,
        np.full(3, 2 * HALF),
    )
    assert found.tolist() == [True, True, False]  # the last: two edges of one side
    assert offset[:2] == pytest.approx([0.01, 0.01])


def _ok() -> dict[str, np.ndarray]:
    z = np.zeros(7)
    return {"q": z, "qd": z, "tau": z, "wrench": np.zeros(6), "tau_cmd": z}


def _check(**kw: np.ndarray) -> None:
    args = {**_ok(), **kw}
    recovery = float(args.pop("recovery_qd", 0.0))
    check(
        **args,
        recovery_qd=recovery,
        qd_max=np.ones(7),
        tau_max=np.full(7, 10.0),
        force_max=50.0,
        moment_max=5.0,
        q_lo=np.full(7, -2.0),
        q_hi=np.full(7, 2.0),
        stop_k=np.full(7, 0.1),  # 1 / (2 * 5 rad/s^2)
    )


def test_safety_check_passes_within_limits() -> None:
    _check(qd=np.full(7, 0.99), tau_cmd=np.full(7, -9.9))


@pytest.mark.parametrize(
    ("kw", "quantity", "joint"),
    [
        ({"qd": np.array([0, 0, 1.5, 0, 0, 0, 0.0])}, "velocity", 2),
        ({"qd": np.array([0, 0, 0, 0, 0, 0, np.nan])}, "measured velocity not finite", 6),
        ({"tau": np.array([0, 11.0, 0, 0, 0, 0, 0])}, "measured torque", 1),
        ({"wrench": np.array([40.0, 40.0, 0, 0, 0, 0])}, "force", -1),
        ({"wrench": np.array([0, 0, 0, 0, 0, np.inf])}, "wrench not finite", -1),
        ({"tau_cmd": np.array([np.nan, 0, 0, 0, 0, 0, 0])}, "commanded torque not finite", 0),
        ({"tau_cmd": np.array([0, 0, 0, 0, -12.0, 0, 0])}, "commanded torque", 4),
        ({"q": np.array([0, 0, 0, 2.01, 0, 0, 0])}, "position", 3),
        ({"q": np.array([0, -2.2, 0, 0, 0, 0, 0])}, "position", 1),
        # 1.95 rad moving at 0.9 rad/s toward 2.0: it needs 0.081 rad to stop
        (
            {"q": np.array([0, 0, 0, 0, 0, 1.95, 0]), "qd": np.array([0, 0, 0, 0, 0, 0.9, 0])},
            "stopping position",
            5,
        ),
        (
            {"q": np.array([-1.95, 0, 0, 0, 0, 0, 0]), "qd": np.array([-0.9, 0, 0, 0, 0, 0, 0])},
            "stopping position",
            0,
        ),
    ],
)
def test_safety_check_names_what_tripped(kw: dict, quantity: str, joint: int) -> None:
    with pytest.raises(Violation) as exc:
        _check(**kw)
    assert exc.value.quantity == quantity and exc.value.joint == joint


def test_a_joint_near_its_limit_moving_away_or_slowly_is_fine() -> None:
    # 1.95 rad moving away, or toward the limit at 0.3 rad/s (stops in 0.009 rad)
    _check(q=np.full(7, 1.95), qd=np.full(7, -0.9))
    _check(q=np.full(7, 1.95), qd=np.full(7, 0.3))


def test_a_joint_left_outside_its_limits_may_move_back_slowly_and_only_back() -> None:
    """A joint resting past its limit less the margin (or past the limit):
    at rest or moving back toward the range below the recovery speed it is
    let go; moving further out, or back too fast, it is refused; with no
    recovery speed it is refused at once."""
    out = np.array([0, 0, 0, 2.03, 0, 0, 0.0])  # past 2.0 (the limit less the margin)
    low = -out
    for q, qd in ((out, 0.0), (out, -0.3), (out, 0.01), (low, 0.3), (low, -0.01)):
        _check(q=q, qd=np.array([0, 0, 0, qd, 0, 0, 0.0]), recovery_qd=np.float64(0.5))
    for q, qd in ((out, 0.05), (out, -0.6), (low, -0.05), (low, 0.6)):
        with pytest.raises(Violation) as exc:
            _check(q=q, qd=np.array([0, 0, 0, qd, 0, 0, 0.0]), recovery_qd=np.float64(0.5))
        assert exc.value.quantity == "position" and exc.value.joint == 3
    with pytest.raises(Violation, match="position"):
        _check(q=out)


def test_a_nan_command_is_caught_before_any_comparison() -> None:
    # NaN passes every ">" test: the finiteness check must come first
    with pytest.raises(Violation, match="not finite"):
        _check(tau_cmd=np.full(7, np.nan))


def test_self_calibration_segments_follow_the_task() -> None:
    cfg = load_config(ROOT / "config/redistro.yaml")
    hw = load_hardware(cfg, ROOT / "config")
    task = load_task(ROOT / "tasks/self_calibration.yaml", cfg)
    segs = esc_segments(task, "r1", hw["r1"])
    assert [s["name"] for s in segs] == ["clockwise", "counter_clockwise", "final_positioning"]
    r = math.radians(task.calibration.range_deg)
    assert segs[0]["delta_rad"] == pytest.approx(-r) and segs[1]["delta_rad"] == pytest.approx(r)
    assert segs[2]["goal_rad"] == list(hw["r1"].sensors.home_angle_rad)
    assert task_seconds(task) == pytest.approx(30.5)


BAD_TASKS = [
    ("kind: dance\n", "kind: expected one of"),
    ("robots: [r1, r9]\n", "robots[1]: no robot named 'r9'"),
    ("robots: [r1, r1]\n", "robots[1]: robot 'r1' listed twice"),
    ("calibration: {segment_s: [10, 0, 10]}\n", "calibration.segment_s[1]: expected a number > 0"),
    ("calibration: {range_deg: 40}\n", "calibration.range_deg: expected a number >= 5.0"),
    ("calibration: {speed: 3}\n", "calibration.speed: unknown key"),
    ("calibration: {final_q_rad: {r3: [0, 0, 0, 0, 0, 0, 0]}}\n", "'r3' is not in robots"),
    ("segments: [{name: a, duration_s: 1}]\n", "segments: not used by a self_calibration task"),
]


@pytest.mark.parametrize(("extra", "expect"), BAD_TASKS)
def test_bad_task_files_name_the_field(tmp_path: Path, extra: str, expect: str) -> None:
    cfg = load_config(ROOT / "config/redistro.yaml")
    base = {"task": "t", "kind": "self_calibration", "robots": "[r1, r2]"}
    lines = []
    for key, value in base.items():
        if not extra.startswith(f"{key}:"):
            lines.append(f"{key}: {value}")
    path = tmp_path / "task.yaml"
    path.write_text("\n".join(lines) + "\n" + extra)
    with pytest.raises(ConfigError) as exc:
        load_task(path, cfg)
    assert str(path) in str(exc.value) and expect in str(exc.value), str(exc.value)


def test_a_joint_move_needs_a_goal_per_robot(tmp_path: Path) -> None:
    cfg = load_config(ROOT / "config/redistro.yaml")
    path = tmp_path / "move.yaml"
    path.write_text(
        "task: m\nkind: joint_move\nrobots: [r1, r2]\n"
        "segments:\n  - {name: a, duration_s: 2, q_rad: {r1: [0, 0, 0, 0, 0, 0, 0]}}\n"
    )
    with pytest.raises(ConfigError, match=r"segments\[0\].q_rad: no goal for robot 'r2'"):
        load_task(path, cfg)

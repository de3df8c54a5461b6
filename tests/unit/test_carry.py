"""The carry's per-cycle reference (ssc/carry.py, plain floats) against its
definition (ssc/plan.py's carried(), numpy): each hand on the object's arc,
in along the line by the squeeze's compression, up by the weight's share."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from redistro.config.loader import load_config
from redistro.config.task import load_task
from redistro.ssc.carry import GRAVITY, CarryRun
from redistro.ssc.plan import carried, segment_plans

ROOT = Path(__file__).parents[2]


class _Kin:
    def __init__(self, p: list[float], R: np.ndarray) -> None:
        self.p, self.R = np.array(p), R


class _Law:
    def __init__(self) -> None:
        self.ref = np.zeros((), [("start_p", "f8", 3), ("goal_p", "f8", 3)])
        self.applied = np.zeros(6)
        self.tcp_p = np.zeros(3)


def test_the_reference_is_the_objects_arc_plus_the_squeeze_and_the_weight() -> None:
    cfg = load_config(ROOT / "config/dual_arm.yaml")
    plan = next(p for p in segment_plans(load_task(ROOT / "tasks/dual_carry.yaml", cfg), cfg)
                if p.name == "carry")  # fmt: skip
    assert plan.carry is not None
    rng = np.random.default_rng(3)
    down = np.diag([1.0, -1.0, -1.0])
    kins = [_Kin([0.5, 0.15, 0.165], down), _Kin([0.503, -0.148, 0.166], down)]
    run = CarryRun(plan, kins, 300.0, 280.0)
    assert run.up == [plan.carry_mass_kg * GRAVITY / 560] * 2  # (half the weight on 280 N/m)
    law, wg = _Law(), np.zeros(6)
    for _ in range(200):
        i, t = int(rng.integers(2)), float(rng.uniform(-0.5, plan.move_s + 0.5))
        run.inward[i] = float(rng.uniform(0, 0.05))
        run.before(i, law, t, wg)
        s = min(max(t / plan.move_s, 0.0), 1.0)
        b = 10 * s**3 - 15 * s**4 + 6 * s**5
        arcs, _ = carried(plan.carry, run.p0, [np.eye(3)] * 2, b)
        chord = run.p0[i] + b * (run.goal_p[i] - run.p0[i])
        a = math.radians(plan.carry.turn_deg) * b
        u0 = run.u0[i]
        u = np.array([math.cos(a) * u0[0] - math.sin(a) * u0[1],
                      math.sin(a) * u0[0] + math.cos(a) * u0[1], 0.0])  # fmt: skip
        shift = arcs[i] - chord + run.inward[i] * u + [0, 0, run.up[i]]
        assert np.allclose(law.ref["start_p"], run.p0[i] + shift, atol=1e-12)
        assert np.allclose(law.ref["goal_p"], run.goal_p[i] + shift, atol=1e-12)
        assert np.allclose(wg[:3], plan.carry.squeeze_n * u, atol=1e-12)
        # the squeeze measured along the same line trims the compression
        law.applied[:3] = rng.normal(0, 10, 3)
        law.tcp_p[:] = arcs[i] + rng.normal(0, 0.01, 3)
        before, up = run.inward[i], run.up[i]
        run.after(i, law, 0.005)
        # the height error on the object's path trims the weight's share
        assert math.isclose(run.up[i], up + 2.0 * (arcs[i][2] - law.tcp_p[2]) * 0.005)
        f = float(law.applied[:3] @ u)
        assert math.isclose(run.measured[i], f, abs_tol=1e-12)
        want = min(max(before + 0.015 * (plan.carry.squeeze_n - f) * 0.005, 0.0), 0.1)
        assert math.isclose(run.inward[i], want, abs_tol=1e-15)


def test_a_held_objects_hole_goes_with_the_hand_that_grasped_it(tmp_path: Path) -> None:
    """r1 grasps the block (a hole in it) and presents it turned and lifted;
    r2's goal over ``block.hole`` is where that move takes the hole, not
    where it was drawn; a joint move of r1 leaves it unknown (refused)."""
    import pytest

    from redistro.control.cartesian import rotvec_to_matrix
    from redistro.errors import ConfigError

    cfg = load_config(
        ROOT / "config/dual_arm.yaml",
        ["workcell.objects.block.hole_side_m=0.02", "workcell.objects.block.hole_depth_m=0.03",
         "workcell.objects.block.hole_at_xy_m=[0.005, 0]"],
    )  # fmt: skip
    down, turned = [0, math.pi, 0], [0.3, math.pi - 0.2, 0.1]
    present = [0.45, 0.1, 0.35]
    task = tmp_path / "present.yaml"
    task.write_text(
        "task: present\nkind: strategy\nrobots: [r1, r2]\nsegments:\n"
        f"  - {{name: grasp, robot: r1, skill: grasp, scheme: position, duration_s: 2,\n"
        f"     goal: {{relative_to: block, pos_xyz_rot_xyz: [0, 0, 0.005, {down[0]}, "
        f"{down[1]}, {down[2]}]}}}}\n"
        "  - name: present\n    duration_s: 3\n    moves:\n"
        f"      r1: {{scheme: position, goal: {{pos_xyz_rot_xyz: {present + turned}}}}}\n"
        f"      r2: {{scheme: position, goal: {{relative_to: block.hole, "
        f"pos_xyz_rot_xyz: [0, 0, 0.05, {down[0]}, {down[1]}, {down[2]}]}}}}\n"
    )
    plans = segment_plans(load_task(task, cfg), cfg)
    grasp_p = plans[0].moves[0].pose[:3]
    block = cfg.workcell.objects["block"]
    drawn_hole = grasp_p + np.array([0.005, 0.0, -0.005])  # (the block's yaw is 0)
    R0, R1 = rotvec_to_matrix(np.array(down, float)), rotvec_to_matrix(np.array(turned, float))
    hole = np.array(present) + R1 @ (R0.T @ (drawn_hole - grasp_p))
    r2 = plans[1].move_of("r2")
    assert r2 is not None and block.hole_side_m == 0.02
    assert np.allclose(r2.pose[:3], hole + np.array([0, 0, 0.05]), atol=1e-9), (r2.pose[:3], hole)
    assert not np.allclose(hole, drawn_hole, atol=0.01)  # (it did move)
    text = (
        task.read_text()
        .replace(
            f"{{pos_xyz_rot_xyz: {present + turned}}}", "{q_rad: [0, 0.3, 0, -1.6, 0, 1.9, 0.8]}"
        )
        .replace("r1: {scheme: position", "r1: {scheme: joint")
    )
    task.write_text(text)
    with pytest.raises(ConfigError, match=r"r2.goal.relative_to: where block.hole is"):
        segment_plans(load_task(task, cfg), cfg)


def test_an_insertion_into_a_held_objects_hole_takes_that_hole_and_the_held_peg(
    tmp_path: Path,
) -> None:
    """r1 grasps the block, r2 the peg (an object, no peg on its flange);
    r2's search relative to ``block.hole`` works at the block's hole where
    r1's move put it, with the block's depth and side, and its mouth is the
    TCP's height with the peg's bottom there (the peg's height and the
    grasp's offset above its top under the TCP). Without a held object, a
    force move at the fixture keeps the fixture's mouth."""
    cfg = load_config(ROOT / "tests/data/dual_peg_cell.yaml")
    down = "0, 3.14159265, 0"
    task = tmp_path / "insert.yaml"
    task.write_text(
        "task: insert\nkind: strategy\nrobots: [r1, r2]\nsegments:\n"
        "  - name: grasp\n    duration_s: 2\n    moves:\n"
        f"      r1: {{skill: grasp, scheme: position, goal: {{relative_to: block, "
        f"pos_xyz_rot_xyz: [0, 0.07, 0.005, {down}]}}}}\n"
        f"      r2: {{skill: grasp, scheme: position, goal: {{relative_to: peg, "
        f"pos_xyz_rot_xyz: [0, 0, 0.004, {down}]}}}}\n"
        f"  - {{name: present, robot: r1, scheme: position, duration_s: 3,\n"
        f"     goal: {{pos_xyz_rot_xyz: [0.55, 0.22, 0.3, {down}]}}}}\n"
        f"  - {{name: insert, robot: r2, scheme: force, duration_s: 5,\n"
        f"     goal: {{relative_to: block.hole, pos_xyz_rot_xyz: [0, 0, 0.12, {down}],\n"
        "       force_xyz_torque_xyz: [0, 0, -8, 0, 0, 0], selection_vector: [0, 0, 1, 0, 0, 0]},\n"
        "     search: {pattern: spiral, force_n: 4}}\n"
    )
    plans = segment_plans(load_task(task, cfg), cfg)
    block, peg = cfg.workcell.objects["block"], cfg.workcell.objects["peg"]
    mouth = np.array([0.55, 0.22 - 0.07 + block.hole_at_xy_m[1], 0.3 - 0.005])
    mv = plans[2].moves[0]
    assert np.allclose([*mv.mouth_xy_m], mouth[:2], atol=1e-9), mv.mouth_xy_m
    assert abs(mv.mouth_z_m - (mouth[2] + peg.size_xyz_m[2] + 0.004)) < 1e-9, mv.mouth_z_m
    assert (mv.hole_depth_m, mv.hole_half_m) == (block.hole_depth_m, block.hole_side_m / 2)
    # r2 follows r1's hand: from r1's pose goal and the mouth where it puts it
    assert mv.follows == "r1" and mv.holder_pose is not None and mv.follow_point is not None
    assert np.allclose(mv.holder_pose, plans[1].moves[0].pose)
    assert np.allclose(mv.follow_point, mouth)
    fixture = load_config(ROOT / "config/redistro.yaml")
    tmp_task = tmp_path / "fixture.yaml"
    tmp_task.write_text(
        "task: f\nkind: strategy\nrobots: [r1, r2]\nsegments:\n"
        f"  - {{name: insert, robot: r2, scheme: force, duration_s: 5,\n"
        f"     goal: {{relative_to: hole, pos_xyz_rot_xyz: [0, 0, 0.01, {down}],\n"
        "       force_xyz_torque_xyz: [0, 0, -8, 0, 0, 0], selection_vector: [0, 0, 1, 0, 0, 0]}}\n"
    )
    mv = segment_plans(load_task(tmp_task, fixture), fixture)[0].moves[0]
    h = fixture.workcell.hole
    assert (*mv.mouth_xy_m, mv.mouth_z_m) == tuple(h.xyz_m) and mv.hole_depth_m == h.depth_m
    assert not mv.follows  # (the fixture stands still)

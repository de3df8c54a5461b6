"""The arms kept apart: the load-time check of every segment's motion
(redistro/ssc/clearance.py), on the real URDF through Pinocchio and coal."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from redistro.config.loader import load_config
from redistro.config.model import MIN_CLEARANCE_M, TRIP_M
from redistro.faults import hooks
from redistro.ssc.clearance import (
    GJK_GAP_M,
    ClearanceWatch,
    GroupGeometry,
    _time_at,
    mesh_vertices,
)
from tests.helpers import run_cli

# r1 turned to face r2 (its base 0.9 m away along -y) and reaching out
INTO_R2 = [float(v) for v in hooks.INTO_R2]  # (the arms-collide fault's posture)

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


def test_the_arms_at_their_initial_postures_are_clear_of_everything(group: GroupGeometry) -> None:
    cfg = load_config(None)
    q = {r: np.asarray(cfg.robots[r].initial_q_rad) for r in ("r1", "r2")}
    c = group.closest(q)  # (the nearest: a base and the table's edge, 13 cm)
    assert c.distance_m > 0.1, c


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


# each arm turned toward the other, reaching over: either alone keeps 13 cm
# from the other at rest; together they overlap
TOWARD = {
    "r1": [-1.5708, 0.7, 0.0, -0.3, 0.0, 0.5, 0.0],
    "r2": [1.5708, 0.7, 0.0, -0.3, 0.0, 0.5, 0.0],
}


def _moves_task(robots: list[str]) -> str:
    lines = [
        "task: meet", "kind: strategy", "robots: [r1, r2]", "segments:",
        "  - name: meet", "    duration_s: 6", "    moves:",
    ]  # fmt: skip
    for r in robots:
        lines += [f"      {r}:", "        scheme: joint", f"        goal: {{q_rad: {TOWARD[r]}}}"]
    return "\n".join(lines) + "\n"


def test_two_arms_moving_in_one_segment_are_checked_together(tmp_path: Path) -> None:
    """A segment's moves share one clock, and the load check samples them
    so: each arm's move alone keeps clear, both at once are refused."""
    from redistro.config.task import load_task
    from redistro.ssc.clearance import clearance_problems

    cfg = load_config(None)
    start = {r: list(cfg.robots[r].initial_q_rad) for r in ("r1", "r2")}
    for robots, refused in ((["r1"], False), (["r2"], False), (["r1", "r2"], True)):
        path = tmp_path / f"meet-{len(robots)}-{robots[0]}.yaml"
        path.write_text(_moves_task(robots))
        problems = clearance_problems(cfg, load_task(path, cfg), start)
        assert bool(problems) == refused, (robots, problems)
    line = problems[0]
    assert "segments[0] (meet) at t=" in line and "r1 " in line and "r2 " in line, line


def test_a_samples_time_is_where_the_quintic_profile_reaches_it() -> None:
    assert _time_at(0.5, 4.0) == pytest.approx(2.0, abs=1e-6)  # the profile's middle
    assert _time_at(1.0, 4.0) == pytest.approx(4.0, abs=1e-3)  # (flat at its end)
    s = 0.25**3 * (10 - 15 * 0.25 + 6 * 0.25**2)
    assert _time_at(s, 4.0) == pytest.approx(1.0, abs=1e-6)


@pytest.fixture(scope="module")
def watch_cfg() -> Any:
    return load_config(None)


def _watch(cfg: Any, period_s: float = 0.005) -> ClearanceWatch:
    return ClearanceWatch(cfg, ["r1", "r2"], period_s)


def test_the_watch_measures_every_pair_first_then_only_those_due(watch_cfg: Any) -> None:
    w = _watch(watch_cfg)
    q = [np.asarray(watch_cfg.robots[r].initial_q_rad, dtype=np.float64) for r in ("r1", "r2")]
    assert w.check(q, 0.0) is None
    assert w.measured == len(w.v)  # all of them, in the first cycle
    assert w.closest > 0.1
    for k in range(1, 200):  # the arms at rest: 1 s at 200 Hz
        assert w.check(q, k * 0.005) is None
    # a pair is measured again only when it could have closed in by then
    assert w.measured < 200 * len(w.v) // 10, w.measured


def test_each_pairs_speed_bound_holds_at_the_joint_limits(
    watch_cfg: Any, group: GroupGeometry
) -> None:
    """No pair of links closes faster than the watch's bound when every
    joint moves within its speed limit (random postures and directions)."""
    rng = np.random.default_rng(7)
    w = _watch(watch_cfg)
    qd_max = np.asarray(watch_cfg.esc.safety.qd_max_rad_s)
    pin = w._pin
    g = w.group
    dt = 1e-3
    for _ in range(20):
        q = np.concatenate([rng.uniform(-1.5, 1.5, 7) for _ in range(2)])
        qd = rng.uniform(-1, 1, 14) * np.tile(qd_max, 2)
        pin.computeDistances(g.model, g.data, g.geom, g.gdata, q)
        before = [r.min_distance for r in g.gdata.distanceResults]
        pin.computeDistances(g.model, g.data, g.geom, g.gdata, q + qd * dt)
        after = [r.min_distance for r in g.gdata.distanceResults]
        for k, (a, b) in enumerate(zip(before, after, strict=True)):
            if a > 0 and b > 0:  # (apart: the distance is a distance)
                assert (a - b) / dt <= w.v[k] + 2 * GJK_GAP_M / dt, (k, a, b, w.v[k])


def test_an_arm_swinging_into_the_other_trips_the_watch_while_they_are_apart(
    watch_cfg: Any, group: GroupGeometry
) -> None:
    """r1 steered toward INTO_R2 at 0.4 rad/s, sampled at 200 Hz: the watch
    trips before any sample is closer than TRIP_M, and at the trip the arms
    are still apart (the geometry's own distance, every pair at once)."""
    w = _watch(watch_cfg)
    q1 = np.asarray(watch_cfg.robots["r1"].initial_q_rad, dtype=np.float64).copy()
    q2 = np.asarray(watch_cfg.robots["r2"].initial_q_rad, dtype=np.float64)
    into, step = np.asarray(INTO_R2), hooks.COLLIDE_RAD_S * 0.005
    hit = None
    na = w.group.n_arms
    for k in range(2000):
        q1 += np.clip(into - q1, -step, step)
        hit = w.check([q1, q2], k * 0.005)
        # the nearest of each kind, kept as pairs come in: the least last measure
        assert (w.arms_m, w.cell_m) == (min(w.d[:na]), min(w.d[na:])), k
        if hit is not None:
            break
        assert group.closest({"r1": q1, "r2": q2}).distance_m >= TRIP_M, k
    assert hit is not None, "the watch never tripped"
    truth = group.closest({"r1": q1, "r2": q2}).distance_m
    assert truth >= TRIP_M and hit.distance_m == pytest.approx(truth, abs=1e-4)
    assert hit.links[0].startswith("r1 ") and hit.links[1].startswith("r2 "), hit
    # and back out: the nearest pairs move apart, and are looked for again
    home = np.asarray(watch_cfg.robots["r1"].initial_q_rad, dtype=np.float64)
    for j in range(k + 1, k + 400):
        q1 += np.clip(home - q1, -step, step)
        w.check([q1, q2], j * 0.005)
        assert (w.arms_m, w.cell_m) == (min(w.d[:na]), min(w.d[na:])), j


def test_a_stalled_plant_clock_is_no_error_and_the_watch_still_trips(watch_cfg: Any) -> None:
    """The SSC's task time comes from the plant's steps: a slow plant gives
    two cycles the same time. A pair measured again at the same time has no
    closing speed to read; the watch goes on, and trips as before."""
    w = _watch(watch_cfg)
    q1 = np.asarray(watch_cfg.robots["r1"].initial_q_rad, dtype=np.float64).copy()
    q2 = np.asarray(watch_cfg.robots["r2"].initial_q_rad, dtype=np.float64)
    into, step = np.asarray(INTO_R2), hooks.COLLIDE_RAD_S * 0.005
    hit = None
    for k in range(4000):
        if k % 2:  # every other cycle: the plant's clock stood still
            q1 += np.clip(into - q1, -step, step)
        hit = w.check([q1, q2], (k // 2) * 0.005)
        if hit is not None:
            break
    assert hit is not None, "the watch never tripped"
    assert hit.distance_m >= TRIP_M, hit


def test_the_work_cell_is_in_the_geometry_for_every_link_but_the_tools(
    group: GroupGeometry,
) -> None:
    objs = group.geom.geometryObjects
    pairs = {(objs[p.first].name, objs[p.second].name) for p in group.geom.collisionPairs}
    links = [go.name for go in objs if not go.name.startswith("workcell ")]
    for link in links:
        for box in ("workcell table", "workcell fixture"):
            # (a task puts the tool into the fixture, 1 cm over the table)
            assert ((link, box) in pairs) == (not link.endswith(" tool")), (link, box)


def test_a_task_that_reaches_down_into_the_table_is_refused_at_load(tmp_path: Path) -> None:
    task = tmp_path / "down.yaml"
    task.write_text(
        SWING.replace("robot: r1", "robot: r2").format(q=[0.0, 1.8, 0.0, -0.3, 0.0, 0.3, 0.0])
    )
    done = run_cli("--set", f"session.runs_dir={tmp_path / 'runs'}", "check", str(task))
    assert done.returncode == 2, done.stdout + done.stderr
    line = done.stderr.strip()
    assert "\n" not in line and "Traceback" not in line, line
    assert "segments[0] (reach over)" in line and "and workcell table " in line, line


def test_a_binary_stl_read_here_gives_the_vertices_coal_reads() -> None:
    """The meshes' vertices come from the STL files read with numpy; coal's
    own loader (assimp) is the reference: the same distinct vertices."""
    import coal
    import pybullet_data

    meshes = Path(pybullet_data.getDataPath()) / "kuka_iiwa" / "meshes"
    for k in range(8):
        path = str(meshes / f"link_{k}.stl")
        ours = mesh_vertices(path)
        ref = np.unique(np.asarray(coal.MeshLoader().load(path, np.ones(3)).vertices()), axis=0)
        assert ours.shape == ref.shape, path
        np.testing.assert_array_equal(np.unique(ours, axis=0), ref)
    scaled = mesh_vertices(str(meshes / "link_3.stl"), (2.0, 1.0, 0.5))
    np.testing.assert_allclose(scaled, mesh_vertices(str(meshes / "link_3.stl")) * [2, 1, 0.5])


def test_a_carry_moves_the_hands_as_one_rigid_object() -> None:
    """carried(): the point between the hands moved by the carry's move,
    the hands turned about it by its turn, their distance kept, at every
    fraction of the way."""
    import math

    from redistro.config.task import Carry
    from redistro.ssc.plan import carried

    carry = Carry(object="bar", move_xyz_m=[0.0, 0.2, 0.1], turn_deg=30.0)
    p = [np.array([0.5, 0.15, 0.2]), np.array([0.52, -0.15, 0.2])]
    R = [np.eye(3), np.eye(3)]
    for s in (0.0, 0.3, 1.0):
        q, Rq = carried(carry, p, R, s)
        assert np.isclose(np.linalg.norm(q[1] - q[0]), np.linalg.norm(p[1] - p[0]))
        assert np.allclose((q[0] + q[1]) / 2, (p[0] + p[1]) / 2 + s * np.array([0, 0.2, 0.1]))
        a = math.atan2(Rq[0][1, 0], Rq[0][0, 0])
        assert math.isclose(a, math.radians(30.0 * s), abs_tol=1e-12)
        d0, d1 = p[1] - p[0], q[1] - q[0]
        turn = math.atan2(d1[1], d1[0]) - math.atan2(d0[1], d0[0])
        assert math.isclose(turn, math.radians(30.0 * s), abs_tol=1e-12)

"""The insertion's search (control.search) and the plant's hole truth (plant.truth)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from redistro.config import load_config
from redistro.config.task import Search
from redistro.control.search import Phase, SpiralSearch
from redistro.plant.truth import hole_pose

DT = 0.005
MOUTH = 0.15


def _run(
    s: SpiralSearch,
    z_of: object,
    contact_at: float = 0.5,
    seconds: float = 60.0,
    push_of: object = None,
) -> float:
    """Steps the search; z_of(search) the tip's height, push_of(search) the
    push felt (default: the search's own while in contact). Returns the time
    it stopped."""
    t = 0.0
    while t < seconds:
        z = z_of(s)  # type: ignore[operator]
        push = push_of(s) if push_of is not None else s.p.force_n * (t >= contact_at)  # type: ignore[operator]
        phase = s.step(t, DT, t >= contact_at, z, push)
        if phase in (Phase.IN_HOLE, Phase.NOT_FOUND):
            return t
        t += DT
    return t


def test_the_spiral_covers_the_plane_at_its_pitch_and_speed() -> None:
    p = Search(pattern="spiral", pitch_m=0.0004, speed_m_s=0.005, max_radius_m=0.004, timeout_s=60)
    s = SpiralSearch(p, MOUTH)
    pts = []

    def z_of(srch: SpiralSearch) -> float:
        if srch.phase == Phase.SEARCH:
            pts.append((srch.ox, srch.oy))
        return MOUTH

    end = _run(s, z_of)
    assert s.phase == Phase.NOT_FOUND and s.why == "hole not found within 4 mm"
    xy = np.array(pts)
    r = np.hypot(xy[:, 0], xy[:, 1])
    assert r.max() <= 0.004 + 1e-9
    # the path's speed: the path length over the search's time
    search_s = end - (0.5 + p.settle_s)
    assert s.path_m == pytest.approx(p.speed_m_s * search_s, rel=0.02)
    # every point of the disc is within half a pitch (and a step) of the path
    grid = np.mgrid[-0.0035:0.0035:31j, -0.0035:0.0035:31j].reshape(2, -1).T
    grid = grid[np.hypot(grid[:, 0], grid[:, 1]) < 0.0035]
    d = np.min(np.hypot(grid[:, None, 0] - xy[None, :, 0], grid[:, None, 1] - xy[None, :, 1]), 1)
    assert d.max() <= p.pitch_m / 2 + p.speed_m_s * DT + 1e-6


def test_a_drop_below_the_contact_height_is_the_hole() -> None:
    p = Search(pattern="spiral", drop_m=0.001)
    s = SpiralSearch(p, MOUTH)
    hole = (0.0012, -0.0008)

    def z_of(srch: SpiralSearch) -> float:
        near = math.hypot(srch.ox - hole[0], srch.oy - hole[1]) < 0.0003
        return MOUTH - 0.003 if srch.phase == Phase.SEARCH and near else MOUTH

    _run(s, z_of)
    assert s.phase == Phase.IN_HOLE
    assert math.hypot(s.ox - hole[0], s.oy - hole[1]) < 0.0003
    assert s.why == ""


def test_the_push_gone_as_the_tip_sinks_is_the_hole() -> None:
    """The peg starts to fall: the push is gone before the tip has fallen
    drop_m, and the search stops there; a push lost without the tip sinking
    (a bounce, a slip) is not the hole."""
    p = Search(pattern="spiral", drop_m=0.001, force_n=8.0, pitch_m=0.0004, speed_m_s=0.005)
    hole = (0.0012, -0.0008)

    def near(srch: SpiralSearch) -> bool:
        return srch.phase == Phase.SEARCH and (
            math.hypot(srch.ox - hole[0], srch.oy - hole[1]) < 0.0003
        )

    s = SpiralSearch(p, MOUTH)
    _run(
        s,
        lambda srch: MOUTH - 0.0006 if near(srch) else MOUTH,
        push_of=lambda srch: 0.0 if near(srch) else 8.0,
    )
    assert s.phase == Phase.IN_HOLE
    flick = SpiralSearch(p, MOUTH)
    _run(flick, lambda srch: MOUTH, push_of=lambda srch: 1.0 if near(srch) else 8.0, seconds=20.0)
    assert flick.phase == Phase.SEARCH  # still searching at the end of the run
    # a peg caught by one edge in the slot the walls make dips 0.3 mm and
    # loses its push for a moment: not the hole either
    edge = SpiralSearch(p, MOUTH)
    _run(
        edge,
        lambda srch: MOUTH - 0.0003 if near(srch) else MOUTH,
        push_of=lambda srch: 1.0 if near(srch) else 8.0,
        seconds=20.0,
    )
    assert edge.phase == Phase.SEARCH


def test_contact_below_the_mouth_is_already_in_the_hole() -> None:
    s = SpiralSearch(Search(pattern="spiral"), MOUTH)
    _run(s, lambda srch: MOUTH - 0.03)
    assert s.phase == Phase.IN_HOLE and s.path_m == 0.0


def test_the_search_times_out() -> None:
    p = Search(pattern="spiral", timeout_s=2.0, max_radius_m=0.02)
    s = SpiralSearch(p, MOUTH)
    _run(s, lambda srch: MOUTH)
    assert s.phase == Phase.NOT_FOUND and s.why.startswith("hole not found within 2 s of search")


def test_the_hole_truth_is_the_drawing_plus_its_offsets() -> None:
    base = load_config(None, [])
    same = hole_pose(base)
    assert same.xyz_m == tuple(base.workcell.hole.xyz_m) and same.yaw_deg == 0.0
    fixed = hole_pose(load_config(None, ["plant.hole.offset_xyz_m=[0.001, -0.002, 0]"]))
    assert fixed.offset_xyz_m == pytest.approx((0.001, -0.002, 0.0))
    draws = [
        hole_pose(
            load_config(
                None,
                [
                    "plant.hole.offset_radius_m=0.003",
                    "plant.hole.yaw_range_deg=2",
                    f"plant.hole.seed={seed}",
                ],
            )
        )
        for seed in range(200)
    ]
    lateral = np.array([d.lateral_m for d in draws])
    yaw = np.array([d.yaw_deg for d in draws])
    assert lateral.max() <= 0.003 and abs(yaw).max() <= 2.0
    # uniform over the disc: half the draws within r / sqrt(2)
    assert 0.4 < np.mean(lateral < 0.003 / math.sqrt(2)) < 0.6
    assert len({round(y, 9) for y in yaw}) == 200  # seeded, not constant
    again = hole_pose(
        load_config(
            None,
            ["plant.hole.offset_radius_m=0.003", "plant.hole.yaw_range_deg=2", "plant.hole.seed=7"],
        )
    )
    assert again == draws[7]
    # a rotation matrix for the fixture's boxes
    R = draws[3].rotation()
    assert np.allclose(R @ R.T, np.eye(3)) and math.degrees(
        math.atan2(R[1, 0], R[0, 0])
    ) == pytest.approx(draws[3].yaw_deg)


def test_a_slip_is_not_the_hole_and_the_search_goes_on() -> None:
    """The push gone for a moment and the tip a little lower (a slip): the
    search stops, but meeting the surface again within two drop_m of where it
    began, once settled, sends it on from where it was."""
    p = Search(pattern="spiral", drop_m=0.001, force_n=8.0, settle_s=0.3)
    s = SpiralSearch(p, MOUTH)
    t = 0.0
    while t < 2.0:
        s.step(t, DT, t >= 0.5, MOUTH, 8.0)
        t += DT
    assert s.phase == Phase.SEARCH
    theta = s.theta
    assert s.step(t, DT, True, MOUTH - 0.0006, 0.5) == Phase.IN_HOLE  # the slip
    t += DT
    # still touching right after: not yet taken for the surface (settling)
    assert s.step(t, DT, True, MOUTH - 0.0006, 8.0) == Phase.IN_HOLE
    while s.phase == Phase.IN_HOLE and t < 3.0:
        t += DT
        s.step(t, DT, True, MOUTH - 0.0006, 8.0)
    assert s.phase == Phase.SEARCH and s.false_drops == 1
    assert t - 2.0 == pytest.approx(p.settle_s, abs=2 * DT)
    for _ in range(10):
        t += DT
        s.step(t, DT, True, MOUTH - 0.0006, 8.0)
    assert s.phase == Phase.SEARCH and s.theta > theta
    # a true drop: no contact in the hole, far below; it stays in the hole
    s.step(t, DT, True, MOUTH - 0.003, 0.0)
    for _ in range(200):
        t += DT
        s.step(t, DT, False, MOUTH - 0.01, 0.0)
    assert s.phase == Phase.IN_HOLE and s.false_drops == 1

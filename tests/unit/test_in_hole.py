"""in_hole against poses made by hand: a peg standing at the bottom of a
turned block's hole, one beside the hole, one half way in."""

from __future__ import annotations

import math

from redistro.config.model import ObjectConfig
from redistro.plant.in_hole import in_hole

PEG = ObjectConfig(size_xyz_m=[0.02, 0.02, 0.1], xy_m=[0.0, 0.0])
BLOCK = ObjectConfig(
    size_xyz_m=[0.16, 0.08, 0.06], xy_m=[0.0, 0.0],
    hole_side_m=0.021, hole_depth_m=0.04, hole_at_xy_m=[0.04, 0.0],
)  # fmt: skip


def _yaw(deg: float) -> list[float]:
    a = math.radians(deg) / 2
    return [0.0, 0.0, math.sin(a), math.cos(a)]


def test_a_peg_at_the_bottom_of_a_turned_blocks_hole() -> None:
    yaw = 30.0
    c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    block = {"xyz_m": [0.5, 0.2, 0.3], "quat_xyzw": _yaw(yaw)}
    hx, hy = 0.5 + c * 0.04, 0.2 + s * 0.04  # the hole's axis, world
    for dz, depth, inside in ((0.0, 0.04, True), (0.02, 0.02, True)):
        peg = {"xyz_m": [hx, hy, 0.3 + 0.03 - 0.04 + dz + 0.05], "quat_xyzw": _yaw(-10.0)}
        got = in_hole(PEG, peg, BLOCK, block)
        assert abs(float(got["depth_m"]) - depth) < 1e-5 and got["inside"] is inside, got
        assert float(got["off_m"]) < 1e-5, got
    beside = {"xyz_m": [0.5, 0.2, 0.3 + 0.03 + 0.05], "quat_xyzw": _yaw(0.0)}
    got = in_hole(PEG, beside, BLOCK, block)
    assert got["inside"] is False and abs(float(got["off_m"]) - 0.04) < 1e-5, got

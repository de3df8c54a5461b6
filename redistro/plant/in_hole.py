"""How deep one object stands in another's hole, by the plant's truth (the
objects' poses in plant.json): the peg's bottom face centre in the frame
of the block's hole (origin at the mouth's centre, z out of the hole)."""

from __future__ import annotations

from typing import Any

import numpy as np

from redistro.config.model import ObjectConfig


def _rotation(q: list[float]) -> np.ndarray[Any, Any]:
    import pybullet as pb  # (its math only: no physics client)

    return np.asarray(pb.getMatrixFromQuaternion(q), dtype=np.float64).reshape(3, 3)


def in_hole(
    peg: ObjectConfig, peg_pose: dict[str, Any], block: ObjectConfig, block_pose: dict[str, Any]
) -> dict[str, float | bool]:
    """``depth_m``: how far the peg's bottom is below the hole's mouth,
    ``off_m``: how far its centre is from the hole's axis, ``inside``:
    within the hole's square (``peg``'s bottom down the ``block``'s hole)."""
    Rp, Rb = _rotation(peg_pose["quat_xyzw"]), _rotation(block_pose["quat_xyzw"])
    bottom = np.asarray(peg_pose["xyz_m"]) + Rp @ np.array([0.0, 0.0, -peg.size_xyz_m[2] / 2])
    ax, ay = block.hole_at_xy_m
    mouth = np.asarray(block_pose["xyz_m"]) + Rb @ np.array([ax, ay, block.size_xyz_m[2] / 2])
    d = Rb.T @ (bottom - mouth)
    half = block.hole_side_m / 2
    return {
        "depth_m": round(float(-d[2]), 5),
        "off_m": round(float(np.hypot(d[0], d[1])), 5),
        "inside": bool(block.hole_side_m > 0 and abs(d[0]) <= half and abs(d[1]) <= half),
    }

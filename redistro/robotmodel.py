"""The arm's URDF, shared by the plant (PyBullet) and the controller (Pinocchio).

The KUKA iiwa model from pybullet_data, with a wrist force/torque sensor: a
fixed joint ``wrist_ft`` from the flange (``lbr_iiwa_link_7``) to a ``tool``
link. On a robot that carries the peg the tool is the square peg (its axis
along the flange z axis); otherwise a thin sensor plate. Mesh paths are made
absolute so the generated file can live anywhere.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

FLANGE_LINK = "lbr_iiwa_link_7"
SENSOR_JOINT = "wrist_ft"
TOOL_LINK = "tool"
FLANGE_OFFSET_M = 0.045  # joint 7 frame to the flange face, along z
JOINT_NAMES = [f"lbr_iiwa_joint_{i}" for i in range(1, 8)]
PLATE = (0.06, 0.01, 0.05)  # sensor plate: diameter [m], thickness [m], mass [kg]


@dataclass(frozen=True)
class Peg:
    side_m: float
    length_m: float
    mass_kg: float


def _source() -> Path:
    import pybullet_data

    return Path(pybullet_data.getDataPath()) / "kuka_iiwa" / "model.urdf"


def _box_inertia(m: float, x: float, y: float, z: float) -> tuple[float, float, float]:
    return (m * (y * y + z * z) / 12, m * (x * x + z * z) / 12, m * (x * x + y * y) / 12)


def _tool_link(peg: Peg | None) -> str:
    if peg is not None:
        s, length, m = peg.side_m, peg.length_m, peg.mass_kg
        ixx, iyy, izz = _box_inertia(m, s, s, length)
        geom = f'<box size="{s} {s} {length}"/>'
        cz = length / 2
    else:
        d, t, m = PLATE
        ixx, iyy, izz = _box_inertia(m, d, d, t)
        geom = f'<cylinder radius="{d / 2}" length="{t}"/>'
        cz = t / 2
    return f"""
  <joint name="{SENSOR_JOINT}" type="fixed">
    <parent link="{FLANGE_LINK}"/>
    <child link="{TOOL_LINK}"/>
    <origin rpy="0 0 0" xyz="0 0 {FLANGE_OFFSET_M}"/>
  </joint>
  <link name="{TOOL_LINK}">
    <inertial>
      <origin rpy="0 0 0" xyz="0 0 {cz}"/>
      <mass value="{m}"/>
      <inertia ixx="{ixx:.3e}" ixy="0" ixz="0" iyy="{iyy:.3e}" iyz="0" izz="{izz:.3e}"/>
    </inertial>
    <visual>
      <origin rpy="0 0 0" xyz="0 0 {cz}"/>
      <geometry>{geom}</geometry>
      <material name="Peg"><color rgba="0.8 0.5 0.1 1"/></material>
    </visual>
    <collision>
      <origin rpy="0 0 0" xyz="0 0 {cz}"/>
      <geometry>{geom}</geometry>
    </collision>
  </link>
"""


def arm_urdf(peg: Peg | None) -> str:
    """The URDF text of one arm, with its tool."""
    src = _source()
    text = src.read_text()
    mesh_dir = src.parent
    text = re.sub(
        r'filename="(meshes/[^"]+)"', lambda m: f'filename="{mesh_dir / m.group(1)}"', text
    )
    return text.replace("</robot>", _tool_link(peg) + "</robot>")


def write_arm_urdf(directory: Path | str, name: str, peg: Peg | None) -> Path:
    """Write ``<directory>/<name>.urdf`` and return its path."""
    path = Path(directory) / f"{name}.urdf"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(arm_urdf(peg))
    return path


def quat_rpy(r: float, p: float, y: float) -> tuple[float, float, float, float]:
    """Roll-pitch-yaw (URDF's: R = Rz(y) Ry(p) Rx(r)) as a quaternion (x, y,
    z, w: PyBullet's and ROS's order)."""
    cr, sr, cp, sp = math.cos(r / 2), math.sin(r / 2), math.cos(p / 2), math.sin(p / 2)
    cy, sy = math.cos(y / 2), math.sin(y / 2)
    return (
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    )

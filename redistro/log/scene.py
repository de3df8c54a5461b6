"""The session log's 3D scene, in standard ROS 2 messages, made when the log is merged.

After the run (off every cycle), from the log's own metadata and its
feedback and plan channels, ``session.mcap`` gets what a 3D viewer
(Foxglove, Rerun, RViz from a rosbag2 replay) needs to draw the group:

- ``/robot_description`` (``std_msgs/msg/String``), once: the URDF of the
  group, a ``world`` link with each arm's links and joints prefixed with
  its robot (``r1_lbr_iiwa_link_3``, the joints as ``/<robot>/joint_states``
  names them), every mesh replaced by its bounding box (no ``package://``
  look-up);
- ``/tf_static``, once: ``world`` to each base, each flange to its
  ``<robot>_tool``, and the work-cell as the controller believes it
  (``hole_believed``, ``<object>_believed``: never the plant's truth);
- ``/tf`` (``tf2_msgs/msg/TFMessage``), every logged cycle: per robot each
  joint's parent link to child link from the measured joint positions, and
  ``<robot>_goal``, the SSC's goal pose of the tool;
- ``/workcell/markers`` (``visualization_msgs/msg/MarkerArray``), once: the
  table, the hole's fixture and the objects, as believed; and
  ``/markers/wrench``, at most ``ARROW_HZ``: each wrist's force as an arrow
  in its tool frame.
"""

from __future__ import annotations

import copy
import math
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from redistro.log.frames import CDR_HEADER
from redistro.log.ros2 import Cdr

ARROW_HZ = 30.0  # the wrench arrows' rate at most
ARROW_M_PER_N = 0.01  # an arrow's length per newton
WORLD = "world"

TF = "tf2_msgs/msg/TFMessage"
STRING = "std_msgs/msg/String"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"


@cache
def _store() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def definition(msgtype: str) -> str:
    """A standard message's ``ros2msg`` definition, with its dependencies."""
    return str(_store().generate_msgdef(msgtype, ros_version=2)[0])


def quat_rpy(r: float, p: float, y: float) -> np.ndarray[Any, Any]:
    """URDF roll-pitch-yaw as a quaternion (x, y, z, w)."""
    cr, sr, cp, sp = math.cos(r / 2), math.sin(r / 2), math.cos(p / 2), math.sin(p / 2)
    cy, sy = math.cos(y / 2), math.sin(y / 2)
    return np.array(
        [
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy,
        ]
    )


def quat_mul(a: np.ndarray[Any, Any], b: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Hamilton products of quaternions (x, y, z, w), broadcast over the leading axes."""
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def quat_rotvec(r: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Rotation vectors (..., 3) as quaternions (..., 4)."""
    angle = np.linalg.norm(r, axis=-1, keepdims=True)
    safe = np.where(angle > 1e-12, angle, 1.0)
    return np.concatenate([r / safe * np.sin(angle / 2), np.cos(angle / 2)], axis=-1)


class Arm:
    """One robot's kinematic chain as the URDF draws it: the revolute
    joints in order (parent, child, origin, axis) and the fixed ones."""

    def __init__(self, robot: str, peg: list[float] | None) -> None:
        from redistro.robotmodel import Peg, arm_urdf

        self.robot = robot
        self.root = ET.fromstring(arm_urdf(Peg(*peg) if peg else None))
        self.moving: list[tuple[str, str, np.ndarray[Any, Any], np.ndarray[Any, Any]]] = []
        self.axes: list[np.ndarray[Any, Any]] = []
        self.fixed: list[tuple[str, str, np.ndarray[Any, Any]]] = []
        for joint in self.root.iter("joint"):
            parent = self.name(_attr(joint, "parent", "link"))
            child = self.name(_attr(joint, "child", "link"))
            xyz, rpy = _origin(joint)
            pose = np.concatenate([xyz, quat_rpy(*rpy)])
            if joint.get("type") == "fixed":
                self.fixed.append((parent, child, pose))
            else:
                self.moving.append((parent, child, np.asarray(xyz), pose[3:]))
                axis = joint.find("axis")
                a = [
                    float(v)
                    for v in (axis.get("xyz", "0 0 1") if axis is not None else "0 0 1").split()
                ]
                self.axes.append(np.asarray(a) / np.linalg.norm(a))
        first = self.root.find("link")
        assert first is not None
        self.base = self.name(str(first.get("name")))

    def name(self, link: str) -> str:
        return f"{self.robot}_{link}"

    def links(self) -> list[str]:
        return [self.name(str(link.get("name"))) for link in self.root.iter("link")]

    def transforms(self, q: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        """(cycles, joints, 7): each joint's parent-to-child translation and
        rotation (x, y, z, w) at the joint positions ``q`` (cycles, joints)."""
        n = len(q)
        out = np.empty((n, len(self.moving), 7))
        for k, ((_, _, xyz, rot), axis) in enumerate(zip(self.moving, self.axes, strict=True)):
            half = q[:, k] / 2
            turn = np.concatenate([axis * np.sin(half)[:, None], np.cos(half)[:, None]], axis=1)
            out[:, k, :3] = xyz
            out[:, k, 3:] = quat_mul(rot, turn)
        return out


def _attr(el: ET.Element, tag: str, key: str) -> str:
    sub = el.find(tag)
    assert sub is not None
    return str(sub.get(key))


def _origin(el: ET.Element) -> tuple[list[float], list[float]]:
    o = el.find("origin")
    if o is None:
        return [0.0] * 3, [0.0] * 3
    return (
        [float(v) for v in o.get("xyz", "0 0 0").split()],
        [float(v) for v in o.get("rpy", "0 0 0").split()],
    )


class TfPacker:
    """``tf2_msgs/msg/TFMessage`` of fixed (parent, child) pairs, CDR-encoded
    for many cycles at once: a template with each transform's stamp and its
    seven doubles at offsets known from the start."""

    def __init__(self, pairs: list[tuple[str, str]]) -> None:
        c = Cdr()
        c.u32(len(pairs))
        self.stamps: list[int] = []
        self.values: list[int] = []
        for parent, child in pairs:
            c._align(4)
            self.stamps.append(len(c.buf))
            c.buf += bytes(8)
            c.string(parent)
            c.string(child)
            c._align(8)
            self.values.append(len(c.buf))
            c.buf += bytes(56)
        self.template = np.frombuffer(CDR_HEADER + bytes(c.buf), np.uint8)

    def pack(self, log_ns: np.ndarray[Any, Any], values: np.ndarray[Any, Any]) -> list[bytes]:
        """One message per cycle: ``values`` (cycles, pairs, 7), stamped ``log_ns``."""
        n = len(log_ns)
        out = np.tile(self.template, (n, 1))
        stamp = np.empty(n, [("sec", "<i4"), ("nanosec", "<u4")])
        stamp["sec"], stamp["nanosec"] = np.divmod(np.asarray(log_ns, np.int64), 1_000_000_000)
        sb = stamp.view(np.uint8).reshape(n, 8)
        vb = np.ascontiguousarray(values, "<f8").view(np.uint8).reshape(n, len(self.values), 56)
        for k, (s, v) in enumerate(zip(self.stamps, self.values, strict=True)):
            at = len(CDR_HEADER)
            out[:, at + s : at + s + 8] = sb
            out[:, at + v : at + v + 56] = vb[:, k]
        return [row.tobytes() for row in out]


def group_urdf(arms: dict[str, Arm], bases: dict[str, list[float]]) -> str:
    """The group's URDF: ``world``, each arm fixed to it at its base,
    every mesh replaced by its bounding box, colours inline."""
    robot = ET.Element("robot", name="redistro_group")
    ET.SubElement(robot, "link", name=WORLD)
    for r, arm in arms.items():
        for el in arm.root:
            if el.tag == "material":
                continue  # (shared names would clash: each visual gets its colour inline)
            el = copy.deepcopy(el)
            el.set("name", arm.name(str(el.get("name"))))
            for ref in (*el.findall("parent"), *el.findall("child")):
                ref.set("link", arm.name(str(ref.get("link"))))
            for part in (*el.findall("visual"), *el.findall("collision")):
                _primitive(part)
            robot.append(el)
        fix = ET.SubElement(robot, "joint", name=f"{r}_base", type="fixed")
        ET.SubElement(fix, "parent", link=WORLD)
        ET.SubElement(fix, "child", link=arm.base)
        ET.SubElement(fix, "origin", xyz=" ".join(map(str, bases[r])), rpy="0 0 0")
    ET.indent(robot)
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"


def _primitive(part: ET.Element) -> None:
    """A visual or collision's mesh as the box that bounds it; a visual
    coloured inline (grey, its tool's colour kept)."""
    geom = part.find("geometry")
    mesh = geom.find("mesh") if geom is not None else None
    if geom is not None and mesh is not None:
        lo, hi = _bounds(str(mesh.get("filename")))
        geom.remove(mesh)
        ET.SubElement(geom, "box", size=" ".join(f"{v:.4f}" for v in hi - lo))
        o = part.find("origin")
        if o is None:
            o = ET.SubElement(part, "origin", rpy="0 0 0", xyz="0 0 0")
        xyz = np.asarray([float(v) for v in o.get("xyz", "0 0 0").split()]) + (lo + hi) / 2
        o.set("xyz", " ".join(f"{v:.4f}" for v in xyz))
    if part.tag == "visual":
        mat = part.find("material")
        color = mat.find("color") if mat is not None else None
        rgba = color.get("rgba") if color is not None else "0.6 0.6 0.65 1"
        if mat is not None:
            part.remove(mat)
        m = ET.SubElement(part, "material", name="")
        ET.SubElement(m, "color", rgba=str(rgba))


@cache
def _bounds(filename: str) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """The bounding box of a mesh (its .obj beside it, vertex lines)."""
    obj = Path(filename).with_suffix(".obj")
    pts = [
        [float(v) for v in line.split()[1:4]]
        for line in obj.read_text().splitlines()
        if line.startswith("v ")
    ]
    a = np.asarray(pts)
    return a.min(axis=0), a.max(axis=0)


def static_transforms(meta: dict[str, Any], arms: dict[str, Arm]) -> list[tuple[str, str, Any]]:
    """(parent, child, pose xyz + quaternion): the bases, the tools, the
    work-cell as believed."""
    out: list[tuple[str, str, Any]] = []
    for r, arm in arms.items():
        base = meta["robots"][r]["base_xyz_m"]
        out.append((WORLD, arm.base, np.array([*base, 0, 0, 0, 1.0])))
        out += arm.fixed
    cell = meta.get("workcell") or {}
    if meta.get("hole_xyz_m") is not None:
        out.append((WORLD, "hole_believed", np.array([*meta["hole_xyz_m"], 0, 0, 0, 1.0])))
    for name, obj in (cell.get("objects") or {}).items():
        rot = quat_rpy(0, 0, math.radians(obj["yaw_deg"]))
        xyz = [*obj["xy_m"], cell["table_top_m"] + obj["size_xyz_m"][2] / 2]
        out.append((WORLD, f"{name}_believed", np.array([*xyz, *rot])))
    return out


def workcell_markers(meta: dict[str, Any], stamp_ns: int) -> Any:
    """The table, the fixture and the objects as the controller believes them."""
    cell = meta.get("workcell") or {}
    out = []
    if "table_top_m" in cell:
        top, (hx, hy), cx = cell["table_top_m"], cell["table_half_xy_m"], cell["table_x_m"]
        out.append(
            _box("table", [cx, 0, top - 0.01], [2 * hx, 2 * hy, 0.02], (0.55, 0.45, 0.35, 1))
        )
    hole = cell.get("hole")
    if hole:
        x, y, z = hole["xyz_m"]
        side, wall, depth = hole["side_m"], hole["wall_m"], hole["depth_m"] + hole["floor_m"]
        block = [side + 2 * wall, side + 2 * wall, depth]
        out.append(_box("fixture", [x, y, z - depth / 2], block, (0.3, 0.5, 0.8, 0.5)))
    if meta.get("hole_xyz_m") is not None:  # the mouth of the hole the task aims at
        side = hole["side_m"] if hole else 0.02
        mouth = _box("hole_believed", [0, 0, 0], [side, side, 0.002], (0.05, 0.05, 0.05, 1))
        out.append({**mouth, "frame": "hole_believed"})
    for name, obj in (cell.get("objects") or {}).items():
        out.append(
            _box(
                f"{name}_believed",
                [0, 0, 0],
                obj["size_xyz_m"],
                (0.2, 0.7, 0.3, 0.8),
                frame=f"{name}_believed",
            )
        )
    return _marker_array(out, stamp_ns)


def _box(
    ns: str, xyz: list[float], size: list[float], rgba: tuple[float, ...], frame: str = WORLD
) -> dict[str, Any]:
    return {
        "ns": ns,
        "type": 1,
        "frame": frame,
        "xyz": xyz,
        "scale": size,
        "rgba": rgba,
        "points": [],
    }


def _arrow(robot: str, force: np.ndarray[Any, Any]) -> dict[str, Any]:
    tip = [float(v) * ARROW_M_PER_N for v in force]
    return {
        "ns": f"{robot}_wrench",
        "type": 0,
        "frame": f"{robot}_tool",
        "xyz": [0, 0, 0],
        "scale": [0.006, 0.012, 0.015],  # shaft and head diameters, head length
        "rgba": (0.9, 0.2, 0.1, 1),
        "points": [[0, 0, 0], tip],
    }


def _marker_array(items: list[dict[str, Any]], stamp_ns: int) -> bytes:
    ts = _store()
    t = ts.types
    stamp = t["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    point, vec = t["geometry_msgs/msg/Point"], t["geometry_msgs/msg/Vector3"]
    empty_image = t["sensor_msgs/msg/CompressedImage"](
        header=t["std_msgs/msg/Header"](stamp=stamp, frame_id=""),
        format="",
        data=np.zeros(0, np.uint8),
    )
    markers = []
    for i, m in enumerate(items):
        markers.append(
            t["visualization_msgs/msg/Marker"](
                header=t["std_msgs/msg/Header"](stamp=stamp, frame_id=m["frame"]),
                ns=m["ns"],
                id=i,
                type=m["type"],
                action=0,
                pose=t["geometry_msgs/msg/Pose"](
                    position=point(*map(float, m["xyz"])),
                    orientation=t["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0),
                ),
                scale=vec(*map(float, m["scale"])),
                color=t["std_msgs/msg/ColorRGBA"](*map(float, m["rgba"])),
                lifetime=t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
                frame_locked=True,
                points=[point(*map(float, p)) for p in m["points"]],
                colors=[],
                texture_resource="",
                texture=empty_image,
                uv_coordinates=[],
                text="",
                mesh_resource="",
                mesh_file=t["visualization_msgs/msg/MeshFile"](
                    filename="", data=np.zeros(0, np.uint8)
                ),
                mesh_use_embedded_materials=False,
            )
        )
    msg = t[MARKER_ARRAY](markers=markers)
    return bytes(ts.serialize_cdr(msg, MARKER_ARRAY))


def string_message(text: str) -> bytes:
    c = Cdr()
    c.string(text)
    return CDR_HEADER + bytes(c.buf)


class Scene:
    """What the merge adds to the session log, from the log's metadata
    (``redistro.meta``: the robots' bases and tools, the believed work-cell)
    and each robot's feedback and plan arrays."""

    def __init__(self, meta: dict[str, Any]) -> None:
        self.meta = meta
        self.arms = {r: Arm(r, v.get("peg")) for r, v in sorted(meta["robots"].items())}

    def messages(
        self,
        feedback: dict[str, tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]],
        plans: dict[str, tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]],
        start_ns: int,
    ) -> Iterator[tuple[int, str, bytes]]:
        """(log time, topic, CDR message), in time order per topic:
        ``feedback``/``plans`` per robot: (log times, packed array)."""
        bases = {r: v["base_xyz_m"] for r, v in self.meta["robots"].items()}
        yield start_ns, "/robot_description", string_message(group_urdf(self.arms, bases))
        static = static_transforms(self.meta, self.arms)
        pack = TfPacker([(p, c) for p, c, _ in static])
        yield (
            start_ns,
            "/tf_static",
            pack.pack(np.array([start_ns]), np.stack([v for *_, v in static])[None])[0],
        )
        yield start_ns, "/workcell/markers", workcell_markers(self.meta, start_ns)
        for r, arm in self.arms.items():
            if r not in feedback:
                continue
            times, fb = feedback[r]
            values = arm.transforms(np.asarray(fb["q_rad"], float))
            tf = TfPacker([(p, c) for p, c, *_ in arm.moving])
            for t, data in zip(times.tolist(), tf.pack(times, values), strict=True):
                yield t, "/tf", data
        for r, (times, plan) in plans.items():
            xyz, rot = (
                np.asarray(plan["goal_xyz_m"], float),
                np.asarray(plan["goal_rot_xyz"], float),
            )
            values = np.concatenate([xyz, quat_rotvec(rot)], axis=1)[:, None, :]
            goal = TfPacker([(WORLD, f"{r}_goal")])
            for t, data in zip(times.tolist(), goal.pack(times, values), strict=True):
                yield t, "/tf", data
        yield from self._arrows(feedback)

    def _arrows(
        self, feedback: dict[str, tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]]
    ) -> Iterator[tuple[int, str, bytes]]:
        next_ns = 0
        period = int(1e9 / ARROW_HZ)
        robots = [r for r in self.arms if r in feedback]
        if not robots:
            return
        times = feedback[robots[0]][0]
        for t in times.tolist():
            if t < next_ns:
                continue
            next_ns = t + period
            items = []
            for r in robots:
                rt, fb = feedback[r]
                j = min(int(np.searchsorted(rt, t)), len(rt) - 1)
                items.append(_arrow(r, np.asarray(fb["wrench"][j][:3])))
            yield t, "/markers/wrench", _marker_array(items, t)

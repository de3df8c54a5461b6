"""The session log's 3D scene, in standard ROS 2 messages, made by the log writer.

From the log's own metadata (the robots' bases and tools, the work-cell as
the controller believes it) and each cycle's feedback and plan, the
writer process (off every cycle) adds what a 3D viewer (Foxglove, Rerun,
RViz from a rosbag2 replay) needs to draw the group:

- ``/tf`` (``tf2_msgs/msg/TFMessage``), every logged cycle: per robot each
  joint's parent link to child link from the measured joint positions
  (:class:`ArmFk`, pure Python: about 15 us a robot), and ``<robot>_goal``,
  the SSC's goal pose of the tool;
- at the end of the file, stamped at its first cycle: ``/robot_description``
  (``std_msgs/msg/String``): the URDF of the group, a ``world`` link with
  each arm's links and joints prefixed with its robot (``r1_lbr_iiwa_link_3``,
  the joints as ``/<robot>/joint_states`` names them), every mesh replaced
  by its bounding box (no ``package://`` look-up); ``/tf_static``: ``world``
  to each base, each flange to its ``<robot>_tool``, and the work-cell as
  believed (``hole_believed``, ``<object>_believed``: never the plant's
  truth); ``/workcell/markers`` (``visualization_msgs/msg/MarkerArray``):
  the table, the hole's fixture and the objects; and ``/markers/wrench``,
  at most ``ARROW_HZ``: each wrist's force as an arrow in its tool frame.
"""

from __future__ import annotations

import copy
import math
import struct
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from functools import cache
from pathlib import Path
from typing import Any

from redistro.log.frames import CDR_HEADER
from redistro.log.ros2 import Cdr
from redistro.robotmodel import quat_rpy

ARROW_HZ = 30.0  # the wrench arrows' rate at most
ARROW_M_PER_N = 0.01  # an arrow's length per newton
WORLD = "world"


# The standard messages the scene writes: their ``ros2msg`` definitions with
# their dependencies, as rosbags' ROS 2 Jazzy store generates them, and
# their CDR encoded here (the unit tests hold both to rosbags): the writer
# needs neither rosbags nor numpy, about 150 ms of every session's end.
def _msgdef(top: str, *deps: str) -> str:
    return top + "".join(f"{'=' * 80}\nMSG: {d}\n{_MSG[d]}" for d in deps)


_XYZ = "float64 x\nfloat64 y\nfloat64 z\n"
_MSG = {
    "geometry_msgs/TransformStamped": (
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n"
    ),
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "builtin_interfaces/Duration": "int32 sec\nuint32 nanosec\n",
    "geometry_msgs/Transform": (
        "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n"
    ),
    "geometry_msgs/Vector3": _XYZ,
    "geometry_msgs/Point": _XYZ,
    "geometry_msgs/Quaternion": _XYZ + "float64 w\n",
    "geometry_msgs/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
    "std_msgs/ColorRGBA": "float32 r\nfloat32 g\nfloat32 b\nfloat32 a\n",
    "sensor_msgs/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "visualization_msgs/UVCoordinate": "float32 u\nfloat32 v\n",
    "visualization_msgs/MeshFile": "string filename\nuint8[] data\n",
    "visualization_msgs/Marker": "".join(
        f"int32 {name}={value}\n"
        for value, name in enumerate(
            [
                "ARROW",
                "CUBE",
                "SPHERE",
                "CYLINDER",
                "LINE_STRIP",
                "LINE_LIST",
                "CUBE_LIST",
                "SPHERE_LIST",
                "POINTS",
                "TEXT_VIEW_FACING",
                "MESH_RESOURCE",
                "TRIANGLE_LIST",
                "ARROW_STRIP",
            ]
        )
    )
    + "int32 ADD=0\nint32 MODIFY=0\nint32 DELETE=2\nint32 DELETEALL=3\n"
    + "std_msgs/Header header\nstring ns\nint32 id\nint32 type\nint32 action\n"
    + "geometry_msgs/Pose pose\ngeometry_msgs/Vector3 scale\nstd_msgs/ColorRGBA color\n"
    + "builtin_interfaces/Duration lifetime\nbool frame_locked\n"
    + "geometry_msgs/Point[] points\nstd_msgs/ColorRGBA[] colors\n"
    + "string texture_resource\nsensor_msgs/CompressedImage texture\n"
    + "visualization_msgs/UVCoordinate[] uv_coordinates\nstring text\n"
    + "string mesh_resource\nvisualization_msgs/MeshFile mesh_file\n"
    + "bool mesh_use_embedded_materials\n",
}
TF = "tf2_msgs/msg/TFMessage"
TF_DEF = _msgdef(
    "geometry_msgs/TransformStamped[] transforms\n",
    "geometry_msgs/TransformStamped",
    "std_msgs/Header",
    "builtin_interfaces/Time",
    "geometry_msgs/Transform",
    "geometry_msgs/Vector3",
    "geometry_msgs/Quaternion",
)
STRING = "std_msgs/msg/String"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
MARKER_ARRAY_DEF = _msgdef(
    "visualization_msgs/Marker[] markers\n",
    "visualization_msgs/Marker",
    "std_msgs/Header",
    "builtin_interfaces/Time",
    "geometry_msgs/Pose",
    "geometry_msgs/Point",
    "geometry_msgs/Quaternion",
    "geometry_msgs/Vector3",
    "std_msgs/ColorRGBA",
    "builtin_interfaces/Duration",
    "sensor_msgs/CompressedImage",
    "visualization_msgs/UVCoordinate",
    "visualization_msgs/MeshFile",
)
DEFINITIONS = {TF: TF_DEF, STRING: "string data\n", MARKER_ARRAY: MARKER_ARRAY_DEF}


@cache
def full_store() -> Any:
    """rosbags' whole ROS 2 Jazzy store (its type hashes, the tests' definitions)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def definition(msgtype: str) -> str:
    """A standard message's ``ros2msg`` definition, with its dependencies."""
    return DEFINITIONS[msgtype]


Quat = tuple[float, float, float, float]  # x, y, z, w


def quat_mul(a: Quat, b: Quat) -> Quat:
    """The Hamilton product a b of quaternions (x, y, z, w)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def quat_rotvec(x: float, y: float, z: float) -> Quat:
    """A rotation vector as a quaternion."""
    angle = math.sqrt(x * x + y * y + z * z)
    if angle < 1e-12:
        return (0.0, 0.0, 0.0, 1.0)
    k = math.sin(angle / 2) / angle
    return (x * k, y * k, z * k, math.cos(angle / 2))


Pose = tuple[float, float, float, float, float, float, float]  # translation, rotation


class Arm:
    """One robot's kinematic chain as the URDF draws it: the revolute
    joints in order (parent, child, origin, axis) and the fixed ones."""

    def __init__(self, robot: str, peg: list[float] | None) -> None:
        from redistro.robotmodel import Peg, arm_urdf

        self.robot = robot
        self.root = ET.fromstring(arm_urdf(Peg(*peg) if peg else None))
        # revolute joints: parent, child, origin translation, origin rotation, axis
        self.moving: list[tuple[str, str, tuple[float, ...], Quat, tuple[float, ...]]] = []
        self.fixed: list[tuple[str, str, Pose]] = []
        for joint in self.root.iter("joint"):
            parent = self.name(_attr(joint, "parent", "link"))
            child = self.name(_attr(joint, "child", "link"))
            xyz, rpy = _origin(joint)
            rot = quat_rpy(*rpy)
            if joint.get("type") == "fixed":
                self.fixed.append((parent, child, _pose(xyz, rot)))
            else:
                axis = joint.find("axis")
                text = axis.get("xyz", "0 0 1") if axis is not None else "0 0 1"
                a = [float(v) for v in text.split()]
                n = math.sqrt(sum(v * v for v in a))
                self.moving.append((parent, child, tuple(xyz), rot, tuple(v / n for v in a)))
        first = self.root.find("link")
        assert first is not None
        self.base = self.name(str(first.get("name")))

    def name(self, link: str) -> str:
        return f"{self.robot}_{link}"

    def links(self) -> list[str]:
        return [self.name(str(link.get("name"))) for link in self.root.iter("link")]

    def transforms(self, q: list[float] | tuple[float, ...]) -> list[Pose]:
        """Each revolute joint's parent-to-child translation and rotation at
        the joint positions ``q`` (the translation is the joint's origin)."""
        out: list[Pose] = []
        sin, cos = math.sin, math.cos
        for (_, _, (x, y, z), (rx, ry, rz, rw), axis), qi in zip(self.moving, q, strict=True):
            s, c = sin(qi / 2), cos(qi / 2)
            if axis == (0.0, 0.0, 1.0):  # (the iiwa's every joint: rot times (0, 0, s, c))
                r = (rx * c + ry * s, ry * c - rx * s, rw * s + rz * c, rw * c - rz * s)
            else:
                r = quat_mul((rx, ry, rz, rw), (axis[0] * s, axis[1] * s, axis[2] * s, c))
            out.append((x, y, z, *r))
        return out


def _pose(xyz: Any, rot: Quat) -> Pose:
    return (float(xyz[0]), float(xyz[1]), float(xyz[2]), *rot)


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


_STAMP = struct.Struct("<iI")
_POSE = struct.Struct("<7d")


class TfTemplate:
    """``tf2_msgs/msg/TFMessage`` of fixed (parent, child) pairs, CDR-encoded:
    a template with each transform's stamp and its seven doubles at offsets
    known from the start (a message: a copy and 2 packs per transform)."""

    def __init__(self, pairs: list[tuple[str, str]]) -> None:
        c = Cdr()
        c.u32(len(pairs))
        self.stamps: list[int] = []
        self.values: list[int] = []
        at = len(CDR_HEADER)
        for parent, child in pairs:
            c._align(4)
            self.stamps.append(at + len(c.buf))
            c.buf += bytes(8)
            c.string(parent)
            c.string(child)
            c._align(8)
            self.values.append(at + len(c.buf))
            c.buf += bytes(56)
        self.template = CDR_HEADER + bytes(c.buf)

    def pack(self, log_ns: int, poses: list[Pose]) -> bytes:
        """One message: ``poses`` (translation, rotation x y z w) stamped ``log_ns``."""
        out = bytearray(self.template)
        sec, nsec = divmod(log_ns, 1_000_000_000)
        for s_at, v_at, pose in zip(self.stamps, self.values, poses, strict=True):
            _STAMP.pack_into(out, s_at, sec, nsec)
            _POSE.pack_into(out, v_at, *pose)
        return bytes(out)


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
            for part in el.findall("collision"):
                el.remove(part)  # (a picture: what the viewers draw)
            for part in el.findall("visual"):
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
        ET.SubElement(
            geom, "box", size=" ".join(f"{b - a:.4f}" for a, b in zip(lo, hi, strict=True))
        )
        o = part.find("origin")
        if o is None:
            o = ET.SubElement(part, "origin", rpy="0 0 0", xyz="0 0 0")
        at = [float(v) for v in o.get("xyz", "0 0 0").split()]
        xyz = [v + (a + b) / 2 for v, a, b in zip(at, lo, hi, strict=True)]
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
def _bounds(filename: str) -> tuple[list[float], list[float]]:
    """The bounding box of a mesh (its .obj beside it, vertex lines): its
    lowest and highest x, y, z (no numpy: the log writer has none)."""
    obj = Path(filename).with_suffix(".obj")
    axes = zip(
        *(
            [float(v) for v in line.split()[1:4]]
            for line in obj.read_text().splitlines()
            if line.startswith("v ")
        ),
        strict=True,
    )
    lo, hi = [], []
    for values in axes:
        lo.append(min(values))
        hi.append(max(values))
    return lo, hi


def static_transforms(meta: dict[str, Any], arms: dict[str, Arm]) -> list[tuple[str, str, Pose]]:
    """(parent, child, pose): the bases, the tools, the work-cell as believed."""
    out: list[tuple[str, str, Pose]] = []
    for r, arm in arms.items():
        x, y, z = meta["robots"][r]["base_xyz_m"]
        out.append((WORLD, arm.base, (x, y, z, 0.0, 0.0, 0.0, 1.0)))
        out += arm.fixed
    cell = meta.get("workcell") or {}
    if meta.get("hole_xyz_m") is not None:
        x, y, z = meta["hole_xyz_m"]
        out.append((WORLD, "hole_believed", (x, y, z, 0.0, 0.0, 0.0, 1.0)))
    for name, obj in (cell.get("objects") or {}).items():
        rot = quat_rpy(0, 0, math.radians(obj["yaw_deg"]))
        x, y = obj["xy_m"]
        z = cell["table_top_m"] + obj["size_xyz_m"][2] / 2
        out.append((WORLD, f"{name}_believed", (x, y, z, *rot)))
    return out


def workcell_markers(meta: dict[str, Any], stamp_ns: int) -> bytes:
    """The table, the fixture and the objects as the controller believes them."""
    return _marker_array(_workcell_items(meta), stamp_ns)


def _workcell_items(meta: dict[str, Any]) -> list[dict[str, Any]]:
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
    return out


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


def _arrow(robot: str, force: tuple[float, float, float]) -> dict[str, Any]:
    tip = [v * ARROW_M_PER_N for v in force]
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
    """``visualization_msgs/msg/MarkerArray`` in CDR, one marker an item
    (the unit tests hold it to rosbags' encoding of the same, byte for byte)."""
    c = Cdr()
    sec, nanosec = stamp_ns // 10**9, stamp_ns % 10**9
    c.u32(len(items))
    for i, m in enumerate(items):
        c.i32(sec)  # header
        c.u32(nanosec)
        c.string(m["frame"])
        c.string(m["ns"])
        c.i32(i)  # id
        c.i32(int(m["type"]))
        c.i32(0)  # action: ADD
        c.f64s([*map(float, m["xyz"]), 0.0, 0.0, 0.0, 1.0])  # pose
        c.f64s([*map(float, m["scale"])])
        c.f32s([*map(float, m["rgba"])])  # color
        c.i32(0)  # lifetime (none)
        c.u32(0)
        c.u8(1)  # frame_locked
        c.u32(len(m["points"]))
        for p in m["points"]:
            c.f64s([*map(float, p)])
        c.u32(0)  # colors
        c.string("")  # texture_resource
        c.i32(sec)  # texture: its header, format and data (none)
        c.u32(nanosec)
        c.string("")
        c.string("")
        c.u32(0)
        c.u32(0)  # uv_coordinates
        c.string("")  # text
        c.string("")  # mesh_resource
        c.string("")  # mesh_file: filename, data (none)
        c.u32(0)
        c.u8(0)  # mesh_use_embedded_materials
    return CDR_HEADER + bytes(c.buf)


def string_message(text: str) -> bytes:
    c = Cdr()
    c.string(text)
    return CDR_HEADER + bytes(c.buf)


class Online:
    """The scene as the log writer makes it. Per cycle (no numpy): one
    ``/tf`` message with every joint of every robot whose feedback the
    node logs (``parts``, in the order the writer meets them: ``("feedback",
    robot)``) and the goal of every plan (``("plan", robot)``), a wrist force
    kept for the arrows at most ``ARROW_HZ``. At the end: the static scene
    and the arrows (:meth:`closing`)."""

    def __init__(self, meta: dict[str, Any], parts: list[tuple[str, str]]) -> None:
        self.meta = meta
        self.arms = {r: Arm(r, v.get("peg")) for r, v in sorted(meta["robots"].items())}
        pairs: list[tuple[str, str]] = []
        for kind, robot in parts:
            if kind == "feedback":
                pairs += [(p, c) for p, c, *_ in self.arms[robot].moving]
            else:
                pairs.append((WORLD, f"{robot}_goal"))
        self.tf = TfTemplate(pairs)
        self.first_ns = 0
        self.period_ns = int(1e9 / ARROW_HZ)
        self.next_arrow: dict[str, int] = {}
        self.forces: list[tuple[int, str, tuple[float, float, float]]] = []

    def joints(
        self, robot: str, q: tuple[float, ...], force: tuple[float, ...], ns: int
    ) -> list[Pose]:
        """The robot's joint transforms for this cycle (its force kept)."""
        if ns >= self.next_arrow.get(robot, 0):
            self.next_arrow[robot] = ns + self.period_ns
            self.forces.append((ns, robot, (force[0], force[1], force[2])))
        return self.arms[robot].transforms(q)

    @staticmethod
    def goal(xyz: tuple[float, ...], rot: tuple[float, ...]) -> Pose:
        return _pose(xyz, quat_rotvec(*rot))

    def message(self, ns: int, poses: list[Pose]) -> bytes:
        """The cycle's ``/tf`` message (``poses`` in the order of ``parts``)."""
        self.first_ns = self.first_ns or ns
        return self.tf.pack(ns, poses)

    def closing(self) -> Iterator[tuple[int, str, str, bytes]]:
        """(log time, topic, type, message): the static scene at the first
        cycle's time, then the wrench arrows, one array per sample time."""
        if not self.first_ns:
            return
        yield from static_messages(self.meta, self.arms, self.first_ns)
        by_time: dict[int, list[dict[str, Any]]] = {}
        for ns, robot, force in self.forces:
            by_time.setdefault(ns, []).append(_arrow(robot, force))
        for ns, items in by_time.items():
            yield ns, "/markers/wrench", MARKER_ARRAY, _marker_array(items, ns)


def static_messages(
    meta: dict[str, Any], arms: dict[str, Arm], stamp_ns: int
) -> list[tuple[int, str, str, bytes]]:
    """(log time, topic, type, message): the group's URDF, its static
    transforms and the work-cell's markers."""
    bases = {r: meta["robots"][r]["base_xyz_m"] for r in arms}
    static = static_transforms(meta, arms)
    tf = TfTemplate([(p, c) for p, c, _ in static]).pack(stamp_ns, [v for *_, v in static])
    return [
        (stamp_ns, "/robot_description", STRING, string_message(group_urdf(arms, bases))),
        (stamp_ns, "/tf_static", TF, tf),
        (stamp_ns, "/workcell/markers", MARKER_ARRAY, workcell_markers(meta, stamp_ns)),
    ]

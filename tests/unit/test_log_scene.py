"""The log's 3D scene: the group's URDF, the transforms packed by hand, checked by other code."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from redistro.log import scene

ROBOTS = {"r1": {"base_xyz_m": [0.0, 0.45, 0.0], "peg": None}}
ROBOTS["r2"] = {"base_xyz_m": [0.0, -0.45, 0.0], "peg": [0.02, 0.1, 0.1]}


@pytest.fixture(scope="module")
def arms() -> dict[str, scene.Arm]:
    return {r: scene.Arm(r, v["peg"]) for r, v in ROBOTS.items()}


def test_the_group_urdf_is_one_robot_with_both_arms_at_their_bases(
    arms: dict[str, scene.Arm],
) -> None:
    """Pinocchio builds the group from the URDF text alone (no mesh to
    find): 14 joints named as the joint states name them, and its forward
    kinematics agrees with the transforms the log carries, on random poses."""
    import pinocchio as pin

    text = scene.group_urdf(arms, {r: v["base_xyz_m"] for r, v in ROBOTS.items()})
    assert "<mesh" not in text and "package://" not in text
    model = pin.buildModelFromXML(text)
    names = [model.names[i] for i in range(1, model.njoints)]
    assert names == [f"{r}_lbr_iiwa_joint_{k}" for r in ROBOTS for k in range(1, 8)]
    data = model.createData()
    rng = np.random.default_rng(7)
    q = rng.uniform(-2.0, 2.0, (200, 14))
    for r, arm in arms.items():
        i = list(ROBOTS).index(r)
        tool = model.getFrameId(f"{r}_tool")
        for n in range(0, 200, 7):
            values = arm.transforms(tuple(q[n, 7 * i : 7 * i + 7]))
            pin.framesForwardKinematics(model, data, q[n])
            pose = np.eye(4)
            pose[:3, 3] = ROBOTS[r]["base_xyz_m"]
            for k in range(7):
                pose = pose @ _matrix(np.asarray(values[k]))
            flange = data.oMf[model.getFrameId(f"{r}_lbr_iiwa_link_7")]
            np.testing.assert_allclose(pose[:3, 3], flange.translation, atol=1e-12)
            np.testing.assert_allclose(pose[:3, :3], flange.rotation, atol=1e-12)
            assert np.linalg.norm(data.oMf[tool].translation - flange.translation) > 0.04


def _matrix(v: np.ndarray) -> np.ndarray:  # (translation, rotation x y z w)
    import pinocchio as pin

    m = np.eye(4)
    m[:3, :3] = pin.Quaternion(v[6], v[3], v[4], v[5]).toRotationMatrix()
    m[:3, 3] = v[:3]
    return m


def test_packed_transforms_decode_in_rosbags_to_the_same_values() -> None:
    """The hand-packed TFMessage, deserialized by rosbags' own CDR code."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    pairs = [("world", "a"), ("a", "bb_longer_name"), ("bb_longer_name", "c")]
    rng = np.random.default_rng(3)
    values = rng.normal(size=(50, 3, 7))
    stamps = rng.integers(0, 2**31 * 10**9, 50)
    template = scene.TfTemplate(pairs)
    for v, t in zip(values, stamps, strict=True):
        data = template.pack(int(t), [tuple(row) for row in v])  # type: ignore[misc]
        msg = store.deserialize_cdr(data, scene.TF)
        assert [(x.header.frame_id, x.child_frame_id) for x in msg.transforms] == pairs
        for x, row in zip(msg.transforms, v, strict=True):
            assert (x.header.stamp.sec, x.header.stamp.nanosec) == divmod(int(t), 10**9)
            tr, rot = x.transform.translation, x.transform.rotation
            got = [tr.x, tr.y, tr.z, rot.x, rot.y, rot.z, rot.w]
            np.testing.assert_array_equal(got, row)


def test_stamps_split_into_seconds_and_nanoseconds() -> None:
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    t = 1_764_000_000_123_456_789
    data = scene.TfTemplate([("world", "x")]).pack(t, [(0.0,) * 7])  # type: ignore[list-item]
    stamp = store.deserialize_cdr(data, scene.TF).transforms[0].header.stamp
    assert (stamp.sec, stamp.nanosec) == (1_764_000_000, 123_456_789)


def test_rotation_vectors_become_the_quaternions_pinocchio_makes() -> None:
    import pinocchio as pin

    rng = np.random.default_rng(5)
    r = rng.normal(size=(100, 3))
    r[0] = 0.0
    q = [scene.quat_rotvec(*v) for v in r]
    for v, quat in zip(r, q, strict=True):
        want = pin.Quaternion(pin.exp3(v))
        got = pin.Quaternion(quat[3], *quat[:3])
        assert got.angularDistance(want) < 1e-9


def _cell_meta() -> dict[str, Any]:
    meta: dict[str, Any] = {
        "robots": ROBOTS,
        "hole_xyz_m": [0.55, -0.35, 0.15],
        "workcell": {
            "table_top_m": 0.1,
            "table_half_xy_m": [0.3, 0.6],
            "table_x_m": 0.55,
            "hole": {"xyz_m": [0.55, -0.35, 0.15], "side_m": 0.021, "wall_m": 0.03},
            "objects": {"bar": {"size_xyz_m": [0.04, 0.4, 0.06], "xy_m": [0.5, 0.0], "yaw_deg": 2}},
        },
    }
    meta["workcell"]["hole"].update(depth_m=0.04, floor_m=0.01)
    return meta


def test_the_workcell_markers_decode_in_a_ros2_reader() -> None:
    """... and in mcap-ros2-support, from the definition the log carries."""
    from mcap.records import Schema
    from mcap_ros2.decoder import DecoderFactory

    meta = _cell_meta()
    data = scene.workcell_markers(meta, 5)
    text = scene.definition(scene.MARKER_ARRAY).encode()
    schema = Schema(id=1, name=scene.MARKER_ARRAY, encoding="ros2msg", data=text)
    decode = DecoderFactory().decoder_for("cdr", schema)
    assert decode is not None
    msg = decode(data)
    assert [m.ns for m in msg.markers] == ["table", "fixture", "hole_believed", "bar_believed"]
    bar = msg.markers[-1]
    assert bar.header.frame_id == "bar_believed" and bar.type == 1  # a cube in its own frame
    assert [bar.scale.x, bar.scale.y, bar.scale.z] == [0.04, 0.4, 0.06]


def test_the_definitions_are_the_standard_ones() -> None:
    """The writer registers its standard messages from its own texts: each
    is the one rosbags' ROS 2 store generates."""
    full = scene.full_store()
    for msgtype in (scene.TF, scene.STRING, scene.MARKER_ARRAY):
        assert scene.definition(msgtype) == full.generate_msgdef(msgtype, ros_version=2)[0]


def _rosbags_markers(items: list[dict[str, Any]], stamp_ns: int) -> bytes:
    """The marker array of ``items`` as rosbags serializes it (the oracle)."""
    ts = scene.full_store()
    t = ts.types
    stamp = t["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    point, header = t["geometry_msgs/msg/Point"], t["std_msgs/msg/Header"]
    none = np.zeros(0, np.uint8)
    markers = [
        t["visualization_msgs/msg/Marker"](
            header=header(stamp=stamp, frame_id=m["frame"]),
            ns=m["ns"],
            id=i,
            type=m["type"],
            action=0,
            pose=t["geometry_msgs/msg/Pose"](
                position=point(*map(float, m["xyz"])),
                orientation=t["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0),
            ),
            scale=t["geometry_msgs/msg/Vector3"](*map(float, m["scale"])),
            color=t["std_msgs/msg/ColorRGBA"](*map(float, m["rgba"])),
            lifetime=t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
            frame_locked=True,
            points=[point(*map(float, p)) for p in m["points"]],
            colors=[],
            texture_resource="",
            texture=t["sensor_msgs/msg/CompressedImage"](
                header=header(stamp=stamp, frame_id=""), format="", data=none
            ),
            uv_coordinates=[],
            text="",
            mesh_resource="",
            mesh_file=t["visualization_msgs/msg/MeshFile"](filename="", data=none),
            mesh_use_embedded_materials=False,
        )
        for i, m in enumerate(items)
    ]
    msg = t[scene.MARKER_ARRAY](markers=markers)
    return bytes(ts.serialize_cdr(msg, scene.MARKER_ARRAY))


def test_the_marker_arrays_are_rosbags_own_to_the_byte() -> None:
    """The work-cell's markers and random arrows (odd names, empty and
    long point lists): the scene's CDR is the one rosbags writes."""
    rng = np.random.default_rng(7)
    meta = _cell_meta()
    items = scene._workcell_items(meta)
    assert scene.workcell_markers(meta, 5) == _rosbags_markers(items, 5)
    for n in range(40):
        arrows = [
            {
                "frame": "f" * int(rng.integers(0, 9)),
                "ns": "n" * int(rng.integers(0, 13)),
                "type": int(rng.integers(0, 13)),
                "xyz": rng.normal(size=3).tolist(),
                "scale": rng.random(3).tolist(),
                "rgba": rng.random(4).tolist(),
                "points": rng.normal(size=(int(rng.integers(0, 4)), 3)).tolist(),
            }
            for _ in range(int(rng.integers(0, 4)))
        ]
        stamp = int(rng.integers(0, 2**31 * 10**9))
        assert scene._marker_array(arrows, stamp) == _rosbags_markers(arrows, stamp), n


def test_the_z_axis_shortcut_is_the_general_product(arms: dict[str, scene.Arm]) -> None:
    """Every iiwa joint turns about z, computed by a shortcut: the same as
    the general axis-angle product (an axis given as a list takes that path)."""
    import copy

    arm = arms["r2"]
    general = copy.copy(arm)
    general.moving = [(p, c, xyz, rot, list(axis)) for p, c, xyz, rot, axis in arm.moving]  # type: ignore[misc]
    rng = np.random.default_rng(11)
    for q in rng.uniform(-3.0, 3.0, (100, 7)):
        np.testing.assert_allclose(
            arm.transforms(tuple(q)), general.transforms(tuple(q)), atol=1e-15
        )


def test_one_tf_message_a_cycle_holds_every_part_in_order() -> None:
    meta = {"robots": ROBOTS}
    parts = [("feedback", "r1"), ("plan", "r1"), ("feedback", "r2"), ("plan", "r2")]
    online = scene.Online(meta, parts)
    q = (0.1, -0.2, 0.3, -1.2, 0.2, 0.9, 0.0)
    poses = online.joints("r1", q, (1.0, 2.0, 3.0), 7)
    poses.append(online.goal((0.5, 0.1, 0.3), (0.0, 0.0, 0.0)))
    poses += online.joints("r2", q, (0.0, 0.0, -5.0), 7)
    poses.append(online.goal((0.5, -0.1, 0.3), (0.0, 0.0, 0.1)))
    from rosbags.typesys import Stores, get_typestore

    msg = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(online.message(7, poses), scene.TF)
    children = [t.child_frame_id for t in msg.transforms]
    assert children == [f"r1_lbr_iiwa_link_{k}" for k in range(1, 8)] + ["r1_goal"] + [
        f"r2_lbr_iiwa_link_{k}" for k in range(1, 8)
    ] + ["r2_goal"]
    assert [f[1] for f in online.forces] == ["r1", "r2"]  # (the arrows' samples)

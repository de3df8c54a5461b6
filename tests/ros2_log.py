"""A session log checked by readers no one here wrote: rosbags, mcap-ros2-support, Rerun.

Used by the session tests on a real run's ``session.mcap``.
"""

from __future__ import annotations

import re
import subprocess
import xml.etree.ElementTree as ET
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from tests.helpers import ROOT

RERUN = ROOT / ".venv" / "bin" / "rerun"


def rosbags_counts(path: Path) -> tuple[Counter[str], list[tuple[int, str, Any]]]:
    """Every message of every channel deserialized by rosbags (as a rosbag2
    MCAP file): the count per topic, and the transforms and joint states in
    log order as (log time, topic, message)."""
    from rosbags.highlevel import AnyReader

    counts: Counter[str] = Counter()
    keep: list[tuple[int, str, Any]] = []
    with AnyReader([path]) as reader:
        for conn, t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            counts[conn.topic] += 1
            if conn.topic in ("/tf", "/tf_static", "/robot_description") or conn.topic.endswith(
                "/joint_states"
            ):
                keep.append((t, conn.topic, msg))
    return counts, keep


def mcap_ros2_count(path: Path) -> int:
    """Every message decoded by mcap-ros2-support from its ros2msg schema."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return sum(1 for _ in reader.iter_decoded_messages())


def rerun_entities(path: Path, tmp: Path) -> Counter[tuple[str, str]]:
    """Rerun's MCAP import (``rerun mcap convert``), its recording printed:
    rows per (entity path, archetype)."""
    rrd = tmp / "session.rrd"
    subprocess.run(
        [str(RERUN), "mcap", "convert", str(path), "-o", str(rrd)],
        check=True,
        capture_output=True,
        timeout=300,
    )
    printed = subprocess.run(
        [str(RERUN), "rrd", "print", str(rrd)],
        check=True,
        capture_output=True,
        text=True,
        timeout=300,
    ).stdout
    rows: Counter[tuple[str, str]] = Counter()
    for m in re.finditer(r"with (\d+) rows .*? - (\S+) - data columns: \[(.*)\]", printed):
        for arch in {c.split(":")[0] for c in m.group(3).split()}:
            rows[(m.group(2), arch)] += int(m.group(1))
    return rows


def _matrix(tr: Any) -> np.ndarray[Any, Any]:
    x, y, z, w = tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w
    m = np.eye(4)
    m[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    m[:3, 3] = [tr.translation.x, tr.translation.y, tr.translation.z]
    return m


def to_world(frame: str, tree: dict[str, tuple[str, np.ndarray[Any, Any]]]) -> Any:
    """The pose of ``frame`` in ``world`` through the tree (None: no path)."""
    pose = np.eye(4)
    for _ in range(64):
        if frame == "world":
            return pose
        if frame not in tree:
            return None
        frame, m = tree[frame][0], tree[frame][1] @ pose
        pose = m
    return None


def check_tf_tree(
    kept: list[tuple[int, str, Any]], robots: dict[str, Any], every: int = 25
) -> dict[str, int]:
    """Every link of ``/robot_description`` has a path to ``world`` at every
    logged cycle (each ``/tf`` message), and every ``every``-th cycle each
    tool's pose in the tree is Pinocchio's forward kinematics of the joint
    states logged with it. Returns counts of what was checked."""
    from redistro.control.dynamics import ArmModel
    from redistro.robotmodel import Peg

    urdf = next(m.data for _, topic, m in kept if topic == "/robot_description")
    links = [el.get("name") for el in ET.fromstring(urdf).iter("link")]
    assert len(links) == 1 + 9 * len(robots), links
    tree: dict[str, tuple[str, np.ndarray[Any, Any]]] = {}
    models = {
        r: ArmModel(Peg(*v["peg"]) if v["peg"] else None, v["base_xyz_m"])
        for r, v in robots.items()
    }
    joints: dict[str, np.ndarray[Any, Any]] = {}
    checked = {"cycles": 0, "poses": 0}

    def check_cycle() -> None:
        missing = [link for link in links if to_world(str(link), tree) is None]
        assert not missing, f"cycle {checked['cycles']}: no path to world from {missing}"
        checked["cycles"] += 1
        if checked["cycles"] % every:
            return
        for robot, q in joints.items():
            k = models[robot].kinematics(q)
            pose = to_world(f"{robot}_tool", tree)
            np.testing.assert_allclose(pose[:3, 3], k.sensor_p, atol=1e-9)
            np.testing.assert_allclose(pose[:3, :3], k.R, atol=1e-9)
            checked["poses"] += 1

    # a /tf message is one cycle, whole (every robot's joints and goal):
    # checked as it comes, with the joint states logged just before it. The
    # static scene, written at the file's end, is stamped at its first cycle
    # and comes after that cycle's messages: the first /tf waits for it.
    static_seen = pending = False
    for _t, topic, msg in kept:
        if topic.endswith("/joint_states"):
            joints[topic.split("/")[1]] = np.asarray(msg.position, float)
        elif topic in ("/tf", "/tf_static"):
            for ts in msg.transforms:
                tree[ts.child_frame_id] = (ts.header.frame_id, _matrix(ts.transform))
            if topic == "/tf_static":
                static_seen = True
                if pending:
                    check_cycle()
                    pending = False
            elif static_seen:
                check_cycle()
            else:
                pending = True
    if pending:
        check_cycle()  # (fails: no static scene, no path to world)
    return checked

"""A live session as ROS 2 topics over Zenoh, taken by a ROS 2 client no one here wrote."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import (
    ROOT,
    attach_running,
    copy_runs,
    load_json,
    read_session_id,
    start_cli,
)

pytestmark = pytest.mark.peg

SHORT = "tasks/peg_insertion_short.yaml"
JOINTS = [f"r2_lbr_iiwa_joint_{k}" for k in range(1, 8)]
TAKE = 40


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_a_ros2_client_over_zenoh_takes_a_live_sessions_joint_states(
    calibrated: Path, tmp_path: Path
) -> None:
    """zenoh-ros2-sdk, subscribed to the bridge of a running peg session
    (``ros2.bridge``), lists its topics from the liveliness tokens and
    receives ``/r2/joint_states`` on the key its own type hash makes: r2's
    joint names, the positions the session logged at that time, at most
    ``ros2.rate_hz``. The session ends ok and inserted."""
    from redistro.log.mcapfile import read_log

    port = _free_port()
    runs = copy_runs(calibrated, tmp_path)
    out = tmp_path / "run"
    proc = start_cli(
        "--set",
        f"session.runs_dir={runs}",
        "--set",
        "ros2.bridge=true",
        "--set",
        f"ros2.listen=[tcp/127.0.0.1:{port}]",
        "session",
        SHORT,
        "--out",
        str(out),
    )
    try:
        sid = read_session_id(proc)
        attach_running(sid, "esc.r2", min_cycle=100, timeout=120).close()
        args = [str(port), "/r2/joint_states", str(TAKE), "60", str(tmp_path / "msgs")]
        listener = subprocess.run(
            [sys.executable, "tests/ros2_listener.py", *args],
            capture_output=True,
            text=True,
            timeout=120,
            cwd=ROOT,
            check=False,
            # (its default config, rmw_zenoh's, offers shared memory: a
            # /dev/shm file outliving the process)
            env={**os.environ, "ZENOH_CONFIG_OVERRIDE": "transport/shared_memory/enabled=false"},
        )
        said, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, said[-3000:] + err[-3000:]
    assert listener.returncode == 0, listener.stderr[-3000:]
    doc = json.loads(listener.stdout.strip().splitlines()[-1])
    topics = dict((name, types) for name, types in doc["topics"])
    assert topics.get("/r2/joint_states") == ["sensor_msgs/msg/JointState"], topics
    assert topics.get("/r1/wrench") == ["geometry_msgs/msg/WrenchStamped"], topics
    assert topics.get("/ssc/segment") == ["std_msgs/msg/String"], topics
    msgs = doc["messages"]
    assert len(msgs) == TAKE, (len(msgs), doc["key"])
    stamps = np.asarray([m["stamp_ns"] for m in msgs])
    assert np.all(np.diff(stamps) > 0)
    summary = load_json(out / "summary.json")
    assert (stamps[-1] - stamps[0]) / 1e9 >= (TAKE - 1) / 100.0, "more than 100 Hz"
    sl = read_log(out / "session.mcap")
    logged_t = sl.log_times["/r2/feedback"]
    logged_q = sl.arrays["/r2/feedback"]["q_rad"]
    for m in msgs:
        assert m["name"] == JOINTS
        assert len(m["position"]) == len(m["velocity"]) == len(m["effort"]) == 7
        # what the SSC logged within 50 ms of it (both read the measured joints)
        near = np.abs(logged_t - m["stamp_ns"]) <= 50_000_000
        assert near.any(), "a message stamped outside the session"
        gap = np.abs(logged_q[near] - np.asarray(m["position"])).max(axis=1).min()
        assert gap < 0.01, (gap, m)
    assert summary["result"] == "ok" and summary["inserted"] is True, summary.get("reason")

"""A short real session logged, read back and inspected; ``top`` on it while it runs."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.conftest import descendants
from tests.helpers import attach_running, load_json, read_session_id, run_cli, start_cli

SHORT = "tasks/self_calibration_short.yaml"
ROBOTS = ("r1", "r2")


@pytest.fixture(scope="module")
def logged(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """One short self-calibration, with ``top --once --json`` taken mid-run."""
    tmp = tmp_path_factory.mktemp("logged")
    run = tmp / "run"
    proc = start_cli(
        "--set", f"session.runs_dir={tmp / 'runs'}", "session", SHORT, "--out", str(run)
    )
    top: dict[str, Any] = {}
    tree: set[int] = set()
    try:
        sid = read_session_id(proc)
        for node in ("esc.r1", "esc.r2"):
            attach_running(sid, node, min_cycle=50).close()
        before = descendants(proc.pid)
        res = run_cli("top", sid, "--once", "--json", timeout=60)
        after = descendants(proc.pid)
        assert res.returncode == 0, res.stderr
        top = json.loads(res.stdout)
        tree = before & after  # the processes that lived all through the look
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    return {"run": run, "top": top, "tree": tree, "sid": sid, "stdout": out}


def test_the_mcap_file_holds_every_cycle_less_the_counted_drops(logged: dict[str, Any]) -> None:
    from mcap.reader import make_reader

    run: Path = logged["run"]
    summary = load_json(run / "summary.json")
    assert summary["result"] == "ok", summary["reason"]
    log = summary["log"]
    assert log["file"] == "session.mcap" and (run / "session.mcap").exists()
    assert not list(run.glob("esc.*.mcap")), "the parts are merged into session.mcap"
    counts: dict[str, int] = {}
    cycles: dict[str, list[int]] = {}
    with open(run / "session.mcap", "rb") as f:
        reader = make_reader(f)
        for _, channel, msg in reader.iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            if channel.topic.endswith("/feedback"):
                # (after the CDR header: the ROS 2 message's first field)
                cycles.setdefault(channel.topic, []).append(
                    int.from_bytes(msg.data[4:12], "little")
                )
    for r in ROBOTS:
        node = f"esc.{r}"
        node_cycles = summary["nodes"][node]["cycles"]
        rec = log["nodes"][node]
        assert rec["complete"] and rec["cycles"] == node_cycles
        expected = node_cycles - rec["dropped"]
        for topic in (
            f"/{r}/feedback",
            f"/{r}/setpoint",
            f"/{r}/control",
            f"/{r}/guard",
            f"/{node}/timing",
        ):
            assert counts[topic] == expected, (topic, counts[topic], node_cycles, rec)
        assert rec["dropped"] <= 0.05 * node_cycles, rec
        seen = np.asarray(cycles[f"/{r}/feedback"])
        assert np.all(np.diff(seen) > 0) and seen[0] >= 1 and seen[-1] <= node_cycles
        assert counts[f"/{node}/segments"] >= 3  # the three calibration segments
    # the run's messages (what messages.log holds) are in the log too
    assert sum(v for k, v in counts.items() if k.endswith("/messages")) >= 1


def test_every_cycle_message_decodes_in_a_ros2_reader(logged: dict[str, Any]) -> None:
    """mcap-ros2-support (no part of redistro) decodes every message of every
    cycle channel from its ros2msg schema: as many as we read, the same values."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from redistro.log.mcapfile import read_log

    path = logged["run"] / "session.mcap"
    ours = read_log(path)
    decoded: dict[str, list[Any]] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, _msg in reader.iter_messages():
            if channel.message_encoding == "cdr":
                assert schema is not None and schema.encoding == "ros2msg", channel.topic
                standard = (
                    "sensor_msgs/msg/JointState",
                    "geometry_msgs/msg/WrenchStamped",
                    "tf2_msgs/msg/TFMessage",  # (the 3D scene: redistro.log.scene)
                    "std_msgs/msg/String",
                    "visualization_msgs/msg/MarkerArray",
                )
                assert schema.name.startswith("redistro/msg/") or schema.name in standard
        f.seek(0)
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        topics = set(ours.arrays)
        for _s, channel, _m, m in reader.iter_decoded_messages(topics=sorted(topics)):
            decoded.setdefault(channel.topic, []).append(m)
    assert set(decoded) == topics and len(topics) >= 10
    # every message of every channel decodes there: the events too
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        every = sum(1 for _ in reader.iter_decoded_messages())
    assert every == sum(ours.counts.values())
    assert sum(len(v) for v in ours.events.values()) >= 3
    for topic, msgs in decoded.items():
        arr = ours.arrays[topic]
        assert len(msgs) == len(arr) == ours.counts[topic], topic
        cycles = np.asarray([m.log_cycle for m in msgs])
        np.testing.assert_array_equal(cycles, arr["log_cycle"], err_msg=topic)
    for r in ROBOTS:
        q = np.asarray([m.q_rad for m in decoded[f"/{r}/feedback"]])
        np.testing.assert_array_equal(q, ours.arrays[f"/{r}/feedback"]["q_rad"])
    # each robot's feedback as the standard messages too: JointState, WrenchStamped
    std: dict[str, list[Any]] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        want = [f"/{r}/{k}" for r in ROBOTS for k in ("joint_states", "wrench")]
        for schema, channel, _m, m in reader.iter_decoded_messages(topics=want):
            assert schema is not None and schema.name in (
                "sensor_msgs/msg/JointState",
                "geometry_msgs/msg/WrenchStamped",
            )
            std.setdefault(channel.topic, []).append(m)
    for r in ROBOTS:
        fb = ours.arrays[f"/{r}/feedback"]
        states, wrenches = std[f"/{r}/joint_states"], std[f"/{r}/wrench"]
        assert len(states) == len(wrenches) == len(fb)
        assert states[0].name[0] == f"{r}_lbr_iiwa_joint_1" and len(states[0].name) == 7
        np.testing.assert_array_equal(np.asarray([m.position for m in states]), fb["q_rad"])
        np.testing.assert_array_equal(
            np.asarray([m.wrench.force.z for m in wrenches]), fb["wrench"][:, 2]
        )


def test_log_plot_writes_the_png_set(logged: dict[str, Any], tmp_path: Path) -> None:
    res = run_cli("log", "plot", str(logged["run"]), "--out", str(tmp_path), timeout=240)
    assert res.returncode == 0, res.stderr
    expected = [
        f"{r}-{what}.png"
        for r in ROBOTS
        for what in (
            "joint-positions",
            "joint-velocities",
            "joint-accelerations",
            "joint-torques",
            "wrench-tool",
            "wrench-world",
            "end-effector",
        )
    ] + ["esc.r1-timing.png", "esc.r2-timing.png"]
    for name in expected:
        data = (tmp_path / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000, name


def test_log_summary_and_export(logged: dict[str, Any], tmp_path: Path) -> None:
    run: Path = logged["run"]
    summary = load_json(run / "summary.json")
    res = run_cli("log", "summary", str(run), "--json")
    assert res.returncode == 0, res.stderr
    rows = json.loads(res.stdout)
    assert rows["task"] == "self_calibration_short" and rows["result"] == "ok"
    assert {n["node"] for n in rows["nodes"]} == {"esc.r1", "esc.r2"}
    assert [n["logged"] for n in rows["nodes"]] == [
        summary["log"]["nodes"][n["node"]]["recorded"] for n in rows["nodes"]
    ]
    names = [s["name"] for s in rows["segments"] if s["robot"] == "r1"]
    assert names == ["clockwise", "counter_clockwise", "final_positioning"]
    res = run_cli("log", "summary", str(run))
    assert res.returncode == 0 and "self_calibration_short" in res.stdout
    res = run_cli("log", "export", str(run), "--csv", str(tmp_path))
    assert res.returncode == 0, res.stderr
    lines = (tmp_path / "r1_feedback.csv").read_text().splitlines()
    header = lines[0].split(",")
    assert header[:2] == ["log_time_ns", "log_cycle"] and "q_rad_7" in header
    node_rec = summary["log"]["nodes"]["esc.r1"]
    assert len(lines) - 1 == node_rec["recorded"]
    assert (tmp_path / "esc.r1_segments.csv").exists()


def test_log_commands_refuse_what_is_not_a_log(tmp_path: Path) -> None:
    res = run_cli("log", "summary", str(tmp_path / "nope"))
    assert res.returncode == 2 and "no such run folder" in res.stderr
    assert res.stderr.count("\n") == 1 and "Traceback" not in res.stderr
    bad = tmp_path / "session.mcap"
    bad.write_bytes(b"not an mcap file")
    res = run_cli("log", "plot", str(bad))
    assert res.returncode == 2 and "not a readable session log" in res.stderr
    assert res.stderr.count("\n") == 1
    # a log of an older redistro: ROS 1 messages
    from mcap.writer import Writer

    old = tmp_path / "old" / "session.mcap"
    old.parent.mkdir()
    with open(old, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="redistro")
        sid = w.register_schema("redistro/r1_feedback", "ros1msg", b"uint64 log_cycle\n")
        cid = w.register_channel("/r1/feedback", "ros1", sid)
        w.add_message(cid, 1, (1).to_bytes(8, "little"), 1)
        w.finish()  # type: ignore[no-untyped-call]
    res = run_cli("log", "summary", str(old.parent))
    assert res.returncode == 2 and "not a log of this redistro" in res.stderr, res.stderr
    assert res.stderr.count("\n") == 1 and "Traceback" not in res.stderr


def test_top_once_json_lists_every_process(logged: dict[str, Any]) -> None:
    doc = logged["top"]
    sessions = [s for s in doc["sessions"] if s["session"] == logged["sid"]]
    assert len(sessions) == 1
    s = sessions[0]
    nodes = {n["node"]: n for n in s["nodes"]}
    assert set(nodes) == {"esc.r1", "esc.r2"}
    listed: set[int] = {o["pid"] for o in s["other_processes"]}
    summary = load_json(logged["run"] / "summary.json")
    for name, n in nodes.items():
        # the scheduling shown is what each worker was granted
        granted = {w["pid"]: w["scheduling"] for w in summary["nodes"][name]["workers"]}
        for p in n["processes"]:
            g = granted[p["pid"]]
            want = {"SCHED_RR": f"rr/{g['priority']}", "nice": f"nice/{g['nice']}"}
            assert p["sched"] == want.get(g["policy"], g["policy"]), (p, g)
    for n in nodes.values():
        assert n["state"] == "routine" and n["cycle"] > 0 and n["estop"] is False
        assert n["measured_hz"] and n["measured_hz"] > 0
        listed.add(n["manager_pid"])
        roles = [p["role"] for p in n["processes"]]
        assert roles == ["acquisition", "calibration", "pid", "sender", "recorder"]
        for p in n["processes"]:
            assert p["pid"] > 0 and p["state"] == "routine"
            assert p["heartbeat_age_cycles"] is not None
            listed.add(p["pid"])
    assert logged["tree"], "no process seen under the session"
    assert logged["tree"] <= listed, logged["tree"] - listed
    whats = sorted(o["what"] for o in s["other_processes"])
    assert whats == ["logwriter", "logwriter", "plant"], whats


def test_a_session_without_a_terminal_prints_plain_progress(logged: dict[str, Any]) -> None:
    out: str = logged["stdout"]
    assert "\x1b[" not in out  # no terminal control codes in a pipe
    assert "session log" in out and "cycles dropped" in out

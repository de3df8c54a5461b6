"""Bad input at the front door: every case ends with one line naming what is
wrong, exit code 2, no traceback, nothing created or started (the CLI, real
processes)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from tests.helpers import ROOT, run_cli

PARK = [0.0, 0.5, 0.0, -1.2, 0.0, 1.0, 0.0]


def _mcap_with_event(path: Path, body: bytes) -> None:
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("redistro/Event", "jsonschema", b"{}")
        cid = w.register_channel("ssc/events", "json", sid)
        w.add_message(cid, 1, body, 1)
        w.finish()


def _corrupt_mcap(path: Path, compressed: bool = True) -> None:
    """A session log of chunks (compressed or not) with one byte flipped
    inside the first chunk's records."""
    from mcap.writer import CompressionType, Writer

    kind = CompressionType.ZSTD if compressed else CompressionType.NONE
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=4096, compression=kind)
        w.start()
        sid = w.register_schema("redistro/Event", "jsonschema", b"{}")
        cid = w.register_channel("/ssc/events", "json", sid)
        for i in range(200):
            w.add_message(cid, i, b'{"event": "tick", "n": %d}' % i, i)
        w.finish()
    data = bytearray(path.read_bytes())
    # inside the first zstd frame, or a digit of a message in the first chunk
    at = data.index(b"\x28\xb5\x2f\xfd") + 40 if compressed else data.index(b'"n": 7}') + 5
    data[at] ^= 0x01
    path.write_bytes(bytes(data))


def _run_with_summary(
    tmp: Path, name: str, summary: str, meta: dict[str, str] | None = None
) -> Path:
    """A run folder: a small session log (with metadata) and a summary.json."""
    from mcap.writer import Writer

    run = tmp / name
    run.mkdir()
    with open(run / "session.mcap", "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("redistro/Event", "jsonschema", b"{}")
        cid = w.register_channel("/ssc/events", "json", sid)
        w.add_message(cid, 1, b'{"event": "segment"}', 1)
        if meta is not None:
            w.add_metadata("redistro.meta", meta)
        w.finish()
    (run / "summary.json").write_text(summary)
    return run


TRY = "tests/data/moves_and_skills.yaml"
CARRY = "tasks/dual_carry_short.yaml"
PEG = "tasks/dual_peg.yaml"


def _swap(task: str, old: bytes, new: bytes, count: int = -1) -> bytes:
    """A task file of the repository with one part replaced (it must be there)."""
    data = (ROOT / task).read_bytes()
    assert old in data, (task, old)
    return data.replace(old, new, count)


def _inputs(tmp: Path) -> dict[str, Path]:
    """The bad files, by name."""
    big = "9" * 5000
    files = {
        "empty": b"",
        "no_duration": b"task: t\nkind: joint_move\nrobots: [r1]\nsegments:\n"
        b"  - name: a\n    q_rad: {r1: [0, 0.5, 0, -1.2, 0, 1, 0]}\n",
        "latin1": b"task: caf\xe9\nkind: joint_move\nrobots: [r1]\n",
        "dup_keys": b"task: t\ntask: u\nkind: self_calibration\nrobots: [r1]\n",
        "alias_bomb": b"a: &a [x, x, x, x, x, x, x, x, x]\n"
        + b"".join(
            f"{n}: &{n} [{', '.join(['*' + p] * 9)}]\n".encode()
            for p, n in zip("abcdefgh", "bcdefghi", strict=True)
        )
        + b"task: *i\n",
        "many_segments": (
            "task: t\nkind: strategy\nrobots: [r1]\nsegments:\n"
            + "".join(
                f"  - {{name: s{i}, duration_s: 1, robot: r1, scheme: joint, "
                f"goal: {{q_rad: {PARK}}}}}\n"
                for i in range(300)
            )
        ).encode(),
        "deep_yaml": b"task: " + b"[" * 100_000 + b"]" * 100_000 + b"\n",
        "a_file": b"x",
        "fast_after_cartesian": (ROOT / "tasks/fault_drill.yaml")
        .read_bytes()
        .replace(
            b"q_rad: [0, 0.5, 0, -1.2, 0, 1.0, 0]\n      move_s: 5",
            b"q_rad: [2.5, 0.5, 0, -1.2, 0, 1.0, 0]\n      move_s: 0.05",
        ),
        "huge_force": (ROOT / "tasks/peg_insertion_short.yaml")
        .read_bytes()
        .replace(b"force_xyz_torque_xyz: [0, 0, -20", b"force_xyz_torque_xyz: [0, 0, -1.0e+6"),
        "moves_and_robot": _swap(
            "tasks/dual_reach.yaml",
            b"  - name: home\n    duration_s: 3.5\n",
            b"  - name: home\n    duration_s: 3.5\n    robot: r2\n",
        ),
        "moves_two_clocks": _swap(
            "tasks/dual_reach.yaml",
            b"0, 1.0, 0]\n          move_s: 2.5\n      r2:\n        scheme: position",
            b"0, 1.0, 0]\n          move_s: 2\n      r2:\n        scheme: position",
        ),
        "moves_stranger": _swap("tasks/dual_reach.yaml", b"      r1:\n", b"      r9:\n"),
        "push_position": _swap(TRY, b"skill: guarded_move", b"skill: push"),
        "guarded_no_contact": _swap(TRY, b"contact_n: 2", b"pose_within_m: 0.001"),
        "unknown_frame": _swap(TRY, b"relative_to: hole", b"relative_to: crate"),
        "carry_no_object": _swap(
            CARRY, b"carry: {object: bar, move_xyz_m: [0, 0, 0.1], ", b"carry: {"
        ),
        "carry_one_hand": _swap(
            CARRY, b"      r2: {skill: carry, scheme: position, goal: {move_s: 1.5}}\n", b"", 1
        ),
        "stiff_wrist": _swap(PEG, b"1500, 40, 40, 30]}\n", b"1500, 400, 40, 30]}\n"),
        "joint_stiffness": _swap(
            PEG, b"scheme: position\n    duration_s: 9\n", b"scheme: joint\n    duration_s: 9\n"
        ),
        "until_alone": _swap(TRY, b"skill: hold\n", b"skill: hold\n    until: any\n"),
        "hold_stiffness": _swap(
            TRY,
            b"skill: hold\n",
            b"skill: hold\n    goal: {stiffness_xyz_rot_xyz: [9, 9, 9, 9, 9, 9]}\n",
        ),
        "hold_with_goal": _swap(
            TRY, b"skill: hold\n", b"skill: hold\n    goal: {q_rad: [0, 0, 0, 0, 0, 0, 0]}\n"
        ),
        "big_int": f"task: t\nkind: joint_move\nrobots: [r1]\nsegments:\n"
        f"  - {{name: a, duration_s: {big}, q_rad: {{r1: {PARK}}}}}\n".encode(),
        "big_float_int": f"task: t\nkind: joint_move\nrobots: [r1]\nsegments:\n"
        f"  - {{name: a, duration_s: {10**25}, q_rad: {{r1: {PARK}}}}}\n".encode(),
    }
    out = {}
    for name, body in files.items():
        out[name] = tmp / f"{name}.yaml"
        out[name].write_bytes(body)
    fifo = tmp / "fifo.yaml"
    os.mkfifo(fifo)
    out["fifo"] = fifo
    out["old_run"] = tmp / "old_run"
    out["old_run"].mkdir()
    (out["old_run"] / "messages.log").write_text("an earlier run's\n")
    (tmp / "list_event").mkdir()
    _mcap_with_event(tmp / "list_event" / "session.mcap", b"[1, 2, 3]")
    (tmp / "deep_event").mkdir()
    _mcap_with_event(tmp / "deep_event" / "session.mcap", b"[" * 100_000 + b"]" * 100_000)
    out["list_event"] = tmp / "list_event"
    out["deep_event"] = tmp / "deep_event"
    (tmp / "corrupt").mkdir()
    _corrupt_mcap(tmp / "corrupt" / "session.mcap")
    out["corrupt"] = tmp / "corrupt"
    (tmp / "corrupt_plain").mkdir()
    _corrupt_mcap(tmp / "corrupt_plain" / "session.mcap", compressed=False)
    out["corrupt_plain"] = tmp / "corrupt_plain"
    out["typed_summary"] = _run_with_summary(
        tmp, "typed_summary", '{"task": "t", "nodes": {"ssc": {"cycles": "many"}}}'
    )
    out["list_segments"] = _run_with_summary(tmp, "list_segments", '{"segments": {"a": 1}}')
    out["typed_meta"] = _run_with_summary(tmp, "typed_meta", "{}", {"physics_hz": '"fast"'})
    out["short_base"] = _run_with_summary(
        tmp, "short_base", "{}", {"robots": '{"r1": {"base_xyz_m": [0, 1]}}'}
    )
    logged = '{"result": "ok", "log": {"digest": "00"}}'
    for name, replay in (("realtime_run", None), ("corrupt_replay", "{not json"),
                         ("replay_no_config", '{"clock": "lockstep"}')):  # fmt: skip
        run = tmp / name
        run.mkdir()
        (run / "summary.json").write_text(logged)
        if replay is not None:
            (run / "replay.json").write_text(replay)
        out[name] = run
    return out


CASES = [
    ("empty task", ["session", "{empty}"], "empty.yaml: task: missing (expected a string)"),
    (
        "segment without duration_s",
        ["session", "{no_duration}"],
        "segments[0].duration_s: missing (expected a number)",
    ),
    ("task not UTF-8", ["session", "{latin1}"], "latin1.yaml: not UTF-8 text (byte 9"),
    ("config /dev/zero", ["--config", "/dev/zero", "session", "tasks/park.yaml"], "not a regular"),
    ("task is a FIFO", ["session", "{fifo}"], "fifo.yaml: cannot read task (not a regular file)"),
    (
        "robot io file is a FIFO",
        ["--set", "robots.r1.io={fifo}", "session", "tasks/park.yaml"],
        "fifo.yaml: cannot read config (not a regular file)",
    ),
    ("--out an existing file", ["session", "tasks/park.yaml", "--out", "{a_file}"], "not a folder"),
    (
        "--out unwritable",
        ["session", "tasks/park.yaml", "--out", "/proc/redistro/run"],
        "--out /proc/redistro/run: /proc is on a proc pseudo-filesystem",
    ),
    ("duplicate keys", ["session", "{dup_keys}"], "dup_keys.yaml:2: invalid YAML (key 'task'"),
    ("alias bomb", ["session", "{alias_bomb}"], "invalid YAML (anchors (&name) are not allowed)"),
    ("deep YAML", ["session", "{deep_yaml}"], "invalid YAML (nested deeper than 64 levels)"),
    ("300 segments", ["session", "{many_segments}"], "segments: at most 254 segments"),
    (
        "typo in a dict key",
        ["--set", "scheduling.priorities.acquistion=30", "session", "tasks/park.yaml"],
        "scheduling.priorities.acquistion: unknown key (known: acquisition,",
    ),
    (
        "negative seed",
        ["--set", "plant.seed=-1", "session", "tasks/park.yaml"],
        "plant.seed: expected an integer >= 0",
    ),
    (
        "malformed peer",
        ["--set", "ddm.peers=[10.0.0.2]", "session", "tasks/park.yaml"],
        "ddm.peers[0]: expected host:port",
    ),
    (
        "robot name outside the IPC alphabet",
        ["--set", "robots.r1/x={}", "session", "tasks/park.yaml"],
        "a robot name is 1-32 letters, digits, _ or -, got 'r1/x'",
    ),
    ("top --interval nan", ["top", "--interval", "nan"], "--interval: expected a number"),
    ("bridge to no session", ["bridge", "20990101T000000-000000"], "no running session"),
    (
        "bridge --listen not an endpoint",
        ["bridge", "--listen", "http://x:1"],
        "bridge: --listen[0]: ",
    ),
    (
        "ros2.listen not an endpoint",
        ["--set", "ros2.listen=[tcp/127.0.0.1:0]", "check", "tasks/park.yaml"],
        "ros2.listen[0]",
    ),
    (
        "ros2.rate_hz over 100",
        ["--set", "ros2.rate_hz=500", "check", "tasks/park.yaml"],
        "ros2.rate_hz",
    ),
    (
        "log export --csv into a file",
        ["log", "export", "--csv", "{a_file}", "{list_event}"],
        "--csv",
    ),
    ("an MCAP event that is a list", ["log", "summary", "{list_event}"], "is not a JSON object"),
    ("an MCAP event nested deep", ["log", "summary", "{deep_event}"], "nested deeper than 64"),
    # numbers too big to convert, in files and in --set
    ("an integer of 5000 digits", ["session", "{big_int}"], "an integer of 5000 characters"),
    ("an integer of 26 digits", ["session", "{big_float_int}"], "duration_s: expected a number"),
    (
        "--set an integer of 5000 digits",
        ["--set", "esc.rate_hz=" + "9" * 5000, "session", "tasks/park.yaml"],
        "--set esc.rate_hz: value is not valid YAML (an integer of 5000 characters",
    ),
    (
        "--set an integer beyond 2^63",
        ["--set", f"plant.seed={2**64}", "session", "tasks/park.yaml"],
        "plant.seed: expected an integer within +-2^63",
    ),
    # --set goes through the files' loader
    (
        "--set nested 3000 deep",
        ["--set", "esc.rate_hz=" + "[" * 3000, "session", "tasks/park.yaml"],
        "--set esc.rate_hz: value is not valid YAML (nested deeper than 64 levels)",
    ),
    (
        "--set an alias bomb",
        ["--set", "esc.cpus=[&a [1, 1, 1, 1], [*a, *a, *a, *a]]", "session", "tasks/park.yaml"],
        "anchors (&name) are not allowed",
    ),
    (
        "--set a value of 70 000 characters",
        ["--set", "session.runs_dir=" + "x" * 70_000, "session", "tasks/park.yaml"],
        "--set session.runs_dir: a value of 70000 characters (at most 65536)",
    ),
    (
        "a peer's port in unicode digits",
        ["--set", "ddm.peers=[127.0.0.1:\uff14\uff10\uff10\uff10]", "session", "tasks/park.yaml"],
        "ddm.peers[0]: expected host:port",
    ),
    # the log tools' other inputs
    ("summary.json with a wrong type", ["log", "summary", "{typed_summary}"], "nodes.ssc.cycles"),
    (
        "summary.json segments a mapping",
        ["log", "summary", "{list_segments}"],
        "segments: expected a list",
    ),
    ("metadata of the wrong type", ["log", "plot", "{typed_meta}"], "redistro.meta: physics_hz"),
    ("a base of two numbers", ["log", "plot", "{short_base}"], "robots.r1.base_xyz_m"),
    ("a flipped byte in a chunk", ["log", "summary", "{corrupt}"], "not a readable session log"),
    (
        "a flipped byte in an uncompressed chunk",
        ["log", "summary", "{corrupt_plain}"],
        "not a readable session log",
    ),
    (
        "log diff of a corrupt log",
        ["log", "diff", "{list_event}", "{corrupt}"],
        "not a readable session log",
    ),
    ("log diff with no second run", ["log", "diff", "{list_event}"], "the following arguments"),
    ("log diff with a missing run", ["log", "diff", "{list_event}", "{empty}"], "not a run folder"),
    # output targets that can never be written
    (
        "--csv into /sys",
        ["log", "export", "--csv", "/sys/redistro", "{list_event}"],
        "/sys is on a sysfs",
    ),
    (
        "--json into /proc",
        ["bench", "kernels", "--json", "/proc/redistro.json"],
        "--json /proc/redistro.json: /proc is on a proc pseudo-filesystem",
    ),
    # motions the guard would have to stop
    (
        "a joint move after a Cartesian one, too fast",
        ["check", "{fast_after_cartesian}"],
        "segments[1].goal.q_rad: joint 1 would move",
    ),
    ("a goal force of 1e6 N", ["check", "{huge_force}"], "a goal force of 1e+06 N, over"),
    (
        "a segment of moves that names a robot too",
        ["session", "{moves_and_robot}"],
        "segments[1].robot: a segment with moves gives it per robot (moves.<robot>)",
    ),
    (
        "a segment's moves on two clocks",
        ["session", "{moves_two_clocks}"],
        "segments[0].moves: the robots of one segment move on one clock: give them the same "
        "goal.move_s (got r1 2 s, r2 2.5 s)",
    ),
    ("a move for a robot not in the task", ["check", "{moves_stranger}"], "moves.r9: 'r9' is not"),
    (
        "a skill under a scheme it does not run under",
        ["check", "{push_position}"],
        "segments[1].moves.r2.scheme: the skill push runs under force, not position",
    ),
    (
        "a guarded move without its contact force",
        ["check", "{guarded_no_contact}"],
        "segments[1].moves.r2.end.contact_n: a guarded_move ends at contact: give the force",
    ),
    ("a hold with a goal", ["check", "{hold_with_goal}"], "segments[2].goal: a hold has no goal"),
    (
        "a hold with a stiffness",
        ["check", "{hold_stiffness}"],
        "segments[2].goal: a hold has no goal",
    ),
    (
        "until on a segment of one robot",
        ["check", "{until_alone}"],
        "segments[2].until: for a segment of several robots (moves)",
    ),
    (
        "a goal relative to an object the work-cell does not have",
        ["check", "{unknown_frame}"],
        "segments[0].moves.r2.goal.relative_to: no frame named 'crate' (known: world, hole)",
    ),
    (
        "a bench dual offset beyond its range",
        ["bench", "dual", "--offset-radius-mm", "11"],
        "--offset-radius-mm: expected 0 to 10, got 11",
    ),
    (
        "a bench dual of a task that carries nothing",
        [
            "--config",
            "config/dual_arm.yaml",
            "bench",
            "dual",
            "--task-file",
            "tasks/grasp_lift.yaml",
        ],
        "bench dual --task carry needs a task that carries one object",
    ),
    (
        "a bench dual of a peg insertion that inserts into no held object",
        ["bench", "dual", "--task", "peg", "--task-file", "tasks/dual_reach.yaml"],
        "bench dual --task peg needs a task that inserts into one held object's hole",
    ),
    (
        "a carry that names no object",
        ["--config", "config/dual_arm.yaml", "check", "{carry_no_object}"],
        "segments[2].carry.object: name the object the hands carry",
    ),
    (
        "a carry of one hand",
        ["--config", "config/dual_arm.yaml", "check", "{carry_one_hand}"],
        "segments[2].moves: a carry is two hands' moves, both skill: carry",
    ),
    (
        "a held block's wrist stiffer than the loop allows",
        ["--config", "config/dual_peg.yaml", "check", "{stiff_wrist}"],
        "segments[4].goal.stiffness_xyz_rot_xyz: 400 N m/rad is over 100",
    ),
    (
        "a Cartesian stiffness on a joint move",
        ["--config", "config/dual_peg.yaml", "check", "{joint_stiffness}"],
        "segments[4].goal.stiffness_xyz_rot_xyz: a joint move has no Cartesian one",
    ),
    (
        "the plant's truth of an object the work-cell does not have",
        ["--set", "plant.objects={crate: {yaw_deg: 1}}", "session", "tasks/park.yaml"],
        "plant.objects.crate: no object named 'crate' in workcell.objects",
    ),
    (
        "a run folder that holds an earlier run",
        ["session", "tasks/park.yaml", "--out", "{old_run}"],
        "holds a run already (messages.log): give a new or empty folder",
    ),
    # what check refuses that would fail only once running
    (
        "a zenoh listen endpoint without a port",
        ["--set", "ddm.zenoh.listen=[tcp/127.0.0.1]", "session", "tasks/park.yaml"],
        "ddm.zenoh.listen[0]: expected tcp|udp|tls|quic/host:port",
    ),
    (
        "a zenoh listen endpoint on port 0",
        ["--set", "ddm.zenoh.listen=[tcp/127.0.0.1:0]", "session", "tasks/park.yaml"],
        "ddm.zenoh.listen[0]: expected a port 1-65535",
    ),
    (
        "a tls endpoint without certificates",
        [
            "--set",
            "ddm.transport=zenoh",
            "--set",
            "ddm.zenoh.listen=[tls/127.0.0.1:7447]",
            "session",
            "tasks/park.yaml",
        ],
        "ddm.zenoh.tls.ca_file: a tls/ endpoint needs it",
    ),
    (
        "a zenoh group that is a wildcard",
        ["--set", "ddm.zenoh.group=lab/**", "session", "tasks/park.yaml"],
        "ddm.zenoh.group: expected 1-64 letters, digits, _ or - (no key-expression wildcards)",
    ),
    (
        "a hole the plant cannot place",
        ["--set", "workcell.hole.xyz_m=[0.55, -0.35, 0.04]", "session", "tasks/park.yaml"],
        "leaves no room for the table",
    ),
    (
        "both bases at one point",
        ["--set", "robots.r1.base_xyz_m=[0, -0.45, 0]", "session", "tasks/park.yaml"],
        "--set: robots.r2.base_xyz_m: 0.000 m from r1's base",
    ),
    (
        "a base in the table",
        ["--set", "robots.r1.base_xyz_m=[0.5, 0.2, 0]", "session", "tasks/park.yaml"],
        "stands in the table",
    ),
    (
        "runs folder under /proc",
        ["--set", "session.runs_dir=/proc/redistro-runs", "check", "tasks/park.yaml"],
        "session.runs_dir /proc/redistro-runs: /proc is on a proc pseudo-filesystem",
    ),
    ("view of no folder", ["view", "{realtime_run}/none"], ": no such run folder"),
    ("view of nothing", ["view"], "view: give a run folder, or --live [SESSION]"),
    ("live view of no session", ["view", "--live", "nosuch"], "no running session nosuch"),
    ("view of a run without its log", ["view", "{realtime_run}"], "no session log"),
    ("view on port 0", ["view", "{realtime_run}", "--port", "0"], "--port 0: expected 1-65535"),
    (
        "view on a host name",
        ["view", "{realtime_run}", "--bind", "example.org"],
        "--bind example.org: expected an IP address of this host",
    ),
    (
        "view on another host's address",
        ["view", "{realtime_run}", "--bind", "192.0.2.1"],
        "--bind 192.0.2.1 --port 8080: Cannot assign requested address",
    ),
    ("ctl of no session", ["ctl", "nosuch", "pause"], "ctl: no running session nosuch"),
    ("ctl of an unknown order", ["ctl", "x", "dance"], "argument order: invalid choice: 'dance'"),
    ("ctl pause of a robot", ["ctl", "x", "pause", "r1"], "ctl pause: takes no robot (got r1)"),
    ("ctl jog of no robot", ["ctl", "x", "jog"], "ctl jog: name the robot"),
    ("ctl jog without a step", ["ctl", "x", "jog", "r1"], "ctl jog: give a step"),
    (
        "ctl jog too far",
        ["ctl", "x", "jog", "r2", "--mm", "4", "4", "0"],
        "ctl jog: --mm moves 5.66 mm; at most 5",
    ),
    (
        "ctl jog turned too far",
        ["ctl", "x", "jog", "r2", "--deg", "0", "0", "-3"],
        "ctl jog: --deg turns 3°; at most 2",
    ),
    ("ctl jog by nan", ["ctl", "x", "jog", "r2", "--mm", "nan", "0", "0"], "finite numbers"),
    ("ctl with no time", ["ctl", "x", "stop", "--timeout", "0"], "--timeout: expected 0.1..600 s"),
    ("replay of no folder", ["replay", "{realtime_run}/none"], ": no such run folder"),
    ("replay of a file", ["replay", "{a_file}"], ": no such run folder"),
    (
        "replay of a real-time run",
        ["replay", "{realtime_run}"],
        ": not a lockstep run (no replay.json)",
    ),
    ("replay of a corrupt replay file", ["replay", "{corrupt_replay}"], "not readable JSON"),
    ("replay of a replay file without config", ["replay", "{replay_no_config}"], "no config"),
    (
        "a lockstep session at two rates",
        [
            "--set",
            "esc.rate_hz=500",
            "session",
            "tasks/peg_insertion_short.yaml",
            "--clock",
            "lockstep",
        ],
        "session.clock lockstep: esc.rate_hz (500) and ssc.rate_hz (200) must be equal",
    ),
    (
        "an unknown clock",
        ["session", "tasks/park.yaml", "--clock", "fast"],
        "argument --clock: invalid choice: 'fast'",
    ),
    (
        "absurd sensor noise",
        ["--set", "plant.ft_noise_n=1e6", "session", "tasks/park.yaml"],
        "plant.ft_noise_n: expected a number >= 0 and <= 10",
    ),
]


@pytest.mark.parametrize(("name", "args", "expect"), CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_exit_2_nothing_left(
    tmp_path: Path, name: str, args: list[str], expect: str
) -> None:
    files = _inputs(tmp_path)
    for key, path in files.items():
        args = [a.replace("{" + key + "}", str(path)) for a in args]
    shm_before = {e for e in os.listdir("/dev/shm") if "redistro" in e}
    listing = sorted(p.name for p in tmp_path.iterdir())
    runs = tmp_path / "runs"
    if "session.runs_dir=/proc/redistro-runs" not in args:
        args = ["--set", f"session.runs_dir={runs}", *args]
    done = run_cli(*args, timeout=60)
    assert done.returncode == 2, (name, done.stdout[-2000:], done.stderr[-2000:])
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("redistro: error: "), done.stderr[-2000:]
    assert len(lines[0]) <= 400, lines[0]
    assert expect in lines[0], lines[0]
    assert "Traceback" not in done.stderr and done.stdout == ""
    assert {e for e in os.listdir("/dev/shm") if "redistro" in e} == shm_before
    assert sorted(p.name for p in tmp_path.iterdir()) == listing
    assert not Path("/proc/redistro").exists()


def test_an_error_line_is_400_characters_prefix_included() -> None:
    done = run_cli("--set", "k" * 1000 + "=1", "check", "tasks/park.yaml", timeout=60)
    assert done.returncode == 2
    line = done.stderr.strip()
    assert line.startswith("redistro: error: --set kkk") and len(line) <= 400, line


def test_names_with_markup_are_printed_as_they_are(tmp_path: Path) -> None:
    """A task and a segment named like rich markup: log summary prints them."""
    summary = {
        "task": "[/x] peg [bold]",
        "kind": "strategy",
        "result": "ok",
        "segments": [{"name": "[/]", "robot": "r2", "scheme": "force", "duration_s": 1.0}],
    }
    import json

    run = _run_with_summary(tmp_path, "markup", json.dumps(summary))
    done = run_cli("log", "summary", str(run), timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "[/x] peg [bold]" in done.stdout and "[/]" in done.stdout, done.stdout


def test_a_positions_file_nested_deep_is_corrupt_not_a_crash(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    (runs / "positions").mkdir(parents=True)
    (runs / "positions" / "r1.json").write_text("[" * 10_000 + "]" * 10_000)
    task = tmp_path / "move.yaml"
    task.write_text(
        f"task: t\nkind: joint_move\nrobots: [r1]\nsegments:\n"
        f"  - {{name: a, duration_s: 5, q_rad: {{r1: {PARK}}}}}\n"
    )
    done = run_cli("--set", f"session.runs_dir={runs}", "session", str(task), timeout=60)
    assert done.returncode == 2, done.stderr[-2000:]
    line = done.stderr.strip()
    assert "positions unknown (corrupt): nested deeper than 64 levels" in line, line
    assert sorted(p.name for p in runs.iterdir()) == ["positions"]


def test_the_shipped_inputs_pass_the_front_door() -> None:
    """Every shipped task and config loads (what the fuzzing mutates)."""
    from redistro.config import load_config
    from redistro.config.hardware import load_hardware
    from redistro.config.task import load_task
    from redistro.errors import ConfigError

    cfg = load_config(ROOT / "config/redistro.yaml")
    load_hardware(cfg, ROOT / "config")
    dual = load_config(ROOT / "config/dual_arm.yaml")  # (the two-arm tasks' objects)
    load_hardware(dual, ROOT / "config")
    peg = load_config(ROOT / "config/dual_peg.yaml")
    load_hardware(peg, ROOT / "config")
    two_arm = {
        "dual_carry.yaml": dual, "dual_carry_short.yaml": dual, "grasp_lift.yaml": dual,
        "dual_peg.yaml": peg, "dual_peg_short.yaml": peg,
    }  # fmt: skip
    for task in sorted((ROOT / "tasks").glob("*.yaml")):
        assert load_task(task, two_arm.get(task.name, cfg)).segments is not None
        if task.name in two_arm:
            with pytest.raises(ConfigError, match="no frame named"):  # (their objects)
                load_task(task, cfg)
    assert stat.S_ISREG(os.stat(ROOT / "config/redistro.yaml").st_mode)


OTHER = 12345  # a uid that is not ours


@pytest.mark.skipif(os.getuid() != 0, reason="makes a folder of another user (root only)")
def test_an_out_folder_of_another_user_with_planted_links_is_refused(tmp_path: Path) -> None:
    """Another user's folder holding links to our private files, named as a
    run folder's files: the session refuses the folder before anything, and
    our files stay as they were."""
    victim = tmp_path / "victim"
    victim.write_text("secret\n")
    victim.chmod(0o600)
    trap = tmp_path / "trap"
    trap.mkdir(mode=0o777)
    os.chmod(trap, 0o777)
    for name in ("summary.json.tmp", "summary.json", "messages.log", "plant.json"):
        (trap / name).symlink_to(victim)
    os.chown(trap, OTHER, OTHER)
    runs = tmp_path / "runs"
    done = run_cli("--set", f"session.runs_dir={runs}", "session", "tasks/park.yaml", "--out",
                   str(trap), timeout=60)  # fmt: skip
    assert done.returncode == 2, done.stderr[-2000:]
    assert f"is owned by uid {OTHER}, not by you (0) or root" in done.stderr, done.stderr
    assert victim.read_text() == "secret\n"
    assert sorted(p.name for p in trap.iterdir()) == sorted(
        ["summary.json.tmp", "summary.json", "messages.log", "plant.json"]
    )
    # a folder of ours that anyone may write into is refused the same way
    open_dir = tmp_path / "open"
    open_dir.mkdir()
    os.chmod(open_dir, 0o777)
    done = run_cli("session", "tasks/park.yaml", "--out", str(open_dir), timeout=60)
    assert done.returncode == 2 and "is writable by others (mode 0777)" in done.stderr


def test_an_export_replaces_a_planted_link_never_its_target(tmp_path: Path) -> None:
    """A CSV name planted as a link to a private file: the export writes its
    own file in the link's place; the file it pointed to is untouched."""
    import json

    victim = tmp_path / "victim"
    victim.write_text("secret\n")
    victim.chmod(0o600)
    run = _run_with_summary(tmp_path, "run", json.dumps({"task": "t"}))
    out = tmp_path / "csv"
    out.mkdir()
    (out / "ssc_events.csv").symlink_to(victim)
    done = run_cli("log", "export", "--csv", str(out), str(run), timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    assert victim.read_text() == "secret\n"
    csv_file = out / "ssc_events.csv"
    assert not csv_file.is_symlink() and csv_file.read_text().startswith("log_time_ns")
    assert sorted(p.name for p in out.iterdir()) == ["ssc_events.csv"]  # no temporary left

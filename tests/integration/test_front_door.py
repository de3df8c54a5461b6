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


def _inputs(tmp: Path) -> dict[str, Path]:
    """The bad files, by name."""
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
    }
    out = {}
    for name, body in files.items():
        out[name] = tmp / f"{name}.yaml"
        out[name].write_bytes(body)
    fifo = tmp / "fifo.yaml"
    os.mkfifo(fifo)
    out["fifo"] = fifo
    (tmp / "list_event").mkdir()
    _mcap_with_event(tmp / "list_event" / "session.mcap", b"[1, 2, 3]")
    (tmp / "deep_event").mkdir()
    _mcap_with_event(tmp / "deep_event" / "session.mcap", b"[" * 100_000 + b"]" * 100_000)
    out["list_event"] = tmp / "list_event"
    out["deep_event"] = tmp / "deep_event"
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
        "--out /proc/redistro/run: cannot be created",
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
    (
        "log export --csv into a file",
        ["log", "export", "--csv", "{a_file}", "{list_event}"],
        "--csv",
    ),
    ("an MCAP event that is a list", ["log", "summary", "{list_event}"], "is not a JSON object"),
    ("an MCAP event nested deep", ["log", "summary", "{deep_event}"], "nested deeper than 64"),
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
    done = run_cli("--set", f"session.runs_dir={runs}", *args, timeout=60)
    assert done.returncode == 2, (name, done.stdout[-2000:], done.stderr[-2000:])
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("redistro: error: "), done.stderr[-2000:]
    assert len(lines[0]) < 400, lines[0]
    assert expect in lines[0], lines[0]
    assert "Traceback" not in done.stderr and done.stdout == ""
    assert {e for e in os.listdir("/dev/shm") if "redistro" in e} == shm_before
    assert sorted(p.name for p in tmp_path.iterdir()) == listing
    assert not Path("/proc/redistro").exists()


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

    cfg = load_config(ROOT / "config/redistro.yaml")
    load_hardware(cfg, ROOT / "config")
    for task in sorted((ROOT / "tasks").glob("*.yaml")):
        assert load_task(task, cfg).segments is not None
    assert stat.S_ISREG(os.stat(ROOT / "config/redistro.yaml").st_mode)

"""Sessions: reaping what a killed session left, and bad input rejected cleanly."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from redistro.ipc import names
from tests.helpers import (
    attach_running,
    bench_cycle,
    load_json,
    pid_gone,
    read_session_id,
    run_cli,
    session_entries,
    start_cli,
    wait_for,
)


def _kill_whole_session(tmp_path: Path) -> str:
    """Start a session in its own process group and SIGKILL all of it."""
    proc = start_cli(
        *bench_cycle("200", "2", "60", str(tmp_path / "x.json")),
        new_session=True,
    )
    sid = read_session_id(proc)
    ld = attach_running(sid, "bench", min_cycle=5)
    pids = [int(ld.block("manager").read()["pid"])]
    pids += [int(ld.block("proc", j).read()["pid"]) for j in range(2)]
    ld.close()
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)
    proc.communicate()
    wait_for(lambda: all(pid_gone(p) for p in pids), 10, "the killed session's processes")
    left = session_entries(sid)
    assert any(e.endswith(".localdata") for e in left), left
    assert any(e.startswith("sem.") for e in left), left
    return sid


def test_redistro_clean_reaps_a_killed_session(tmp_path: Path) -> None:
    sid = _kill_whole_session(tmp_path)
    done = run_cli("clean")
    assert done.returncode == 0, done.stderr
    assert f"removed /redistro.{sid}.bench.localdata" in done.stdout
    assert f"removed /redistro.{sid}.bench.ready" in done.stdout
    assert session_entries(sid) == []
    assert not (names.runtime_dir() / sid).exists()


def test_the_next_start_reaps_a_killed_session(tmp_path: Path) -> None:
    sid = _kill_whole_session(tmp_path)
    out = tmp_path / "next.json"
    done = run_cli(
        *bench_cycle("200", "1", "0.2", str(out)),
    )
    assert done.returncode == 0, done.stderr
    assert f"reaped /redistro.{sid}.bench.localdata" in done.stderr
    assert session_entries(sid) == []
    assert load_json(out)["result"] == "ok"


def test_clean_keeps_live_sessions(tmp_path: Path) -> None:
    proc = start_cli(
        *bench_cycle("200", "1", "60", str(tmp_path / "x.json")),
    )
    try:
        sid = read_session_id(proc)
        attach_running(sid, "bench", min_cycle=2).close()
        done = run_cli("clean")
        assert done.returncode == 0
        assert sid not in done.stdout.replace(f"kept 1 live session(s): {sid}", "")
        assert session_entries(sid)  # still there: the session is alive
    finally:
        proc.terminate()
        proc.communicate(timeout=30)


BAD_INPUTS = [
    # (config file text or None, extra args, text the one-line error must contain)
    ("bench:\n  rate_hz: 1000\n  nope: 1\n", [], "bench.nope: unknown key"),
    ("bench:\n  rate_hz: fast\n", [], "bench.rate_hz: expected a number > 0"),
    ("bench:\n  rate_hz: -5\n", [], "bench.rate_hz: expected a number > 0"),
    ("scheduling:\n  policy: fifo\n", [], "scheduling.policy: expected one of"),
    ("bench: [1, 2\n", [], "invalid YAML"),
    (None, ["--set", "bench.rate_hz=-1"], "--set: bench.rate_hz: expected a number > 0"),
    (None, ["--set", "bench.heartbeat_limit_cycles=1.5"], "expected an integer"),
    (None, ["--set", "bench.bogus=1"], "--set bench.bogus: no such config key"),
    (None, ["--set", "novalue"], "expected dotted.key=value"),
    (None, ["--rate", "-3"], "--rate: expected a number in (0, 10000]"),
    (None, ["--workers", "many"], "argument --workers: invalid int value"),
    (None, ["--stages", "2,2"], "--stages 2,2: sizes must be >= 1 and add up to --workers 5"),
]


@pytest.mark.parametrize(("config", "extra", "expect"), BAD_INPUTS)
def test_bad_input_is_one_line_exit_2_nothing_created(
    tmp_path: Path, config: str | None, extra: list[str], expect: str
) -> None:
    args = []
    if config is not None:
        path = tmp_path / "bad.yaml"
        path.write_text(config)
        args = ["--config", str(path)]
    runtime = names.runtime_dir()
    before = set(os.listdir(runtime)) if runtime.exists() else set()
    shm_before = {e for e in os.listdir("/dev/shm") if "redistro" in e}
    runs = tmp_path / "runs"
    done = run_cli(
        *args,
        "--set",
        f"session.runs_dir={runs}",
        "bench",
        "cycle",
        "--seconds",
        "1",
        "--no-baseline",
        *extra,
    )
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith("redistro: error: ")
    assert expect in lines[0], lines[0]
    if config is not None:
        assert str(path) in lines[0]  # the file is named
    assert "Traceback" not in done.stderr
    assert done.stdout == ""
    assert {e for e in os.listdir("/dev/shm") if "redistro" in e} == shm_before
    assert (set(os.listdir(runtime)) if runtime.exists() else set()) == before
    assert not runs.exists()


PLANT_BAD_INPUTS = [
    (["--set", "plant.backplane=usb"], "plant.backplane: expected one of 'shm', 'can'"),
    (
        ["--set", "workcell.hole.clearance_m=0.005"],
        "workcell.hole.clearance_m: expected a number > 0",
    ),
    (["--set", "robots.r1.io=nowhere/r1.io.yaml"], "nowhere/r1.io.yaml: cannot read config"),
    (
        ["--set", "robots.r2.initial_q_rad=[0, 1]"],
        "robots.r2.initial_q_rad: expected a list of exactly 7",
    ),
    (["--set", "plant.ft_bias.r9=[0, 0, 0, 0, 0, 0]"], "plant.ft_bias.r9: no robot named 'r9'"),
    (["--backplane", "usb"], "argument --backplane: invalid choice"),
]


@pytest.mark.parametrize(("extra", "expect"), PLANT_BAD_INPUTS)
def test_bad_plant_input_is_one_line_exit_2_nothing_started(
    tmp_path: Path, extra: list[str], expect: str
) -> None:
    runtime = names.runtime_dir()
    before = set(os.listdir(runtime)) if runtime.exists() else set()
    shm_before = {e for e in os.listdir("/dev/shm") if "redistro" in e}
    done = run_cli(
        "--set", f"session.runs_dir={tmp_path / 'runs'}", "bench", "plant", "--seconds", "1", *extra
    )
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("redistro: error: "), done.stderr
    assert expect in lines[0], lines[0]
    assert {e for e in os.listdir("/dev/shm") if "redistro" in e} == shm_before
    assert (set(os.listdir(runtime)) if runtime.exists() else set()) == before
    assert not (tmp_path / "runs").exists()

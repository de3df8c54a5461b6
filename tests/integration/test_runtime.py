"""The Manager/Worker runtime with real processes, real posix_ipc, real signals."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.helpers import (
    attach_running,
    bench_cycle,
    load_json,
    pid_gone,
    read_session_id,
    run_cli,
    start_cli,
    wait_for,
)


def test_five_workers_at_1khz_keep_every_heartbeat(tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    done = run_cli(
        *bench_cycle("1000", "5", "4", str(out)),
    )
    assert done.returncode == 0, done.stderr
    r = load_json(out)
    assert r["result"] == "ok", r["reason"]
    assert r["cycles"] == 4000
    node = r["node_result"]
    assert len(node["workers"]) == 5
    for w in node["workers"]:
        # every cycle was either run, or skipped and counted (overrun, stage timeout)
        assert w["cycles"] + w["stage_timeouts"] + w["skipped"] == 4000, w
        assert w["overruns"] <= w["skipped"]
        assert w["exit"] == "exited with code 0"
    # No heartbeat reached the limit: that would have ended the run abnormal
    # (asserted above). Late and missed ones are counted, not bounded: on this
    # machine a host stall of one vCPU can hold a worker back ~20 ms.
    assert r["lateness_us"]["p50"] > 0 and r["makespan_us"]["p50"] > 0
    assert r["scheduling"]["manager"]["policy"] in ("SCHED_RR", "nice", "default")
    # the manager held the CPUs awake (PM QoS 0), or says why not
    manager = r["scheduling"]["manager"]
    assert manager["cpu_latency_us"] == 0 or any("cpu latency" in x for x in manager["refused"])


@contextlib.contextmanager
def running_bench(tmp_path: Path, *extra: str, rate: str = "200") -> Iterator[tuple]:
    """A 3-worker bench session, running; stopped (SIGKILL) at exit if still alive."""
    out = tmp_path / "bench.json"
    proc = start_cli(
        *bench_cycle(rate, "3", "60", str(out)),
        *extra,
    )
    ld = None
    try:
        sid = read_session_id(proc)
        ld = attach_running(sid, "bench", min_cycle=20)
        yield proc, ld, out
    finally:
        if ld is not None:
            ld.close()
        if proc.poll() is None:
            proc.terminate()
            proc.wait(timeout=30)
        proc.communicate()


def test_sigkill_of_a_worker_is_seen_at_once(tmp_path: Path) -> None:
    with running_bench(tmp_path) as (proc, ld, out):
        victim = int(ld.block("proc", 1).read()["pid"])
        cycle_at_kill = int(ld.block("manager").read()["cycle"])
        killed_ns = time.monotonic_ns()
        os.kill(victim, signal.SIGKILL)
        proc.wait(timeout=30)
    assert proc.returncode == 1
    r = load_json(out)
    assert r["result"] == "abnormal"
    m = re.search(r"worker busy1 \(pid (\d+)\) died: killed by SIGKILL at cycle (\d+)", r["reason"])
    assert m, r["reason"]
    assert int(m.group(1)) == victim
    # Seen through SIGCHLD/waitpid ("died"), not by the heartbeat check (limit 25
    # cycles): as soon as the kernel has torn the process down, typically
    # within the cycle of the kill; the bound leaves room for a loaded machine.
    assert int(m.group(2)) - cycle_at_kill <= 5
    detection_ms = (r["node_result"]["fault_monotonic_ns"] - killed_ns) / 1e6
    assert 0 < detection_ms < 25 * 5
    others = [w for w in r["node_result"]["workers"] if w["name"] != "busy1"]
    assert all(w["exit"] == "exited with code 0" for w in others)


def test_sigstop_of_a_worker_is_caught_by_the_heartbeat_check(tmp_path: Path) -> None:
    limit = 10
    with running_bench(tmp_path, "--set", f"bench.heartbeat_limit_cycles={limit}") as (
        proc,
        ld,
        out,
    ):
        assert int(ld.static["heartbeat_limit_cycles"]) == limit
        victim = int(ld.block("proc", 2).read()["pid"])
        cycle_at_stop = int(ld.block("manager").read()["cycle"])
        os.kill(victim, signal.SIGSTOP)
        proc.wait(timeout=30)
    r = load_json(out)
    assert r["result"] == "abnormal"
    m = re.search(
        rf"worker busy2 \(pid {victim}\) missed (\d+) heartbeats \(limit {limit}\) at cycle (\d+)",
        r["reason"],
    )
    assert m, r["reason"]
    assert int(m.group(1)) == limit
    assert int(m.group(2)) - cycle_at_stop <= limit + 1
    stopped = next(w for w in r["node_result"]["workers"] if w["name"] == "busy2")
    assert stopped["exit"] == "killed by SIGKILL"  # a hung worker is not waited for


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_or_sigterm_ends_the_session_in_order(tmp_path: Path, sig: int) -> None:
    with running_bench(tmp_path) as (proc, ld, out):
        pids = [int(ld.block("proc", j).read()["pid"]) for j in range(3)]
        proc.send_signal(sig)
        proc.wait(timeout=30)
    r = load_json(out)
    assert r["result"] == "abnormal"
    assert "interrupted by" in r["reason"]
    assert all(w["exit"] == "exited with code 0" for w in r["node_result"]["workers"])
    assert all(pid_gone(p) for p in pids)


def test_killing_the_manager_makes_every_worker_exit(tmp_path: Path) -> None:
    with running_bench(tmp_path) as (proc, ld, out):
        manager = int(ld.block("manager").read()["pid"])
        workers = [int(ld.block("proc", j).read()["pid"]) for j in range(3)]
        os.kill(manager, signal.SIGKILL)
        # the workers leave on their own (parent-death signal), before any reaper acts
        wait_for(lambda: all(pid_gone(p) for p in workers), 2.0, "workers to exit")
        proc.wait(timeout=30)
    r = load_json(out)
    assert r["result"] == "abnormal"
    assert "died: killed by SIGKILL" in r["reason"]
    assert r["node_result"]["stragglers_killed"] == []


def test_message_boxes_are_printed_and_logged(tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    done = run_cli(
        "--set",
        f"session.runs_dir={tmp_path}",
        "bench",
        "cycle",
        "--rate",
        "200",
        "--workers",
        "2",
        "--seconds",
        "1",
        "--no-baseline",
        "--message-every",
        "50",
        "--json",
        str(out),
    )
    assert done.returncode == 0, done.stderr
    # each worker posts on every 50th cycle it runs (a cycle skipped on a
    # loaded host posts nothing): each message printed is logged and in
    # the node's result
    printed = re.findall(r"\[bench/(busy[01])\] cycle (\d+): 0 us of work done", done.stderr)
    assert {w for w, _ in printed} == {"busy0", "busy1"}, done.stderr
    assert all(int(c) % 50 == 0 and 0 < int(c) <= 200 for _, c in printed), printed
    r = load_json(out)
    log = (Path(r["run_dir"]) / "messages.log").read_text()
    texts = [m["text"] for m in r["node_result"]["messages"]]
    for w, c in printed:
        assert f"[bench/{w}] cycle {c}: 0 us of work done" in log, (w, c, log)
        assert f"cycle {c}: 0 us of work done" in texts, (c, texts)


@pytest.mark.slow
def test_parallel_stages_and_comparison(tmp_path: Path) -> None:
    out = tmp_path / "cmp.json"
    done = run_cli(
        "bench",
        "cycle",
        "--rate",
        "500",
        "--workers",
        "2",
        "--work-us",
        "300",
        "--seconds",
        "2",
        "--compare-stages",
        "--pin",
        "--no-baseline",
        "--json",
        str(out),
    )
    assert done.returncode == 0, done.stderr
    r = load_json(out)
    serial, parallel = r["serial"], r["parallel"]
    assert serial["result"] == parallel["result"] == "ok"
    assert {w["stage"] for w in serial["node_result"]["workers"]} == {0, 1}
    assert {w["stage"] for w in parallel["node_result"]["workers"]} == {0}
    # two 300 us jobs: serial makespan holds both, parallel about one
    assert serial["makespan_us"]["p50"] > 600
    assert serial["compute_us"]["p50"] >= 300 and parallel["compute_us"]["p50"] >= 300
    pinned = [w["scheduling"]["cpus"] for w in parallel["node_result"]["workers"]]
    assert all(len(c) == 1 for c in pinned) and pinned[0] != pinned[1]


def test_an_off_cycle_worker_keeps_its_own_rate_and_is_watched(tmp_path: Path) -> None:
    """A worker with a negative stage runs on its own timer (as a DDM does) beside
    the node's cycle, signs heartbeats (the node ends ok: none went stale) and
    ends in order."""
    from redistro.ipc.session import Session
    from redistro.process.session_owner import run_node
    from redistro.process.spec import WorkerSpec

    workers = [
        WorkerSpec(name="a", role="busy", stage=0),
        WorkerSpec(name="b", role="busy", stage=1),
        WorkerSpec(name="own", role="busy", stage=-1, rate_hz=400.0),
    ]
    with Session.create() as s:
        r = run_node(_node_at_100hz(s.id, 20, workers, 200), s)
    assert r.result == "ok", r.reason
    by_name = {w.name: w for w in r.workers}
    assert by_name["a"].cycles + by_name["a"].stage_timeouts + by_name["a"].skipped == 200
    own = by_name["own"].cycles + by_name["own"].skipped
    # 2 s at 400 Hz beside the 100 Hz cycle (start-up and end give or take)
    assert 600 <= own <= 900, by_name["own"]
    assert by_name["own"].exit == "exited with code 0"


def test_a_worker_may_carry_its_own_heartbeat_limit(tmp_path: Path) -> None:
    """A worker with its own heartbeat_limit_cycles (the session log's
    recorders) is hung after that many missed heartbeats, not the node's."""
    import threading

    from redistro.ipc.session import Session
    from redistro.process.session_owner import run_node
    from redistro.process.spec import WorkerSpec

    own_limit = 60
    stopped: dict[str, int] = {}

    def stop_it(sid: str) -> None:
        signal.pthread_sigmask(signal.SIG_BLOCK, signal.valid_signals())  # the main thread's
        ld = attach_running(sid, "bench", min_cycle=20)
        try:
            stopped["pid"] = int(ld.block("proc", 1).read()["pid"])
            stopped["cycle"] = int(ld.block("manager").read()["cycle"])
            os.kill(stopped["pid"], signal.SIGSTOP)
        finally:
            ld.close()

    with Session.create() as s:
        workers = [
            WorkerSpec(name="a", role="busy", stage=0),
            WorkerSpec(name="rec", role="busy", stage=1, heartbeat_limit_cycles=own_limit),
        ]
        spec = _node_at_100hz(s.id, 10, workers, 2000)
        helper = threading.Thread(target=stop_it, args=(s.id,))
        helper.start()
        try:
            r = run_node(spec, s)
        finally:
            helper.join(timeout=60)
    assert stopped, "the worker was not stopped"
    assert r.result == "abnormal", r.reason
    hung = r"worker rec \(pid (\d+)\) missed (\d+) heartbeats \(limit (\d+)\) at cycle (\d+)"
    m = re.search(hung, r.reason)
    assert m, r.reason
    assert int(m.group(1)) == stopped["pid"] and int(m.group(3)) == own_limit
    # not before its own limit (the node's is 10), and at it
    assert int(m.group(2)) == own_limit
    assert own_limit <= int(m.group(4)) - stopped["cycle"] <= own_limit + 1


def _node_at_100hz(sid: str, heartbeat_limit: int, workers: list[Any], cycles: int) -> Any:
    """A node of busy workers at 100 Hz that runs ``cycles`` cycles."""
    from redistro.process.spec import NodeSpec

    return NodeSpec(
        session_id=sid,
        node="bench",
        kind="bench",
        rate_hz=100.0,
        heartbeat_limit_cycles=heartbeat_limit,
        workers=workers,
        cycles=cycles,
    )


def test_idle_work_runs_between_cycles_and_gives_way_to_the_sync() -> None:
    """The Idle state: a worker whose idle work never ends (it always says
    there is more) runs it between its cycles, in slices, and still takes
    every sync: the cycle never waits on it. The manager drains the message
    boxes in its own Idle, after the syncs went out."""
    from redistro.ipc.session import Session
    from redistro.process.session_owner import run_node
    from redistro.process.spec import WorkerSpec

    workers = [
        WorkerSpec(name="a", role="busy", stage=0, params={"idle_us": 50}),
        WorkerSpec(name="b", role="busy", stage=1, params={"message_every": 50}),
    ]
    with Session.create() as s:
        r = run_node(_node_at_100hz(s.id, 20, workers, 200), s)
    assert r.result == "ok", r.reason
    a, b = (next(w for w in r.workers if w.name == n) for n in ("a", "b"))
    # every cycle was taken (run, or skipped and counted on a host stall),
    # though the idle work always had more to do
    assert a.cycles + a.skipped + a.stage_timeouts == 200, a
    # ... and it ran: 10 ms periods less the guard, in 50 us slices
    assert a.idle_slices > 20 * a.cycles, a
    assert b.idle_slices == 0  # no idle work: nothing run, nothing paid
    assert r.idle_slices >= 200  # the manager's: the message boxes, after each tick
    # b's messages (one every 50 of its cycles) drained in the manager's Idle:
    # each cycle b ran that posted one (a cycle a host stall skipped posts none)
    texts = [m["text"] for m in r.messages if m["text"].endswith("us of work done")]
    posted = {f"cycle {k}: 0 us of work done" for k in (50, 100, 150, 200)}
    assert set(texts) <= posted and len(texts) == len(set(texts)), texts
    # (a loaded host's stalls may cost more cycles than b posts on: then
    # at least one of the four still arrives)
    assert len(texts) >= max(len(posted) - b.skipped - b.stage_timeouts, 1), (texts, b)

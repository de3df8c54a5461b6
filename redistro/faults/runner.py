"""Run one fault scenario against a real session and measure what happened.

The session is the real command line (``redistro session
tasks/fault_drill.yaml``) in a child process; the runner attaches to the
SSC's Local Data read-only to see r2 move, waits a random 0.5-2.5 s of its
first segment, breaks the target process, waits for the session to end and
reads its summary. Times are CLOCK_MONOTONIC on one host: the injection, the
first fault a manager recorded (``fault_monotonic_ns``), the plant's freezes
(every brake of a robot on).

Past the house's ~400 lines: each kind of scenario (a process broken, an
input refused, a start refused, stale IPC, hogs) measures the same row.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from redistro.config.model import Config
from redistro.drivers import positions
from redistro.errors import RedistroError
from redistro.faults.catalogue import Scenario
from redistro.faults.common import (
    count_of,
    die_with_parent,
    ipc_left,
    one_line_refusal,
    pids_of,
    session_id,
    sid_from,
)
from redistro.localdata.view import NodeView
from redistro.process.plan import RECORDERS

TASK = "tasks/fault_drill.yaml"
# the switches stuck: found in the first sweep, which the short calibration
# makes as the long one does (over 10 degrees in 2 s)
CALIBRATION_TASK = "tasks/self_calibration_short.yaml"
ROBOT = 1  # r2, the robot that moves (index in the task's robots)
SESSION_TIMEOUT_S = 240.0
HOGS_TASK = "tasks/peg_insertion_short.yaml"  # (every segment of the main job, in 27 s)


def _cli(runs: Path, config_args: list[str]) -> list[str]:
    return [sys.executable, "-m", "redistro.cli", "--set", f"session.runs_dir={runs}", *config_args]


def ensure_calibrated(runs: Path, cfg: Config, config_args: list[str], say: Any) -> None:
    """Known joint positions in ``runs`` and the arms at their park pose:
    the baseline every scenario starts from (a self-calibration when the
    positions are unknown, a park when the arms stand elsewhere: a
    self-calibration's sweep finds the home switches only within a few
    degrees of it, and a switch out of reach would look stuck)."""
    unknown = []
    for r in ("r1", "r2"):
        try:
            positions.read(runs / "positions" / f"{r}.json", [r])
        except positions.PositionsUnknown as exc:
            unknown.append(str(exc))
    if unknown:
        # the arms may stand anywhere after a crash, out of reach of the home
        # switches' sweep: they start from their initial pose (as if put back)
        (runs / "plant-pose.json").unlink(missing_ok=True)
        say(f"joint positions unknown ({'; '.join(unknown)}): self-calibration first")
        task = "tasks/self_calibration.yaml"
    else:
        away = _away_from_park(runs, cfg)
        if not away:
            return
        say(f"{away}: parking the arms first")
        task = "tasks/park.yaml"
    done = subprocess.run(
        [*_cli(runs, config_args), "session", task],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
        preexec_fn=die_with_parent,
    )
    if done.returncode != 0:
        raise RedistroError(f"{task} before the scenarios failed: {done.stdout[-500:]}")


PARKED_WITHIN_RAD = 0.035  # 2 degrees: well inside the calibration's sweep


def _away_from_park(runs: Path, cfg: Config) -> str:
    """Which arm the plant's pose file puts off its park pose (its
    ``initial_q_rad``), and by how much; "" when both are parked."""
    from redistro.plant.process import read_pose

    path = cfg.plant.pose_file or str(runs / cfg.session.plant_pose_file)
    pose = read_pose(path, list(cfg.robots))
    for robot, q in pose.items():
        off = max(abs(a - b) for a, b in zip(q, cfg.robots[robot].initial_q_rad, strict=True))
        if off > PARKED_WITHIN_RAD:
            return f"{robot} stands {math.degrees(off):.0f} deg off its park pose"
    return ""


def _wait_moving(sid: str, seconds: float, proc: subprocess.Popen[str], deadline: float) -> None:
    """Wait until r2 has been moving ``seconds`` into its first segment
    (else RedistroError, saying what was seen last)."""
    view, seen = None, "the SSC's Local Data never attached"
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            if view is None:
                view = NodeView.open(sid, "ssc")
            if view is not None:
                try:
                    plan = view.read("plan", ROBOT)
                    segment, t = int(plan["segment"]), float(plan["segment_t_s"])
                    if segment >= 1 and t >= seconds:
                        return
                    seen = f"last seen: segment {segment} at {t:.2f} s (wanted {seconds:.2f} s)"
                except Exception as exc:  # (a node's data torn or going: look again)
                    seen = f"the SSC's plan unreadable: {exc}"
            time.sleep(0.01)  # polling a condition with a deadline
        ended = "stalled" if proc.poll() is None else f"ended (exit {proc.returncode})"
        raise RedistroError(f"r2 never moved: the session {ended}; {seen}")
    finally:
        if view is not None:
            view.close()


def _target_pid(sid: str, sc: Scenario) -> int:
    if sc.node == "plant":
        for pid in pids_of(sid):
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            if b"plant" in cmd:
                return pid
        raise RedistroError("no plant process found")
    view = NodeView.open(sid, sc.node)
    if view is None:
        raise RedistroError(f"no Local Data of {sc.node}")
    with view:
        return view.pid(sc.proc)


def run_scenario(
    sc: Scenario, runs: Path, cfg: Config, config_args: list[str], rng: random.Random
) -> dict[str, Any]:
    """Run ``sc`` once; the figures and verdicts as a dict (JSON-ready)."""
    ipc_left("")  # (the first call notes the memory cards already there)
    out_dir = runs / "faults" / sc.name
    shutil.rmtree(out_dir, ignore_errors=True)  # no summary of an earlier run
    out_dir.mkdir(parents=True)
    row: dict[str, Any] = {"name": sc.name, "kind": sc.kind, "what": sc.what}
    row["target"] = f"{sc.node}/{sc.proc}".strip("/")
    row.update(action=sc.action, expected=list(sc.expect))
    if sc.kind == "input":
        from redistro.faults.inputs import run_input

        row.update(run_input(sc, out_dir, config_args))
        return row
    if sc.kind == "start" and sc.action != "stale-ipc":
        row.update(_refused_start(sc, runs, out_dir, config_args))
        return row
    if sc.kind == "can-noise":
        from redistro.faults.can_noise import run_can_noise

        if sc.action == "replay":
            from redistro.faults.can_noise import run_can_replay

            row.update(run_can_replay(out_dir, cfg))
        else:
            row.update(run_can_noise(out_dir, cfg, forged=sc.action == "forged"))
        return row
    if sc.kind == "hogs":
        row.update(_hogs(sc, runs, out_dir, config_args))
        return row
    if sc.kind == "local-user":
        from redistro.faults.local_user import run_local_user

        task = str(_first_segment_drill(out_dir))
        row.update(run_local_user(sc, out_dir, _session_args(sc, runs, config_args), task))
        return row
    if sc.kind == "rerun":
        from redistro.faults.rerun import run_rerun_replay

        task = str(_first_segment_drill(out_dir))
        row.update(run_rerun_replay(sc, out_dir, cfg, _session_args(sc, runs, config_args), task))
        return row
    if sc.kind == "stale-ipc" or sc.action == "stale-ipc":
        row.update(_stale_ipc(sc, runs, out_dir, cfg, config_args, rng))
        return row
    row.update(_break_session(sc, runs, out_dir, cfg, config_args, rng))
    return row


def _session_args(sc: Scenario, runs: Path, config_args: list[str]) -> list[str]:
    sets = [a for kv in sc.sets for a in ("--set", kv)]
    return [*_cli(runs, [*config_args, *sets])]


def _break_session(
    sc: Scenario,
    runs: Path,
    out_dir: Path,
    cfg: Config,
    config_args: list[str],
    rng: random.Random,
) -> dict[str, Any]:
    """Start the drill (or the self-calibration), break it, wait for its end, judge."""
    row: dict[str, Any] = {}
    env = os.environ.copy()
    trigger = out_dir / "inject.trigger"
    if sc.kind in ("inject", "calibration"):
        from redistro.faults.inject import ENV, arm
        from redistro.process import hooks

        env[ENV] = arm(sc.action, str(trigger), node=sc.node, robot="r2", arg=sc.arg)
        env[hooks.ENV] = "redistro.faults.hooks"  # the plant and the ddms take their part
    calibration = sc.kind == "calibration"
    if calibration:
        trigger.touch()  # stuck from the start
    task = CALIBRATION_TASK if calibration else TASK
    if sc.expect == ("ok",):
        task = str(_first_segment_drill(out_dir))
    proc = subprocess.Popen(
        [*_session_args(sc, runs, config_args), "session", task, "--out", str(out_dir)],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=env,
        preexec_fn=die_with_parent,
    )
    deadline = time.monotonic() + SESSION_TIMEOUT_S
    inject_ns = 0
    sid = ""
    cycles_at: dict[str, int] = {}
    try:
        sid = session_id(proc, deadline, "self_calibration" if calibration else "fault_drill")
        if calibration or sc.kind == "limits":
            # stuck from the start, or nothing injected: the drill runs into the limit itself
            inject_ns = time.monotonic_ns()
        else:
            delay = rng.uniform(0.5, 2.5)
            row["injected_after_s"] = round(delay, 3)
            _wait_moving(sid, delay, proc, deadline)
            managers = _managers(sid)
            try:
                inject_ns = _inject(sc, sid, trigger, cfg, managers, cycles_at)
            finally:
                for view in managers:
                    view.close()
        proc.communicate(timeout=max(1.0, deadline - time.monotonic()))
    except (RedistroError, subprocess.TimeoutExpired, OSError, ValueError) as exc:
        row["error"] = str(exc)
    finally:
        _end(proc)
    lockstep = cfg.session.clock == "lockstep"
    fired = _fired_ns(trigger)
    if fired and not lockstep:  # (in lockstep the plant stamps its simulated clock)
        inject_ns = fired
    # in lockstep the plant's records go by its step: those after the fault
    # are those from the step its boards last gave r2's ESC at the injection
    since = cycles_at.get("step", 0) if lockstep else None
    row.update(_verdict(sc, sid, inject_ns, out_dir, runs, cfg, cycles_at, since))
    if "error" in row:
        row["passed"] = False
    return row


# the drill's first segment alone, shortened: the motion still runs past
# the latest injection (2.5 s in), and the segment 1.5 s beyond it
RIDE_OUT_MOVE_S, RIDE_OUT_SEGMENT_S = 3.5, 4.0


def _first_segment_drill(out_dir: Path) -> Path:
    """The drill's first segment alone: a fault the session must ride out
    comes within 2.5 s of it, and the session goes on to its ``ok``."""
    import yaml

    data = yaml.safe_load(Path(TASK).read_text())
    first = data["segments"][0]
    first["duration_s"], first["goal"]["move_s"] = RIDE_OUT_SEGMENT_S, RIDE_OUT_MOVE_S
    data["segments"] = [first]
    path = out_dir / "drill_first_segment.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _managers(sid: str) -> list[NodeView]:
    """A view of every node, attached now so that the cycles at the
    injection are read in microseconds."""
    views = (NodeView.open(sid, node) for node in ("esc.r1", "esc.r2", "ssc"))
    return [v for v in views if v is not None]


def cycle_at(cycle: int, due_ns: int, when_ns: int, period_ms: float) -> int:
    """The node's cycle at ``when_ns``, from a cycle it was in and when that
    cycle's tick was due (the ticks come every period): a fault armed by the
    trigger file takes effect when its process next looks, up to a cycle
    after the trigger, and its detection counts from there."""
    if not due_ns or when_ns <= due_ns:
        return cycle
    return cycle + int((when_ns - due_ns) // int(period_ms * 1e6))


def _read_cycles(views: list[NodeView], into: dict[str, int]) -> None:
    for v in views:
        with contextlib.suppress(Exception):
            m = v.manager()
            into[v.node] = int(m["cycle"])
            into[f"{v.node}/due_ns"] = int(m["tick_due_ns"])  # when that cycle's tick was due
    for v in views:  # an ESC's sender: each of its cycles sends a command
        with contextlib.suppress(Exception):
            into[f"{v.node}/sender"] = int(v.proc("sender")["cycles"])
        if v.node == "esc.r2":  # the boards' sample r2's ESC last took
            with contextlib.suppress(Exception):
                into["step"] = int(v.read("feedback", 0)["step"])


def _end(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.communicate(timeout=60)
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def _fired_ns(trigger: Path) -> int:
    try:
        return int(json.loads(Path(f"{trigger}.fired").read_text())["monotonic_ns"])
    except (OSError, ValueError, KeyError):
        return 0


def _inject(
    sc: Scenario,
    sid: str,
    trigger: Path,
    cfg: Config,
    managers: list[NodeView],
    cycles_at: dict[str, int],
) -> int:
    """Break the session now; the injection's time (CLOCK_MONOTONIC ns). Each
    node's cycle at that moment goes into ``cycles_at``."""
    if sc.kind == "process":
        pid = _target_pid(sid, sc)
        _read_cycles(managers, cycles_at)
        now = time.monotonic_ns()
        os.kill(pid, signal.SIGKILL if sc.action == "kill" else signal.SIGSTOP)
        return now
    if sc.kind == "inject":
        _read_cycles(managers, cycles_at)
        now = time.monotonic_ns()
        trigger.touch()
        return now
    raise RedistroError(f"{sc.name}: nothing to inject for kind {sc.kind}")


def _limit_cycles(sc: Scenario, cfg: Config, node: str) -> float | None:
    if sc.limit in ("death", "guard"):
        return 2
    rate = cfg.ssc.rate_hz if node == "ssc" else cfg.esc.rate_hz
    if sc.limit == "heartbeat":
        hb = cfg.ssc.heartbeat_limit_cycles if node == "ssc" else cfg.esc.heartbeat_limit_cycles
        if sc.proc in RECORDERS:  # the session log's recorders have their own
            from redistro.process.plan import recorder_heartbeat_limit

            hb = recorder_heartbeat_limit(cfg, rate)
        return hb + 2
    if sc.limit == "starving":
        return cfg.ddm.starving_limit_cycles + 2
    if sc.limit == "io":
        return cfg.plant.io_timeout_ms / 1e3 * rate + 2
    return None


def _verdict(
    sc: Scenario,
    sid: str,
    inject_ns: int,
    out_dir: Path,
    runs: Path,
    cfg: Config,
    cycles_at: dict[str, int] | None = None,
    since_step: int | None = None,
) -> dict[str, Any]:
    """A scenario's row: what the session said, when the fault was detected
    and by whom, the freezes and e-stops, what was left behind.
    ``since_step``: in lockstep, the plant's records after the fault are
    those from this step on (else those stamped after ``inject_ns``)."""
    row: dict[str, Any] = {}
    try:
        summary = json.loads((out_dir / "summary.json").read_text())
    except (OSError, ValueError):
        summary = {}
    got = summary.get("result", "none")
    row["got"] = got
    row["cause"] = summary.get("reason", "")
    nodes: dict[str, Any] = summary.get("nodes", {})
    # a manager that failed on its own error (not on the fault it met)
    row["manager_errors"] = [
        f"{name}: {n.get('reason', '')}"
        for name, n in nodes.items()
        if str(n.get("reason", "")).startswith("manager error")
    ]
    row["detected"] = got != "ok" and got != "none"
    detected_ns = _detection(sc, cfg, nodes, inject_ns, cycles_at, row)

    def after(rec: dict[str, Any]) -> bool:  # a plant record (a freeze, a trip) is
        if since_step is None:
            return bool(rec.get("monotonic_ns", 0) >= inject_ns > 0)
        return int(rec.get("step", 0)) >= since_step

    if since_step is not None:  # (wall-clock figures of a paced run say nothing)
        row["clock"] = "lockstep"
        try:  # ticks the plant gave up waiting for (a node ended unseen: none due)
            plant = json.loads((out_dir / "plant.json").read_text())
            row["waits_missed"] = int(plant["lockstep"]["waits_missed"])
        except (OSError, ValueError, KeyError, TypeError):
            pass
        for key in ("detection_ms", "detection_cycles"):
            row.pop(key, None)
    _freezes(sc, summary, nodes, after, detected_ns, row, timed=since_step is None)
    row["estop_every_node"] = bool(nodes) and all(n.get("result") != "ok" for n in nodes.values())
    stops = [int(n["fault_monotonic_ns"]) for n in nodes.values() if n.get("fault_monotonic_ns")]
    if len(stops) == len(nodes) > 1 and detected_ns is not None and since_step is None:
        # from the first node's fault to the last node's e-stop
        row["estop_spread_ms"] = round((max(stops) - min(stops)) / 1e6, 2)
    watchdog = summary.get("plant", {}).get("watchdog_trips") or []
    row["watchdog_trips"] = [t["robot"] for t in watchdog if after(t)]
    row["processes_left"] = len(pids_of(sid)) if sid else 0
    row["ipc_left"] = ipc_left(sid) if sid else []
    valid = []
    for r in ("r1", "r2"):
        try:
            positions.read(runs / "positions" / f"{r}.json", [r])
            valid.append(r)
        except positions.PositionsUnknown as exc:
            row.setdefault("positions_problems", []).append(str(exc))
    row["positions_valid"] = valid == ["r1", "r2"]
    if sc.count:
        row["count"] = {sc.count: count_of(summary, sc.count)}
    if sc.apart:  # the plant's truth
        arms = summary.get("plant", {}).get("arms") or {}
        row["arms_touched"] = arms.get("touched", True)
        row["arms_min_distance_m"] = arms.get("min_distance_m")
    row["passed"] = _passed(sc, got, row)
    return row


def _passed(sc: Scenario, got: str, row: dict[str, Any]) -> bool:
    fault_expected = "ok" not in sc.expect
    return bool(
        got in sc.expect
        and reason_matches(sc.reason, row["cause"])
        and (
            not fault_expected
            or not sc.limit
            or row.get("detection_within_limit", sc.limit == "death" and sc.proc == "manager")
        )
        and (not fault_expected or (sc.node == "plant" and sc.kind == "process")
             or row.get("all_frozen"))
        and (not sc.count or row["count"][sc.count] > 0)
        and (not sc.apart or row.get("arms_touched") is False)
        and row["processes_left"] == 0
        and not row["ipc_left"]
    )  # fmt: skip


def _detection(
    sc: Scenario,
    cfg: Config,
    nodes: dict[str, Any],
    inject_ns: int,
    cycles_at: dict[str, int] | None,
    row: dict[str, Any],
) -> int | None:
    """When the fault was first detected (None: never), by whom, in how
    many of the detecting node's own cycles (its manager's counter, as its
    checks count; ms / period beside it), against its bound."""
    faults = [
        (n["fault_monotonic_ns"], name, n)
        for name, n in nodes.items()
        if n.get("fault_monotonic_ns") and n["fault_monotonic_ns"] >= inject_ns > 0
    ]
    if not faults:
        return None
    detected_ns, first, n = min(faults)
    period_ms = 1e3 / float(n.get("rate_hz") or 200.0)
    ms = (detected_ns - inject_ns) / 1e6
    row["detected_by"] = first
    row["detection_ms"] = round(ms, 2)
    row["detection_cycles"] = round(ms / period_ms, 2)
    limit = _limit_cycles(sc, cfg, first)
    row["detection_limit_cycles"] = limit
    cycles = ms / period_ms
    if cycles_at and first in cycles_at and n.get("fault_cycle") is not None:
        at = cycles_at[first]
        if sc.kind == "inject":  # an armed point acts when its process next looks
            at = cycle_at(at, cycles_at.get(f"{first}/due_ns", 0), inject_ns, period_ms)
        cycles = int(n["fault_cycle"]) - at
        row["detection_node_cycles"] = cycles
    sender = next((w for w in n.get("workers", []) if w.get("name") == "sender"), None)
    if sc.limit == "starving" and cycles_at and f"{first}/sender" in cycles_at and sender:
        # the starving index counts the commands the sender sent without a
        # fresh one: on a loaded host the sender skips cycles, so the bound
        # is in its cycles (it runs no more after the fault)
        cycles = int(sender["cycles"]) - cycles_at[f"{first}/sender"]
        row["detection_sender_cycles"] = cycles
    row["detection_within_limit"] = limit is None or cycles <= limit
    return int(detected_ns)


def _freezes(
    sc: Scenario,
    summary: dict[str, Any],
    nodes: dict[str, Any],
    after: Callable[[dict[str, Any]], bool],
    detected_ns: int | None,
    row: dict[str, Any],
    timed: bool = True,
) -> None:
    """Which robots froze after the fault (``after``: a plant record is),
    and in real time (``timed``) how soon after its detection and each
    after its own ESC's fault (a dead plant freezes nothing)."""
    if sc.kind == "process" and sc.node == "plant":
        return
    frozen: dict[str, float] = {}
    for f in summary.get("plant", {}).get("freezes") or []:
        if after(f) and f["robot"] not in frozen:
            frozen[f["robot"]] = f["monotonic_ns"]
    row["frozen"] = sorted(frozen)
    row["all_frozen"] = set(frozen) >= {"r1", "r2"}
    if not timed:  # (the plant's stamps are its simulated clock)
        return
    if frozen and detected_ns is not None:
        # from the first detection to the last robot's brakes at the plant
        row["freeze_ms"] = round((max(frozen.values()) - detected_ns) / 1e6, 2)
    own = {
        r: round((t - nodes[f"esc.{r}"]["fault_monotonic_ns"]) / 1e6, 2)
        for r, t in frozen.items()
        if nodes.get(f"esc.{r}", {}).get("fault_monotonic_ns")
    }
    if own:
        row["freeze_after_own_fault_ms"] = own


def reason_matches(expected: str, cause: str) -> bool:
    """``expected`` (alternatives split by ``|``; empty: anything) is in ``cause``."""
    return any(part in cause for part in expected.split("|"))


def _refused_start(
    sc: Scenario, runs: Path, out_dir: Path, config_args: list[str]
) -> dict[str, Any]:
    """A broken positions file, a task that may not calibrate on its own:
    refused before any process starts."""
    path = runs / "positions" / "r2.json"
    if sc.action == "positions-missing":
        path.unlink(missing_ok=True)
    elif sc.action == "positions-corrupt":
        path.write_text('{"format": 1, "q_rad": ')  # cut short, as by a full disk
    elif sc.action == "positions-unclean":
        pos = positions.read(path, ["r2"])
        positions.write(path, pos.session, pos.q_rad, clean=False)
    task = out_dir / "drill_no_calibration.yaml"
    text = Path(TASK).read_text().replace("calibrate_if_needed: true", "calibrate_if_needed: false")
    task.write_text(text)
    before = set(os.listdir("/dev/shm"))
    done = subprocess.run(
        [*_session_args(sc, runs, config_args), "session", str(task), "--out", str(out_dir)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        preexec_fn=die_with_parent,
    )
    row = one_line_refusal(done)
    row["ipc_left"] = sorted(set(os.listdir("/dev/shm")) - before)
    row["processes_left"] = 0
    row["plant_started"] = (out_dir / "plant.json").exists()
    row["passed"] = bool(
        row["got"] == "refused"
        and row["one_line"]
        and sc.reason in row["cause"]
        and not row["ipc_left"]
        and not row["plant_started"]
    )
    return row


def _stale_ipc(
    sc: Scenario,
    runs: Path,
    out_dir: Path,
    cfg: Config,
    config_args: list[str],
    rng: random.Random,
) -> dict[str, Any]:
    """Kill every process of a running drill at once (a power cut of the
    controller), then start another: it must reap the leftovers, find the
    positions unclean, calibrate first and run the task."""
    row: dict[str, Any] = {}
    first = out_dir / "crashed"
    task = str(_first_segment_drill(out_dir))  # the crash comes within it
    proc = subprocess.Popen(
        [*_session_args(sc, runs, config_args), "session", task, "--out", str(first)],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        start_new_session=True,
        preexec_fn=die_with_parent,
    )
    deadline = time.monotonic() + SESSION_TIMEOUT_S
    sid = ""
    try:
        sid = session_id(proc, deadline)
        _wait_moving(sid, rng.uniform(0.5, 2.5), proc, deadline)
        victims = [proc.pid, *pids_of(sid)]
        for pid in victims:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        proc.communicate(timeout=30)
        wait_until = time.monotonic() + 10
        while pids_of(sid) and time.monotonic() < wait_until:
            time.sleep(0.02)  # the kernel reaps the orphans (a condition, with a deadline)
        row["killed"] = len(victims)
        row["left_by_crash"] = ipc_left(sid)
    except (RedistroError, subprocess.TimeoutExpired, OSError, ValueError) as exc:
        row["error"] = str(exc)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    second = out_dir / "next"
    done = subprocess.run(
        [*_session_args(sc, runs, config_args), "session", task, "--out", str(second)],
        capture_output=True,
        text=True,
        timeout=SESSION_TIMEOUT_S + 300,
        check=False,
        preexec_fn=die_with_parent,
    )
    try:
        summary = json.loads((second / "summary.json").read_text())
    except (OSError, ValueError):
        summary = {}
    row["got"] = summary.get("result", f"exit {done.returncode}")
    row["cause"] = summary.get("reason", "")
    row["reaped"] = [ln for ln in done.stderr.splitlines() if ln.startswith("reaped ")]
    row["calibrated_first"] = "self-calibration of" in done.stdout
    sids = [x for x in (sid, sid_from(done.stdout)) if x]
    row["processes_left"] = sum(len(pids_of(x)) for x in sids)
    row["ipc_left"] = [o for x in sids for o in ipc_left(x)]
    row["passed"] = bool(
        "error" not in row
        and row["left_by_crash"]
        and row["reaped"]
        and row["calibrated_first"]
        and row["got"] in sc.expect
        and row["processes_left"] == 0
        and not row["ipc_left"]
    )
    return row


def _hogs(sc: Scenario, runs: Path, out_dir: Path, config_args: list[str]) -> dict[str, Any]:
    """The short peg insertion (the main job's four segments) beside two
    processes spinning at normal priority."""
    spin = "import time\nwhile True:\n    pass\n"
    hogs = [
        subprocess.Popen([sys.executable, "-c", spin], preexec_fn=die_with_parent) for _ in range(2)
    ]
    t0 = time.monotonic()
    try:
        done = subprocess.run(
            [*_session_args(sc, runs, config_args), "session", HOGS_TASK, "--out", str(out_dir)],
            capture_output=True,
            text=True,
            timeout=1800,
            check=False,
            preexec_fn=die_with_parent,
        )  # fmt: skip
    finally:
        cpu = 0.0
        for h in hogs:
            with contextlib.suppress(OSError, ValueError):
                stat = Path(f"/proc/{h.pid}/stat").read_text().rsplit(")", 1)[1].split()
                cpu += (int(stat[11]) + int(stat[12])) / os.sysconf("SC_CLK_TCK")
            h.kill()
            h.wait()
    wall = time.monotonic() - t0
    try:
        summary = json.loads((out_dir / "summary.json").read_text())
    except (OSError, ValueError):
        summary = {}
    sid = sid_from(done.stdout)
    row: dict[str, Any] = {
        "got": summary.get("result", f"exit {done.returncode}"),
        "cause": summary.get("reason", ""),
        "inserted": bool(summary.get("inserted")),
        "wall_s": round(wall, 1),
        # how busy the hogs kept the CPUs (2.0: both, the whole time)
        "hog_cpus": round(cpu / wall, 2) if wall > 0 else 0.0,
        "processes_left": len(pids_of(sid)) if sid else 0,
        "ipc_left": ipc_left(sid) if sid else [],
    }
    row["passed"] = bool(
        row["got"] in sc.expect
        and row["inserted"]
        and row["processes_left"] == 0
        and not row["ipc_left"]
    )
    return row

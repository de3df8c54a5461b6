"""Run one fault scenario against a real session and measure what happened.

The session is the real command line (``redistro session
tasks/fault_drill.yaml``) in a child process; the runner attaches to the
SSC's Local Data read-only to see r2 move, waits a random 0.5-2.5 s of its
first segment, breaks the target process, waits for the session to end and
reads its summary. Times are CLOCK_MONOTONIC on one host: the injection, the
first fault a manager recorded (``fault_monotonic_ns``), the plant's freezes
(every brake of a robot on).
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from redistro.config.model import Config
from redistro.drivers import positions
from redistro.errors import RedistroError
from redistro.faults.catalogue import Scenario

TASK = "tasks/fault_drill.yaml"
ROBOT = 1  # r2, the robot that moves (index in the task's robots)
SESSION_TIMEOUT_S = 240.0


def _cli(runs: Path, config_args: list[str]) -> list[str]:
    return [sys.executable, "-m", "redistro.cli", "--set", f"session.runs_dir={runs}", *config_args]


def ensure_calibrated(runs: Path, config_args: list[str], say: Any) -> None:
    """Known joint positions in ``runs`` (a self-calibration when they are not)."""
    unknown = []
    for r in ("r1", "r2"):
        try:
            positions.read(runs / "positions" / f"{r}.json", [r])
        except positions.PositionsUnknown as exc:
            unknown.append(str(exc))
    if not unknown:
        return
    # the arms may stand anywhere after a crash, out of reach of the home
    # switches' sweep: they start from their initial pose (as if put back)
    (runs / "plant-pose.json").unlink(missing_ok=True)
    say(f"joint positions unknown ({'; '.join(unknown)}): self-calibration first")
    done = subprocess.run(
        [*_cli(runs, config_args), "session", "tasks/self_calibration.yaml"],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    if done.returncode != 0:
        raise RedistroError(f"self-calibration before the scenarios failed: {done.stdout[-500:]}")


def _session_id(proc: subprocess.Popen[str], deadline: float) -> str:
    """The fault drill's session id, from the CLI's first lines."""
    assert proc.stdout is not None
    last = ""
    seen: list[str] = []
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        seen.append(line.strip())
        if line.startswith("session "):
            last = line.split()[1]
        elif line.startswith("task fault_drill") and last:
            return last
    said = " | ".join(line for line in seen[-4:] if not line.startswith("["))
    raise RedistroError(f"the fault drill session did not start: {said}")


def _wait_moving(sid: str, seconds: float, proc: subprocess.Popen[str], deadline: float) -> bool:
    """Wait until r2 has been moving ``seconds`` into its first segment."""
    from redistro.localdata import LocalData

    ld = None
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            if ld is None:
                with contextlib.suppress(Exception):
                    ld = LocalData.attach(sid, "ssc")
            if ld is not None:
                try:
                    plan = ld.block("plan", ROBOT).read()
                    if int(plan["segment"]) >= 1 and float(plan["segment_t_s"]) >= seconds:
                        return True
                except Exception:
                    pass
            time.sleep(0.01)  # polling a condition with a deadline
        return False
    finally:
        if ld is not None:
            ld.close()


def _target_pid(sid: str, sc: Scenario) -> int:
    if sc.node == "plant":
        for pid in _pids_of(sid):
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            if b"plant" in cmd:
                return pid
        raise RedistroError("no plant process found")
    from redistro.localdata import LocalData

    ld = LocalData.attach(sid, sc.node)
    try:
        if sc.proc == "manager":
            return int(ld.block("manager").read()["pid"])
        names = ld.proc_names()
        return int(ld.block("proc", names.index(sc.proc)).read()["pid"])
    finally:
        ld.close()


def _pids_of(sid: str) -> list[int]:
    """Processes whose command line names the session (ours: managers, workers, plant)."""
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            cmd = Path(f"/proc/{entry}/cmdline").read_bytes()
            stat = Path(f"/proc/{entry}/stat").read_bytes()
        except OSError:
            continue
        if sid.encode() in cmd and stat[stat.rfind(b")") + 2 :].split()[0] != b"Z":
            out.append(int(entry))
    return out


def _ipc_left(sid: str) -> list[str]:
    left = [e for e in os.listdir("/dev/shm") if sid in e]
    try:
        import sysv_ipc

        from redistro.ipc.sysv import card_key

        for node in ("esc.r1", "esc.r2", "ssc"):
            with contextlib.suppress(sysv_ipc.ExistentialError):
                sysv_ipc.SharedMemory(card_key(sid, node))
                left.append(f"sysv {card_key(sid, node):#010x} ({node})")
    except ImportError:
        pass
    return left


def run_scenario(
    sc: Scenario, runs: Path, cfg: Config, config_args: list[str], rng: random.Random
) -> dict[str, Any]:
    """Run ``sc`` once; the figures and verdicts as a dict (JSON-ready)."""
    out_dir = runs / "faults" / sc.name
    shutil.rmtree(out_dir, ignore_errors=True)  # no summary of an earlier run
    row: dict[str, Any] = {"name": sc.name, "target": f"{sc.node}/{sc.proc}".rstrip("/")}
    row.update(action=sc.action, expected=list(sc.expect))
    proc = subprocess.Popen(
        [*_cli(runs, config_args), "session", TASK, "--out", str(out_dir)],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    deadline = time.monotonic() + SESSION_TIMEOUT_S
    inject_ns = 0
    sid = ""
    try:
        sid = _session_id(proc, deadline)
        delay = rng.uniform(0.5, 2.5)
        row["injected_after_s"] = round(delay, 3)
        if not _wait_moving(sid, delay, proc, deadline):
            raise RedistroError("r2 never moved (the session ended or stalled first)")
        pid = _target_pid(sid, sc)
        inject_ns = time.monotonic_ns()
        os.kill(pid, signal.SIGKILL if sc.action == "kill" else signal.SIGSTOP)
        proc.communicate(timeout=max(1.0, deadline - time.monotonic()))
    except (RedistroError, subprocess.TimeoutExpired, OSError, ValueError) as exc:
        row["error"] = str(exc)
    finally:
        if proc.poll() is None:
            proc.terminate()
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.communicate(timeout=60)
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    row.update(_verdict(sc, sid, inject_ns, out_dir, runs, cfg))
    if "error" in row:
        row["passed"] = False
    return row


def _limit_cycles(sc: Scenario, cfg: Config, node: str) -> float | None:
    if sc.limit == "death":
        return 2
    rate = cfg.ssc.rate_hz if node == "ssc" else cfg.esc.rate_hz
    if sc.limit == "heartbeat":
        hb = cfg.ssc.heartbeat_limit_cycles if node == "ssc" else cfg.esc.heartbeat_limit_cycles
        return hb + 2
    if sc.limit == "starving":
        return cfg.ddm.starving_limit_cycles + 2
    if sc.limit == "io":
        return cfg.plant.io_timeout_ms / 1e3 * rate + 2
    return None


def _verdict(
    sc: Scenario, sid: str, inject_ns: int, out_dir: Path, runs: Path, cfg: Config
) -> dict[str, Any]:
    row: dict[str, Any] = {}
    summary_path = out_dir / "summary.json"
    try:
        summary = json.loads(summary_path.read_text())
    except (OSError, ValueError):
        summary = {}
    got = summary.get("result", "none")
    row["got"] = got
    row["cause"] = summary.get("reason", "")
    nodes: dict[str, Any] = summary.get("nodes", {})
    faults = [
        (n["fault_monotonic_ns"], name, n)
        for name, n in nodes.items()
        if n.get("fault_monotonic_ns") and n["fault_monotonic_ns"] >= inject_ns > 0
    ]
    detected_ns = min(faults)[0] if faults else None
    row["detected"] = got != "ok" and got != "none"
    if detected_ns is not None:
        _, first, n = min(faults)
        period_ms = 1e3 / float(n.get("rate_hz") or 200.0)
        ms = (detected_ns - inject_ns) / 1e6
        row["detected_by"] = first
        row["detection_ms"] = round(ms, 2)
        row["detection_cycles"] = round(ms / period_ms, 2)
        limit = _limit_cycles(sc, cfg, first)
        row["detection_limit_cycles"] = limit
        row["detection_within_limit"] = limit is None or ms / period_ms <= limit
    freezes = summary.get("plant", {}).get("freezes") or []
    frozen: dict[str, float] = {}
    for f in freezes:
        if f.get("monotonic_ns", 0) >= inject_ns > 0 and f["robot"] not in frozen:
            frozen[f["robot"]] = f["monotonic_ns"]
    if sc.node != "plant":
        row["frozen"] = sorted(frozen)
        row["all_frozen"] = set(frozen) >= {"r1", "r2"}
        if frozen and detected_ns is not None:
            row["freeze_ms"] = round((max(frozen.values()) - detected_ns) / 1e6, 2)
    row["estop_every_node"] = bool(nodes) and all(n.get("result") != "ok" for n in nodes.values())
    row["processes_left"] = len(_pids_of(sid)) if sid else 0
    row["ipc_left"] = _ipc_left(sid) if sid else []
    valid = []
    for r in ("r1", "r2"):
        try:
            positions.read(runs / "positions" / f"{r}.json", [r])
            valid.append(r)
        except positions.PositionsUnknown as exc:
            row.setdefault("positions_problems", []).append(str(exc))
    row["positions_valid"] = valid == ["r1", "r2"]
    row["passed"] = bool(
        got in sc.expect
        and sc.reason in row["cause"]
        and row.get("detection_within_limit", sc.limit == "death" and sc.proc == "manager")
        and (sc.node == "plant" or row.get("all_frozen"))
        and row["processes_left"] == 0
        and not row["ipc_left"]
    )
    return row

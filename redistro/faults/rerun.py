"""An earlier run's records sent again in a later run that shares its key.

Nodes started alone share ``ddm.key_file``, so a record of one run is
signed as well as one of the next. The scenario: a session with a key file
runs the drill's first segment while an eavesdropper records every record
its SSC sends to r2 (the ``ddm.capture`` point); a second session with the
same key file starts, and before its SSC comes up a client without the key
connects to r2's ddm and sends the recording (the SSC's hello, then its
commands; the session's SSC, started beside its ESCs, has its ddm held by
``ddm.hold`` until the client is done). The second session must end
``ok``: r2's ddm answers the hello with a challenge the client cannot
meet, refuses every recorded command (not signed with this run's key:
counted ``forged``), gives the client's connection up, and takes its own
SSC when it comes; no recorded command is ever admitted (the command
latency would show run 1's stamps).
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import subprocess
import time
from pathlib import Path
from typing import Any

from redistro.config.model import Config
from redistro.faults.catalogue import Scenario
from redistro.faults.common import count_of, die_with_parent, ipc_left, pids_of, session_id

SESSION_TIMEOUT_S = 120.0


def _session(
    args: list[str], task: str, out: Path, env: dict[str, str] | None = None
) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [*args, "session", task, "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=env,
        preexec_fn=die_with_parent,
    )


def _replay(port: int, records: bytes, until: float, proc: subprocess.Popen[str]) -> dict[str, Any]:
    """Connect to r2's ddm as soon as it listens and send the recording;
    what the ddm answered, and whether it gave the connection up."""
    from redistro.ddm import record as wire
    from redistro.ddm.sockets import self_connected

    out: dict[str, Any] = {"connected": False, "answers": 0, "given_up": False}
    while time.monotonic() < until and proc.poll() is None:
        try:
            sock = socket.create_connection(("127.0.0.1", port), timeout=0.05)
        except OSError:
            time.sleep(0.005)  # r2's ddm does not listen yet: try again (to a deadline)
            continue
        if self_connected(sock):  # (it would keep r2's ddm from listening)
            sock.close()
            continue
        out["connected"] = True
        with sock:
            sock.settimeout(0.2)
            with contextlib.suppress(OSError):
                sock.sendall(records)
            end = time.monotonic() + 5.0
            while time.monotonic() < end:
                try:
                    data = sock.recv(wire.SIZE)
                except TimeoutError:
                    continue
                except OSError:
                    data = b""
                if not data:
                    out["given_up"] = True
                    break
                out["answers"] += 1  # (the challenge to the recorded hello)
        return out
    return out


def _record_run1(out_dir: Path, keyed: list[str], task: str) -> bytes:
    """Run 1, with every record its SSC sends to r2 recorded (``ddm.capture``)."""
    from redistro.faults.inject import ENV, arm
    from redistro.process import hooks

    trigger = out_dir / "capture.trigger"
    trigger.touch()  # recording from the start
    env = os.environ.copy()
    env[ENV] = arm("ddm.capture", str(trigger), node="ssc", robot="r2")
    env[hooks.ENV] = "redistro.faults.hooks"
    first = _session(keyed, task, out_dir / "run1", env)
    try:
        first.communicate(timeout=SESSION_TIMEOUT_S)
    finally:
        if first.poll() is None:
            first.kill()
            first.communicate()
    recording = Path(f"{trigger}.records")
    return recording.read_bytes() if recording.exists() else b""


def run_rerun_replay(
    sc: Scenario, out_dir: Path, cfg: Config, args: list[str], task: str
) -> dict[str, Any]:
    from redistro.ddm import record as wire
    from redistro.ddm.sockets import esc_port
    from redistro.errors import RedistroError
    from redistro.faults.inject import ENV, arm
    from redistro.process import hooks

    key = out_dir / "link.key"
    wire.new_key(key)
    keyed = [*args, "--set", f"ddm.key_file={key}", "--set", "ddm.transport=socket"]
    records = _record_run1(out_dir, keyed, task)
    kinds = [records[i + 6] for i in range(0, len(records) - wire.SIZE + 1, wire.SIZE)]
    row: dict[str, Any] = {
        "recorded_hellos": kinds.count(wire.KIND_HELLO),
        "recorded_commands": kinds.count(wire.KIND_COMMAND),
    }
    # run 2, with the recording sent to r2's ddm before its own SSC comes
    release = out_dir / "hold.trigger"
    env2 = os.environ.copy()
    env2[ENV] = arm("ddm.hold", str(release), node="ssc")
    env2[hooks.ENV] = "redistro.faults.hooks"
    second = _session(keyed, task, out_dir / "run2", env2)
    assert second.stdout is not None
    deadline = time.monotonic() + SESSION_TIMEOUT_S
    sid = ""
    try:
        sid = session_id(second, deadline)
        row.update(_replay(esc_port(cfg, sid, "r2"), records, deadline, second))
        release.touch()  # the SSC's ddm may connect now
        second.communicate(timeout=max(1.0, deadline - time.monotonic()))
    except (RedistroError, subprocess.TimeoutExpired) as exc:
        row["error"] = str(exc) or "the second session did not end in time"
    finally:
        release.touch()
        if second.poll() is None:
            second.kill()
            second.communicate()
    try:
        summary = json.loads((out_dir / "run2" / "summary.json").read_text())
    except (OSError, ValueError):
        summary = {}
    ddm = summary.get("ddm", {}).get("esc.r2", {})
    latency = ddm.get("command_latency_us") or {}
    row.update(
        got=summary.get("result", "no summary"),
        cause=summary.get("reason", ""),
        count={"forged": count_of(ddm, "forged")},
        command_latency_max_us=latency.get("max"),
    )
    row["processes_left"] = len(pids_of(sid)) if sid else 0
    row["ipc_left"] = ipc_left(sid) if sid else []
    row["passed"] = bool(
        "error" not in row
        and row["recorded_hellos"] > 0
        and row["recorded_commands"] > 0
        and row.get("connected")
        and row.get("given_up")
        and row["got"] in sc.expect
        and row["count"]["forged"] > 0
        and latency.get("max") is not None
        and latency["max"] < 1e6  # no command of run 1 admitted
        and row["processes_left"] == 0
        and not row["ipc_left"]
    )
    return row

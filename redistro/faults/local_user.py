"""Another local user against a session (the harness, as root, acts for them
in a child process of uid ``OTHER``).

- ``card-squat``: that user holds memory-card keys of the project's range
  (``SQUATS`` of them, drawn at random) while a session runs over reflective
  memory: the session draws its cards' keys elsewhere and ends ``ok``; no
  clean-up removes the other user's cards.
- ``out-planted-links``: that user's folder, writable by all, holding links
  named as a run folder's files (``summary.json.tmp``, ``messages.log``, ...)
  to a private file of ours, given as ``session --out``: refused before
  anything starts, naming the owner; the private file unchanged.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
from pathlib import Path
from typing import Any

from redistro.faults.catalogue import Scenario
from redistro.faults.common import die_with_parent, ipc_left, one_line_refusal, pids_of, sid_from

OTHER = 12345
SQUATS = 256
LINKS = ("summary.json.tmp", "summary.json", "messages.log", "plant.json", "session.mcap")


def as_other(make: Any) -> None:
    """``make()`` in a child process of uid OTHER (forked: modules loaded)."""
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        code = 1
        try:
            os.setgid(OTHER)
            os.setuid(OTHER)
            make()
            code = 0
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        raise OSError(f"the other user's process failed (status {status})")


def run_local_user(
    sc: Scenario, out_dir: Path, session_args: list[str], task: str
) -> dict[str, Any]:
    if os.getuid() != 0:
        return {"got": "skipped", "cause": "acting as another user needs root", "passed": False}
    if sc.action == "card-squat":
        return _card_squat(sc, out_dir, session_args, task)
    return _planted_links(sc, out_dir, session_args, task)


def _card_squat(sc: Scenario, out_dir: Path, session_args: list[str], task: str) -> dict[str, Any]:
    import random

    import sysv_ipc

    from redistro.ipc import sysv

    free = [k for k in range(sysv.KEY_BASE, sysv.KEY_BASE + 0x10000) if k not in sysv.our_keys()]
    keys = random.Random(7).sample(free, SQUATS)

    def squat() -> None:
        for key in keys:
            sysv_ipc.SharedMemory(key, sysv_ipc.IPC_CREX, size=64, mode=0o644)

    row: dict[str, Any] = {}
    as_other(squat)
    try:
        done = subprocess.run(
            [*session_args, "--set", "ddm.transport=reflective", "session", task,
             "--out", str(out_dir / "run")],
            capture_output=True, text=True, timeout=300, check=False,
            preexec_fn=die_with_parent,
        )  # fmt: skip
        sid = sid_from(done.stdout)
        import json

        try:
            summary = json.loads((out_dir / "run" / "summary.json").read_text())
        except (OSError, ValueError):
            summary = {}
        kept = [k for k in keys if _creator(k) == OTHER]
        row.update(
            got=summary.get("result", f"exit {done.returncode}"),
            cause=summary.get("reason", ""),
            squatted=SQUATS,
            squats_kept=len(kept),
            processes_left=len(pids_of(sid)) if sid else 0,
            ipc_left=ipc_left(sid) if sid else [],
        )
    finally:
        for key in keys:  # (the other user's cards: ours to remove, as root)
            with contextlib.suppress(sysv_ipc.Error):
                sysv_ipc.SharedMemory(key).remove()
    row["passed"] = bool(
        row.get("got") in sc.expect
        and row.get("squats_kept") == SQUATS
        and row.get("processes_left") == 0
        and not row["ipc_left"]
    )
    return row


def _creator(key: int) -> int:
    import sysv_ipc

    try:
        return int(sysv_ipc.SharedMemory(key).cuid)
    except sysv_ipc.Error:
        return -1


def _planted_links(
    sc: Scenario, out_dir: Path, session_args: list[str], task: str
) -> dict[str, Any]:
    victim = out_dir / "private"
    victim.write_text("private\n")
    victim.chmod(0o600)
    trap = out_dir / "trap"
    trap.mkdir()
    os.chmod(trap, 0o777)
    for name in LINKS:
        (trap / name).symlink_to(victim)
    os.chown(trap, OTHER, OTHER)
    before = set(os.listdir("/dev/shm"))
    done = subprocess.run(
        [*session_args, "session", task, "--out", str(trap)],
        capture_output=True, text=True, timeout=120, check=False,
        preexec_fn=die_with_parent,
    )  # fmt: skip
    row: dict[str, Any] = one_line_refusal(done)
    row.update(
        victim_intact=victim.read_text() == "private\n",
        links_untouched=sorted(p.name for p in trap.iterdir()) == sorted(LINKS),
        ipc_left=sorted(set(os.listdir("/dev/shm")) - before),
        processes_left=0,
        plant_started="plant running" in done.stdout,
    )
    row["passed"] = bool(
        row["got"] == "refused"
        and row["one_line"]
        and f"owned by uid {OTHER}" in row["cause"]
        and row["victim_intact"]
        and row["links_untouched"]
        and not row["plant_started"]
        and not row["ipc_left"]
    )
    return row

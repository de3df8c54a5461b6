"""What every part of the fault harness shares: how it starts a child, reads
a session's id and a refused command line's end, finds what a session left
behind, and sums a counter of a summary."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

from redistro.errors import RedistroError


def die_with_parent() -> None:
    """preexec_fn of every child the harness starts: SIGTERM when the harness
    dies (a killed harness must not leave a session running beside the next)."""
    from redistro.ipc import signals

    signals.set_parent_death_signal(signal.SIGTERM)


def one_line_refusal(done: subprocess.CompletedProcess[str]) -> dict[str, Any]:
    """How a refused command line ended: exit code, its one line, no traceback."""
    lines = [ln for ln in done.stderr.strip().splitlines() if ln.strip()]
    return {
        "got": "refused" if done.returncode == 2 else f"exit {done.returncode}",
        "exit_code": done.returncode,
        "cause": lines[-1] if lines else "",
        "one_line": len(lines) == 1 and "Traceback" not in done.stderr,
    }


class StopWatch:
    """A stop signal to the harness (Ctrl-C, SIGTERM, SIGHUP: blocked in
    every thread, as in every entry point) ends it in order: a thread of its
    own takes the signal, passes SIGINT to the harness's children (a
    session's owner then ends it: the robot frozen, nothing left behind),
    and no further scenario starts (:attr:`signal` says which came)."""

    def __init__(self) -> None:
        from redistro.ipc import signals

        self.signal = 0
        self._stops = signals.STOP_SIGNALS
        threading.Thread(target=self._watch, name="stop-watch", daemon=True).start()

    def requested(self) -> int:
        """The stop signal taken, or 0."""
        return self.signal

    def _watch(self) -> None:
        from redistro.ipc import signals

        self.signal = signal.sigwait(self._stops)
        for pid in signals.children_of(os.getpid()):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGINT)


def session_id(proc: subprocess.Popen[str], deadline: float, task: str = "fault_drill") -> str:
    """The session id of ``task``, from the CLI's first lines."""
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
        elif line.startswith(f"task {task}") and last:
            return last
    said = " | ".join(line for line in seen[-4:] if not line.startswith("["))
    raise RedistroError(f"the {task} session did not start: {said}")


def pids_of(sid: str) -> list[int]:
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


# the memory cards of this user before the harness began (their keys are
# random: a card of a scenario's session is one that was not there then)
_CARDS_BEFORE: set[int] | None = None


def _cards_now() -> set[int]:
    from redistro.ipc import sysv

    return sysv.our_keys(os.getuid())


def ipc_left(sid: str) -> list[str]:
    """The session's POSIX objects still in /dev/shm, and every memory card
    of this user made since the harness began."""
    global _CARDS_BEFORE
    left = [e for e in os.listdir("/dev/shm") if sid in e]
    if _CARDS_BEFORE is None:
        _CARDS_BEFORE = _cards_now()
        return left
    left += [f"sysv {key:#010x}" for key in sorted(_cards_now() - _CARDS_BEFORE)]
    return left


def count_of(doc: Any, key: str) -> int:
    """The sum of every integer under ``key`` anywhere in ``doc``."""
    if isinstance(doc, dict):
        total = 0
        for k, v in doc.items():
            if k == key and isinstance(v, int) and not isinstance(v, bool):
                total += v
            else:
                total += count_of(v, key)
        return total
    if isinstance(doc, list):
        return sum(count_of(v, key) for v in doc)
    return 0


# -- what the next start finds --


def sid_from(stdout: str) -> str:
    """The session id a ``redistro session`` printed first ('' if none)."""
    for line in stdout.splitlines():
        if line.startswith("session "):
            return line.split()[1]
    return ""

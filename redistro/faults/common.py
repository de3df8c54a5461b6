"""What every part of the fault harness shares: how it starts a child, and
how it reads a refused command line's end."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import threading
from typing import Any


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

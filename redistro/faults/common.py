"""What every part of the fault harness shares: how it starts a child, and
how it reads a refused command line's end."""

from __future__ import annotations

import signal
import subprocess
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

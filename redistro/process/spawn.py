"""Start redistro processes with fork+exec (``python -m redistro.process ...``)."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Sequence

THREAD_ENV = {
    "OPENBLAS_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
}


def spawn(
    args: Sequence[str], *, pass_fds: Sequence[int] = (), env: dict[str, str] | None = None
) -> subprocess.Popen[bytes]:
    """Fork+exec a fresh interpreter running ``redistro.process`` with ``args``.

    The child inherits the caller's signal mask (the runtime signals stay
    blocked across exec) and gets one thread per math library.
    """
    child_env = os.environ.copy()
    child_env.update(THREAD_ENV)
    if env:
        child_env.update(env)
    return subprocess.Popen(
        [sys.executable, "-m", "redistro.process", *args],
        env=child_env,
        pass_fds=tuple(pass_fds),
        close_fds=True,
        stdin=subprocess.DEVNULL,
    )

"""Profile one process of a session: cProfile around its routine.

    python tools/profile.py TASK NODE/WORKER [--set KEY=VALUE ...] [--top N]

(NODE/manager profiles the node's manager, NODE/logwriter its log's writer,
plant/loop the plant's loop.)

runs ``redistro session TASK`` with that one process under cProfile (every
other process runs as usual; the profiled one runs about twice as slow, so
its figures are for where the time goes, not how much), then prints its
functions by own time and writes ``profile-<node>-<worker>.pstats`` into the
session's run folder (open it with ``python -m pstats`` or snakeviz).
Example: ``python tools/profile.py tasks/peg_insertion_short.yaml esc.r2/ddm``.
For native frames (OpenSSL, PyBullet, the kernels), attach py-spy to the
running process instead: ``py-spy record --native -p PID``.
"""

from __future__ import annotations

import argparse
import os
import pstats
import subprocess
import sys
import tempfile
from pathlib import Path

from redistro.process import hooks


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tools/profile.py", description=__doc__.splitlines()[0])
    ap.add_argument("task")
    ap.add_argument("process", help="NODE/WORKER, e.g. esc.r2/ddm or ssc/worker")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--top", type=int, default=25)
    a = ap.parse_args(argv)
    node, _, worker = a.process.partition("/")
    if not node or not worker:
        print(f"tools/profile.py: {a.process!r}: expected NODE/WORKER", file=sys.stderr)
        return 2
    out = Path(tempfile.mkdtemp(prefix="redistro-profile-"))
    env = dict(os.environ, **{hooks.PROFILE_ENV: a.process, hooks.PROFILE_OUT_ENV: str(out)})
    sets = [x for kv in a.set for x in ("--set", kv)]
    cmd = [sys.executable, "-m", "redistro.cli", *sets, "session", a.task, "--out", str(out)]
    rc = subprocess.run(cmd, env=env, check=False).returncode
    stats = out / f"profile-{node}-{worker}.pstats"
    if not stats.exists():
        why = f"{a.process} is not a process of this session, or it never reached its cycles"
        print(f"tools/profile.py: no profile written ({why}); exit {rc}", file=sys.stderr)
        return 1
    pstats.Stats(str(stats)).sort_stats("tottime").print_stats(a.top)
    print(f"session exit {rc}; statistics in {stats}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Helpers for integration tests: run the CLI, find a running session, wait on conditions."""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from redistro.localdata import LocalData, ProcState

ROOT = Path(__file__).resolve().parent.parent
# Run folders of test sessions go to a temporary place, not the repo's runs/.
RUNS = tempfile.mkdtemp(prefix="redistro-test-runs-")
atexit.register(shutil.rmtree, RUNS, True)  # (ignore_errors)
REDISTRO = [sys.executable, "-m", "redistro.cli", "--set", f"session.runs_dir={RUNS}"]


def bench_cycle(rate: str, workers: str, seconds: str, out: Path | str) -> list[str]:
    """Arguments for a cycle benchmark run without the cyclictest baseline."""
    return [
        "bench",
        "cycle",
        "--rate",
        rate,
        "--workers",
        workers,
        "--seconds",
        seconds,
        "--no-baseline",
        "--json",
        str(out),
    ]


# the tests whose verdicts come from the plant's truth, not from timing,
# run their sessions in lockstep: the plant paces the nodes, as fast as the
# CPUs allow (the real-time promise has tests of its own). A lockstep run's
# data do not depend on the schedule: at SCHED_BATCH (scheduling.policy
# batch), these sessions run beside the real-time ones without taking their
# CPUs, and with fewer switches than at the default policy.
LOCKSTEP = ("--set", "session.clock=lockstep", "--set", "scheduling.policy=batch")


def run_cli(
    *args: str, timeout: float = 120, cwd: Path = ROOT, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    """The CLI run to its end (``env``: more environment for it)."""
    return subprocess.run(
        [*REDISTRO, *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=cwd,
        check=False,
        env={**os.environ, **env} if env else None,
    )


def start_cli(*args: str, new_session: bool = False, cwd: Path = ROOT) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [*REDISTRO, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=cwd,
        start_new_session=new_session,
    )


def read_session_id(proc: subprocess.Popen[str]) -> str:
    assert proc.stdout is not None
    line = proc.stdout.readline()  # the CLI prints "session <id>" first, then flushes
    assert line.startswith("session "), f"unexpected first line {line!r}"
    return line.split()[1]


def wait_for(predicate: Callable[[], Any], timeout: float, what: str) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.01)  # polling a condition with a deadline


def attach_running(session_id: str, node: str, min_cycle: int, timeout: float = 30) -> LocalData:
    """Attach to a node's Local Data once every worker is in Routine and cycles run."""

    def attempt() -> LocalData | None:
        try:
            ld = LocalData.attach(session_id, node)
        except Exception:
            return None
        ok = int(ld.block("manager").read()["cycle"]) >= min_cycle and all(
            int(ld.block("proc", j).read()["state"]) == ProcState.ROUTINE for j in range(ld.n_procs)
        )
        if ok:
            return ld
        ld.close()
        return None

    ld: LocalData = wait_for(attempt, timeout, f"{node} of {session_id} to run")
    return ld


def pid_gone(pid: int) -> bool:
    with contextlib.suppress(ChildProcessError):
        os.waitpid(pid, os.WNOHANG)
    try:
        stat = Path(f"/proc/{pid}/stat").read_bytes()
    except OSError:
        return True
    return stat[stat.rfind(b")") + 2 :].split()[0] == b"Z"


def copy_runs(calibrated: Path, tmp_path: Path) -> Path:
    """A private copy of the calibrated runs folder (positions and the arms' pose)."""
    import shutil

    runs = tmp_path / "runs"
    shutil.copytree(calibrated, runs)
    return runs


def load_json(path: Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads(path.read_text())
    return data


def session_entries(session_id: str) -> list[str]:
    return sorted(e for e in os.listdir("/dev/shm") if session_id in e)


@contextlib.contextmanager
def esc_segment(
    procs: list[tuple[str, str, int]], memory: bool = False
) -> Iterator[tuple[str, LocalData]]:
    """A real Local Data segment of an ESC node ``esc.r1`` at 200 Hz, in a
    session of its own, with these (name, role, stage) processes: the
    session's id and the segment, unlinked at the end. memory: the
    in-process stand-in (no POSIX object, no session folder)."""
    from redistro.ipc.names import new_session_id
    from redistro.ipc.session import Session

    with contextlib.nullcontext(None) if memory else Session.create() as session:
        sid = session.id if session is not None else new_session_id()
        seg = LocalData.create(
            sid,
            "esc.r1",
            node_kind="esc",
            proc_names=[p[0] for p in procs],
            proc_roles=[p[1] for p in procs],
            proc_stages=[p[2] for p in procs],
            robot_names=["r1"],
            rate_hz=200.0,
            period_ns=5_000_000,
            heartbeat_limit_cycles=5,
            manifest=session.manifest if session is not None else None,
            memory=memory,
        )
        try:
            yield sid, seg
        finally:
            seg.close()
            seg.unlink()


def make_test_ca(folder: Path, names: tuple[str, ...] = ("ssc", "esc")) -> dict[str, Path]:
    """A certificate authority of the tests' own (openssl, EC P-256, two
    days), and for each of ``names`` a certificate for ``localhost`` and
    127.0.0.1 signed by it (server and client use): ``ca``, ``<name>.pem``,
    ``<name>.key`` (mode 0600) in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)

    def openssl(*args: str) -> None:
        subprocess.run(["openssl", *args], check=True, capture_output=True, timeout=60)

    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    ca, ca_key = folder / "ca.pem", folder / "ca.key"
    openssl("req", "-x509", *ec, "-keyout", str(ca_key), "-out", str(ca), "-days", "2",
            "-subj", f"/CN=redistro test CA {folder.name}",
            "-addext", "basicConstraints=critical,CA:TRUE",
            "-addext", "keyUsage=critical,keyCertSign,cRLSign")  # fmt: skip
    ext = folder / "leaf.ext"
    ext.write_text(
        "basicConstraints=critical,CA:FALSE\n"
        "keyUsage=critical,digitalSignature\n"
        "extendedKeyUsage=serverAuth,clientAuth\n"
        "subjectAltName=DNS:localhost,IP:127.0.0.1\n"
    )
    out = {"ca": ca}
    for name in names:
        key, csr, pem = folder / f"{name}.key", folder / f"{name}.csr", folder / f"{name}.pem"
        openssl("req", *ec, "-keyout", str(key), "-out", str(csr), "-subj", "/CN=localhost")
        sign = ["-CA", str(ca), "-CAkey", str(ca_key), "-CAcreateserial", "-days", "2"]
        openssl("x509", "-req", "-in", str(csr), *sign, "-out", str(pem), "-extfile", str(ext))
        os.chmod(key, 0o600)
        out[f"{name}.pem"], out[f"{name}.key"] = pem, key
    return out

"""cyclictest as the timer-latency baseline, run in the same invocation."""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import subprocess
from typing import Any


def _rr_permitted(priority: int) -> bool:
    try:
        param = os.sched_getparam(0)
        policy = os.sched_getscheduler(0)
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(priority))
        os.sched_setscheduler(0, policy, param)
    except OSError:
        return False
    return True


def histogram_percentiles(text: str, period_us: float = 0.0) -> dict[str, Any] | None:
    """Parse ``cyclictest -h`` output: (p50, p99, max) in µs, the sample count and,
    given ``period_us``, the fraction of wake-ups later than one period."""
    buckets: list[tuple[int, int]] = []
    overflows = 0
    max_us = None
    for line in text.splitlines():
        if line.startswith("# Histogram Overflows:"):
            overflows = int(line.split(":")[1].split()[0])
        elif line.startswith("# Max Latencies:"):
            max_us = int(line.split(":")[1].split()[0])
        elif line and line[0].isdigit():
            parts = line.split()
            if len(parts) >= 2:
                buckets.append((int(parts[0]), int(parts[1])))
    total = sum(c for _, c in buckets) + overflows
    if not total or max_us is None:
        return None

    def pct(p: float) -> float:
        need = math.ceil(p * total)
        seen = 0
        for us, count in buckets:
            seen += count
            if seen >= need:
                return float(us)
        return float(max_us)  # in the overflow bucket

    out: dict[str, Any] = {
        "p50": pct(0.50),
        "p99": pct(0.99),
        "max": float(max_us),
        "samples": total,
    }
    if period_us:
        late = sum(c for us, c in buckets if us > period_us) + overflows
        out["over_period_fraction"] = round(late / total, 6)
    return out


def cyclictest(rate_hz: float, seconds: float, priority: int) -> dict[str, Any] | None:
    """Timer wake-up latency of one cyclictest thread at ``rate_hz`` for ``seconds``.

    Returns None when cyclictest is not on PATH.
    """
    exe = shutil.which("cyclictest")
    if exe is None:
        return None
    interval_us = max(1, round(1e6 / rate_hz))
    cmd = [
        exe,
        "-q",
        "-m",
        "-t",
        "1",
        "-i",
        str(interval_us),
        "-D",
        f"{max(1, math.ceil(seconds))}s",
        "-h",
        "20000",
    ]
    if _rr_permitted(priority):
        cmd += ["-p", str(priority), "--policy=rr"]
    else:
        cmd += ["--policy=other"]
    try:
        done = subprocess.run(
            cmd, capture_output=True, text=True, timeout=seconds + 30, check=False
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        return {"error": str(exc), "command": " ".join(cmd)}
    stats = histogram_percentiles(done.stdout, interval_us)
    if stats is None:
        return {"error": (done.stderr or done.stdout).strip()[:200], "command": " ".join(cmd)}
    stats["command"] = " ".join(cmd)
    return stats


class Cyclictest:
    """cyclictest running beside a benchmark, for its whole length: one thread
    at ``rate_hz`` (at ``priority`` under SCHED_RR when permitted). ``stop()``
    ends it (SIGINT, as Ctrl-C) and returns its figures, or None when it is
    not installed.

    Started with posix_spawn and an empty signal mask: this process blocks
    SIGINT (it takes signals synchronously), and a child inherits the mask."""

    def __init__(self, rate_hz: float, priority: int) -> None:
        import tempfile

        self.pid = 0
        self.interval_us = max(1, round(1e6 / rate_hz))
        exe = shutil.which("cyclictest")
        if exe is None:
            return
        cmd = [exe, "-q", "-m", "-t", "1", "-i", str(self.interval_us), "-h", "20000"]
        if _rr_permitted(priority):
            cmd += ["-p", str(priority), "--policy=rr"]
        else:
            cmd += ["--policy=other"]
        self.command = " ".join(cmd)
        self.out = tempfile.TemporaryFile(mode="w+")  # noqa: SIM115 (closed in stop)
        self.pid = os.posix_spawn(
            exe,
            cmd,
            os.environ,
            file_actions=[
                (os.POSIX_SPAWN_DUP2, self.out.fileno(), 1),
                (os.POSIX_SPAWN_DUP2, self.out.fileno(), 2),
            ],
            setsigmask=(),
            setsid=True,
        )
        from redistro.process.session_owner import SPARED

        SPARED.add(self.pid)  # a session's reaping must leave it running

    def stop(self) -> dict[str, Any] | None:
        if not self.pid:
            return None
        import signal
        import time

        from redistro.process.session_owner import SPARED

        with contextlib.suppress(ProcessLookupError):
            os.kill(self.pid, signal.SIGINT)
        deadline = time.monotonic() + 10
        while os.waitpid(self.pid, os.WNOHANG) == (0, 0):
            if time.monotonic() > deadline:
                os.kill(self.pid, signal.SIGKILL)
                os.waitpid(self.pid, 0)
                break
            time.sleep(0.02)  # cyclictest prints its histogram on the way out
        SPARED.discard(self.pid)
        self.out.seek(0)
        text = self.out.read()
        self.out.close()
        stats = histogram_percentiles(text, self.interval_us)
        if stats is None:
            return {"error": text.strip()[-200:], "command": self.command}
        stats["command"] = self.command
        return stats


def cpu_busy_ticks(stat_path: str = "/proc/stat") -> dict[str, tuple[int, int]]:
    """Per CPU (busy, total) time in USER_HZ ticks, steal left out of both:
    how busy the machine itself was."""
    out: dict[str, tuple[int, int]] = {}
    try:
        with open(stat_path) as f:
            for line in f:
                parts = line.split()
                if parts and parts[0].startswith("cpu") and parts[0] != "cpu" and len(parts) > 8:
                    # user nice system idle iowait irq softirq steal
                    v = [int(x) for x in parts[1:9]]
                    total = sum(v[:7])
                    out[parts[0]] = (total - v[3] - v[4], total)
    except OSError:
        return {}
    return out


def busy_report(
    before: dict[str, tuple[int, int]], after: dict[str, tuple[int, int]]
) -> dict[str, float]:
    """Per CPU, the share of the run's time it was busy [%] (every process on the host)."""
    out: dict[str, float] = {}
    for cpu, (b1, t1) in after.items():
        if cpu in before:
            b0, t0 = before[cpu]
            out[cpu] = round(100 * (b1 - b0) / (t1 - t0), 1) if t1 > t0 else 0.0
    return out


def cpu_steal_ticks(stat_path: str = "/proc/stat") -> dict[str, int]:
    """Per-CPU 'steal' time (USER_HZ ticks): time the hypervisor ran something
    else while this vCPU wanted to run. Empty where the kernel does not say."""
    out: dict[str, int] = {}
    try:
        with open(stat_path) as f:
            for line in f:
                parts = line.split()
                if parts and parts[0].startswith("cpu") and parts[0] != "cpu" and len(parts) > 8:
                    out[parts[0]] = int(parts[8])
    except OSError:
        return {}
    return out


def steal_report(before: dict[str, int], after: dict[str, int], seconds: float) -> dict[str, Any]:
    """Steal per CPU over a run, in ms and as a share of the run's wall time."""
    hz = os.sysconf("SC_CLK_TCK")
    per_cpu = {
        cpu: round((after[cpu] - before[cpu]) * 1000 / hz, 1) for cpu in after if cpu in before
    }
    return {
        "ms": per_cpu,
        "percent_of_run": {
            cpu: round(ms / (10 * seconds), 3) if seconds > 0 else 0.0
            for cpu, ms in per_cpu.items()
        },
        "seconds": round(seconds, 3),
    }

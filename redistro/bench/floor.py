"""The socket floor: what one ddm exchange costs the kernel and the
interpreter alone, measured in the same ``bench group`` run.

Two processes at the ddms' real-time priority play the socket transport's
send/receive/reply over TCP loopback and nothing else: the caller sends a
record of a command's size at the node rate, the replier wakes in epoll,
receives it and sends a feedback-sized reply. The replier's CPU for its
receive and send (``thread_time`` around the two calls, as a ddm's step CPU
is taken around its step) is the floor under an ESC ddm's exchange on this
host, at this moment: no record is checked, encoded or copied.

Run as ``python -m redistro.bench.floor --rate HZ --seconds S`` (the caller;
it starts the replier with fork+exec); prints one JSON line.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import select
import socket
import subprocess
import sys
import time
from typing import Any

COMMAND_BYTES = 120  # about a command record
REPLY_BYTES = 180  # about a feedback record


def _percentiles(ns: list[int]) -> dict[str, float]:
    ns.sort()
    n = len(ns)
    if not n:
        return {}
    return {
        "p50": round(ns[n // 2] / 1e3, 1),
        "p99": round(ns[min(n - 1, int(n * 0.99))] / 1e3, 1),
        "max": round(ns[-1] / 1e3, 1),
        "samples": n,
    }


def _real_time(priority: int) -> None:
    # refused: the floor is then measured at the default policy
    with contextlib.suppress(OSError):
        os.sched_setscheduler(0, os.SCHED_RR | os.SCHED_RESET_ON_FORK, os.sched_param(priority))


def _replier(port: int, count: int, priority: int) -> int:
    s = socket.create_connection(("127.0.0.1", port))
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    _real_time(priority)
    ep = select.epoll()
    ep.register(s.fileno(), select.EPOLLIN)
    buf = bytearray(4 * COMMAND_BYTES)
    reply = bytes(REPLY_BYTES)
    cpu: list[int] = []
    clock = time.thread_time_ns
    for _ in range(count):
        if not ep.poll(1.0):
            break
        c0 = clock()
        if not s.recv_into(buf):
            break
        s.send(reply)
        cpu.append(clock() - c0)
    print(json.dumps(_percentiles(cpu)), flush=True)
    return 0


def measure(rate_hz: float, seconds: float, priority: int) -> dict[str, Any]:
    """The floor at ``rate_hz`` for ``seconds`` (run in a fresh interpreter)."""
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "redistro.bench.floor",
            "--rate",
            str(rate_hz),
            "--seconds",
            str(seconds),
            "--priority",
            str(priority),
        ],
        capture_output=True,
        text=True,
        timeout=seconds + 30,
        check=False,
    )
    try:
        return dict(json.loads(out.stdout.strip().splitlines()[-1]))
    except (ValueError, IndexError):
        return {"error": (out.stderr.strip().splitlines() or ["no output"])[-1]}


def _caller(rate_hz: float, seconds: float, priority: int) -> int:
    count = max(1, int(rate_hz * seconds))
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(1)
    port = listener.getsockname()[1]
    child = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "redistro.bench.floor",
            "--reply",
            str(port),
            "--count",
            str(count),
            "--priority",
            str(priority),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        listener.settimeout(10.0)
        s, _ = listener.accept()
        s.settimeout(1.0)
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        _real_time(priority)
        command = bytes(COMMAND_BYTES)
        buf = bytearray(4 * REPLY_BYTES)
        period = 1.0 / rate_hz
        due = time.monotonic()
        for _ in range(count):
            due += period
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            s.send(command)
            s.recv_into(buf)
        out, _ = child.communicate(timeout=10.0)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
        listener.close()
    figures = json.loads(out.strip().splitlines()[-1])
    figures.update(rate_hz=rate_hz, seconds=seconds)
    print(json.dumps({"reply_cpu_us": figures}), flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m redistro.bench.floor")
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--priority", type=int, default=19)
    ap.add_argument("--reply", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--count", type=int, default=0, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.reply:
        return _replier(a.reply, a.count, a.priority)
    return _caller(a.rate, a.seconds, a.priority)


if __name__ == "__main__":
    sys.exit(main())

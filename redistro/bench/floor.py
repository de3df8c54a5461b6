"""The DDM floor: what a command's way from the SSC worker to an ESC ddm,
and one ddm exchange, cost the kernel and the interpreter alone, measured in
the same ``bench group`` run.

Three processes play the path with nothing else to do: a *worker* (the
caller) stamps the time into an eventfd at the node rate, as the SSC worker
wakes its ddm after each command; a *forwarder* at the ddms' real-time
priority wakes in epoll, reads the stamp and sends a command-sized record
over TCP loopback, then takes the reply, as the SSC ddm does; a *replier*
at the same priority wakes in epoll, receives the record and sends a
feedback-sized reply, as an ESC ddm does. No record is checked, encoded or
copied into Local Data. With ``--robots N`` there are N repliers, and the
forwarder sends to them in turn (the order reversed every other step), as
the SSC's ddm sends a group's N commands: the floor under ``bench ddm
--robots N``.

- ``reply_cpu_us``: the replier's CPU for its receive and send
  (``thread_time`` around the two calls, as a ddm's step CPU is taken around
  its step): the floor under an ESC ddm's exchange.
- ``latency_us``: from the worker's stamp to the replier's clock after its
  receive: the floor under the DDM command latency (two wake-ups, one TCP hop).

Both are the worst replier's percentiles when there are several.

- ``stamps``, ``exchanges``, ``coalesced``: the stamps the worker wrote, the
  forwarder's exchanges, and the stamps it found beside another in one
  wake-up (the worker late, its stamps back to back: the last is sent).
  Every stamp is one or the other; a run ends on the last stamp taken.

The caller holds the CPUs' wake-up latency as the nodes do
(``--cpu-latency US``, ``scheduling.cpu_latency_us``). Run as
``python -m redistro.bench.floor --rate HZ --seconds S``; prints one JSON
line. Every process is started with fork+exec.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import mmap
import os
import select
import socket
import subprocess
import sys
import time
from typing import Any

from redistro.ipc import sched

COMMAND_BYTES = 120  # about a command record
REPLY_BYTES = 180  # about a feedback record
READY_S = 20.0  # the forwarder's start-up, at most (a loaded host)


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


def _worst(rows: list[dict[str, float]]) -> dict[str, float]:
    """Each percentile's worst over the robots (their samples summed)."""
    rows = [r for r in rows if r]
    if not rows:
        return {}
    out = {k: max(r[k] for r in rows) for k in ("p50", "p99", "max")}
    out["samples"] = sum(r["samples"] for r in rows)
    return out


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
    latency: list[int] = []
    clock, now = time.thread_time_ns, time.monotonic_ns
    # every exchange until the forwarder closes (its last stamp taken); ten
    # seconds of silence end a run whose forwarder hangs
    for _ in range(count):
        if not ep.poll(10.0):
            break
        c0 = clock()
        if not s.recv_into(buf):
            break
        t = now()
        s.send(reply)
        cpu.append(clock() - c0)
        latency.append(t - int.from_bytes(buf[:8], "little"))
    print(json.dumps({"cpu": _percentiles(cpu), "latency": _percentiles(latency)}), flush=True)
    return 0


def _forwarder(
    efd: int, sock_fds: list[int], stamp_fd: int, count: int, priority: int, ready_fd: int
) -> int:
    socks = [socket.socket(fileno=fd) for fd in sock_fds]
    orders = (socks, socks[::-1])  # the robots in turn, as the SSC's ddm sends
    stamp = mmap.mmap(stamp_fd, 8)
    _real_time(priority)
    ep = select.epoll()
    ep.register(efd, select.EPOLLIN)
    os.write(ready_fd, b"r")  # (the worker's stamps may come)
    os.close(ready_fd)
    command = bytearray(COMMAND_BYTES)
    buf = bytearray(4 * REPLY_BYTES)
    taken = exchanges = 0
    while taken < count and ep.poll(10.0):
        # a wake-up that finds several stamps (the worker ran late and wrote
        # them back to back) sends the last: one exchange, the rest counted
        taken += os.eventfd_read(efd)
        command[:8] = stamp[:8]
        for s in orders[exchanges & 1]:
            s.send(command)
        for s in socks:
            s.recv_into(buf)
        exchanges += 1
    print(json.dumps({"exchanges": exchanges, "coalesced": taken - exchanges}), flush=True)
    return 0


def _module(*args: str) -> list[str]:
    return [sys.executable, "-m", "redistro.bench.floor", *args]


def measure(
    rate_hz: float,
    seconds: float,
    priority: int,
    cpu_latency_us: int | None = None,
    robots: int = 1,
    module: str = "redistro.bench.floor",
    start_s: float = 30.0,
) -> dict[str, Any]:
    """The floor at ``rate_hz`` for ``seconds`` (run in a fresh interpreter,
    ``python -m module``: this one, or :mod:`redistro.bench.zenoh_floor`),
    with the CPUs' wake-up latency held at ``cpu_latency_us`` as the nodes
    hold it (None: left alone), for ``robots`` repliers; ``start_s`` more
    for its start-up and end."""
    latency = [] if cpu_latency_us is None else ["--cpu-latency", str(cpu_latency_us)]
    out = subprocess.run(
        [
            *(sys.executable, "-m", module),
            *("--rate", str(rate_hz), "--seconds", str(seconds), "--priority", str(priority)),
            *("--robots", str(robots), *latency),
        ],
        capture_output=True,
        text=True,
        timeout=seconds + start_s,
        check=False,
    )
    try:
        return dict(json.loads(out.stdout.strip().splitlines()[-1]))
    except (ValueError, IndexError):
        return {"error": (out.stderr.strip().splitlines() or ["no output"])[-1]}


def _repliers(
    listener: socket.socket, port: int, robots: int, count: int, priority: int, children: list[Any]
) -> list[socket.socket]:
    """One replier process per robot (as one ESC ddm each), connected:
    their connections (each started one goes into ``children``)."""
    conns = []
    listener.settimeout(10.0)
    for _ in range(robots):
        children.append(
            subprocess.Popen(
                _module("--reply", str(port), "--count", str(count), "--priority", str(priority)),
                stdout=subprocess.PIPE,
                text=True,
            )
        )
        conn, _ = listener.accept()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.setblocking(True)
        conns.append(conn)
    return conns


def _worker(
    rate_hz: float, seconds: float, priority: int, cpu_latency_us: int | None, robots: int
) -> int:
    count = max(1, int(rate_hz * seconds))
    granted = sched.Granted()
    held = None if cpu_latency_us is None else sched.hold_cpu_latency(cpu_latency_us, granted)
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(robots)
    port = listener.getsockname()[1]
    efd = os.eventfd(0, os.EFD_CLOEXEC)
    stamp_fd = os.memfd_create("redistro-floor")  # the worker's stamp, shared
    os.ftruncate(stamp_fd, 8)
    stamp = mmap.mmap(stamp_fd, 8)
    ready_r, ready_w = os.pipe()
    children: list[Any] = []
    try:
        conns = _repliers(listener, port, robots, count, priority, children)
        fds = [c.fileno() for c in conns]
        forwarder = subprocess.Popen(
            _module(
                "--forward",
                ",".join(str(v) for v in (efd, stamp_fd, ready_w, *fds)),
                "--count",
                str(count),
                "--priority",
                str(priority),
            ),
            pass_fds=(efd, stamp_fd, ready_w, *fds),
            stdout=subprocess.PIPE,
            text=True,
        )
        children.append(forwarder)
        os.close(ready_w)
        ready_w = -1
        for c in conns:
            c.close()
        # the first stamp once the forwarder waits for it (a stamp before
        # would be taken with the next, one exchange fewer)
        if not select.select([ready_r], [], [], READY_S)[0] or not os.read(ready_r, 1):
            raise SystemExit(f"floor: the forwarder was not ready within {READY_S:g} s")
        period = 1.0 / rate_hz
        due = time.monotonic()
        for _ in range(count):
            due += period
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            stamp[:8] = time.monotonic_ns().to_bytes(8, "little")
            os.eventfd_write(efd, 1)
        outs = [child.communicate(timeout=20.0)[0] for child in children]
    finally:
        for child in children:
            if child.poll() is None:
                child.kill()
                child.wait()
        listener.close()
        stamp.close()
        for fd in (stamp_fd, efd, ready_r, ready_w):
            if fd >= 0:
                os.close(fd)
    *figures, sent = [json.loads(out.strip().splitlines()[-1]) for out in outs]
    result = {
        # the worst robot's (one replier: its own)
        "reply_cpu_us": _worst([f["cpu"] for f in figures]),
        "latency_us": _worst([f["latency"] for f in figures]),
        "stamps": count,
        "exchanges": sent["exchanges"],
        "coalesced": sent["coalesced"],
        "robots": robots,
        "rate_hz": rate_hz,
        "seconds": seconds,
        "cpu_latency_us": granted.cpu_latency_us,
    }
    if held is not None:
        os.close(held)
    print(json.dumps(result), flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m redistro.bench.floor")
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--priority", type=int, default=19)
    ap.add_argument("--cpu-latency", type=int, default=None, help="hold the PM QoS at this [us]")
    ap.add_argument("--robots", type=int, default=1, help="repliers, sent to in turn (1-16)")
    ap.add_argument("--reply", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--forward", default="", help=argparse.SUPPRESS)
    ap.add_argument("--count", type=int, default=0, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.reply:
        return _replier(a.reply, a.count, a.priority)
    if a.forward:
        efd, stamp_fd, ready_fd, *sock_fds = (int(v) for v in a.forward.split(","))
        return _forwarder(efd, sock_fds, stamp_fd, a.count, a.priority, ready_fd)
    return _worker(a.rate, a.seconds, a.priority, a.cpu_latency, max(1, min(16, a.robots)))


if __name__ == "__main__":
    sys.exit(main())

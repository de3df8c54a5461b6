"""The zenoh floor: what zenoh-python alone gives a group's command/reply.

The counterpart of :mod:`redistro.bench.floor` for ``bench ddm --transport
zenoh --floor``, measured in the same run. A *commander* (the SSC's part)
opens a peer session that listens on TCP loopback and puts a
command-sized payload on each robot's key at the node rate, the robots in
turn (the order reversed every other step), stamped just before, from the
thread that keeps the rate, as the SSC's side of ``bench ddm`` does. N
*repliers* (the ESCs' part) open client sessions through it; each takes its
command in zenoh's RX thread (a callback run there, the thread keeping its
Python thread state, as the zenoh transport's) and at once puts a
feedback-sized reply, which the commander counts in one subscriber. Every
session is set up as the project's are (no scouting, no shared memory, one
RX thread), without the records: nothing is signed, checked, encoded or
copied into Local Data, and no user or access rule is checked.

- ``latency_us``: from the command's stamp to the replier's callback (the
  floor under the DDM command latency over zenoh: two zenoh threads woken
  on the way, one TCP hop);
- ``reply_cpu_us``: the replier's callback CPU (its reply's put included);

both the worst replier's percentiles. ``replies`` counts what came back.

Run as ``python -m redistro.bench.zenoh_floor --rate HZ --seconds S
--robots N`` (``redistro.bench.floor.measure(..., module=...)`` from
code); prints one JSON line. Every process blocks the runtime
signals before zenoh is imported, and is started with fork+exec.
"""

import os
import sys

if __name__ == "__main__":
    from redistro.ipc.signals import block_runtime_signals

    block_runtime_signals()

import argparse
import json
import socket
import subprocess
import threading
import time
from typing import Any

from redistro.bench import floor
from redistro.bench.floor import COMMAND_BYTES, REPLY_BYTES, _percentiles, _worst
from redistro.ipc import sched

START_S = 10.0  # the repliers' sessions meet the commander's within this


def _session(listen: list[str], connect: list[str], mode: str) -> Any:
    from redistro.ddm import zenoh_transport as zt

    return zt.open_session(
        {
            "mode": mode,
            "scouting/multicast/enabled": False,
            "scouting/gossip/enabled": False,
            "transport/shared_memory/enabled": False,
            "listen/endpoints": listen,
            "connect/endpoints": connect,
        }
    )


def _replier(port: int, robot: int, count: int, priority: int) -> int:
    import zenoh

    from redistro.ddm.zenoh_transport import _keep_thread_state

    floor._real_time(priority)
    s = _session([], [f"tcp/127.0.0.1:{port}"], "client")
    pub = s.declare_publisher(
        f"floor/{robot}/reply", congestion_control=zenoh.CongestionControl.DROP, express=True
    )
    reply = bytearray(REPLY_BYTES)
    cpu: list[int] = []
    latency: list[int] = []
    kept: set[int] = set()
    done = threading.Event()
    clock, now = time.thread_time_ns, time.monotonic_ns

    def take(sample: Any) -> None:
        ident = threading.get_ident()
        if ident not in kept:
            _keep_thread_state(ident, kept)
        c0 = clock()
        raw = sample.payload.to_bytes()
        t = now()
        reply[:8] = raw[:8]
        pub.put(bytes(reply))
        cpu.append(clock() - c0)
        latency.append(t - int.from_bytes(raw[:8], "little"))
        if len(latency) >= count:
            done.set()

    sub = s.declare_subscriber(
        f"floor/{robot}/command", zenoh.handlers.Callback(take, indirect=False)
    )
    sched.share_with_threads()
    print("ready", flush=True)
    done.wait(START_S + count * 0.1)
    sub.undeclare()
    s.close()
    print(json.dumps({"cpu": _percentiles(cpu), "latency": _percentiles(latency)}), flush=True)
    return 0


def _commander(
    port: int, robots: int, rate_hz: float, count: int, priority: int, ready: Any
) -> int:
    import zenoh

    floor._real_time(priority)
    s = _session([f"tcp/127.0.0.1:{port}"], [], "peer")
    express = {"congestion_control": zenoh.CongestionControl.DROP, "express": True}
    pubs = [s.declare_publisher(f"floor/{r}/command", **express) for r in range(robots)]
    replies = [0] * robots

    def back(sample: Any) -> None:
        replies[int(str(sample.key_expr).split("/")[1])] += 1

    sub = s.declare_subscriber("floor/*/reply", back)
    ready()  # the repliers start now, and have subscribed when this returns
    deadline = time.monotonic() + START_S
    while not all(p.matching_status.matching for p in pubs):  # their subscriptions here
        if time.monotonic() > deadline:
            raise RuntimeError("the repliers' subscriptions never reached the commander")
        time.sleep(0.01)
    sched.share_with_threads()
    orders = (pubs, pubs[::-1])
    command = bytearray(COMMAND_BYTES)
    period_ns = int(1e9 / rate_hz)
    due = time.monotonic_ns()
    for k in range(count):
        due += period_ns
        wait = due - time.monotonic_ns()
        if wait > 0:
            time.sleep(wait / 1e9)
        for pub in orders[k & 1]:
            command[:8] = time.monotonic_ns().to_bytes(8, "little")
            pub.put(bytes(command))
    # the last replies: until every command's came, or 2 s passed (with
    # congestion control DROP, a loaded host may drop a command or a reply)
    deadline = time.monotonic() + 2.0
    while sum(replies) < robots * count and time.monotonic() < deadline:
        time.sleep(0.005)  # polling the subscriber's count, to a deadline
    sub.undeclare()
    s.close()
    print(json.dumps({"replies": replies}), flush=True)
    return 0


def _module(*args: str) -> list[str]:
    return [sys.executable, "-m", "redistro.bench.zenoh_floor", *args]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def _worker(
    rate_hz: float, seconds: float, priority: int, cpu_latency_us: int | None, robots: int
) -> int:
    count = max(1, int(rate_hz * seconds))
    granted = sched.Granted()
    held = None if cpu_latency_us is None else sched.hold_cpu_latency(cpu_latency_us, granted)
    port = _free_port()
    children: list[Any] = []
    try:
        commander = subprocess.Popen(
            _module(
                *("--command", str(port), "--robots", str(robots), "--rate", str(rate_hz)),
                *("--count", str(count), "--priority", str(priority)),
            ),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        children.append(commander)
        assert commander.stdin is not None and commander.stdout is not None
        if commander.stdout.readline().strip() != "listening":
            raise RuntimeError("the commander's session did not open")
        for r in range(robots):  # one replier per robot, as one ESC ddm each
            child = subprocess.Popen(
                _module(
                    *("--reply", str(port), "--robot", str(r)),
                    *("--count", str(count), "--priority", str(priority)),
                ),
                stdout=subprocess.PIPE,
                text=True,
            )
            children.append(child)
            assert child.stdout is not None
            if child.stdout.readline().strip() != "ready":
                raise RuntimeError(f"replier {r} did not meet the commander")
        commander.stdin.write("go\n")
        commander.stdin.flush()
        outs = [child.communicate(timeout=START_S + seconds + 10)[0] for child in children]
    finally:
        for child in children:
            if child.poll() is None:
                child.kill()
                child.wait()
        if held is not None:
            os.close(held)
    figures = [json.loads(out.strip().splitlines()[-1]) for out in outs]
    result = {
        # the worst robot's (one replier: its own)
        "reply_cpu_us": _worst([f["cpu"] for f in figures[1:]]),
        "latency_us": _worst([f["latency"] for f in figures[1:]]),
        "replies": sum(figures[0]["replies"]),
        "commands": count * robots,
        "robots": robots,
        "rate_hz": rate_hz,
        "seconds": seconds,
        "cpu_latency_us": granted.cpu_latency_us,
    }
    print(json.dumps(result), flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m redistro.bench.zenoh_floor")
    ap.add_argument("--rate", type=float, default=200.0)
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--priority", type=int, default=19)
    ap.add_argument("--cpu-latency", type=int, default=None, help="hold the PM QoS at this [us]")
    ap.add_argument("--robots", type=int, default=1, help="repliers, sent to in turn (1-16)")
    ap.add_argument("--reply", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--command", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--robot", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--count", type=int, default=0, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    robots = max(1, min(16, a.robots))
    if a.reply:
        return _replier(a.reply, a.robot, a.count, a.priority)
    if a.command:

        def ready() -> None:
            print("listening", flush=True)
            sys.stdin.readline()  # "go": every replier subscribed

        return _commander(a.command, robots, a.rate, a.count, a.priority, ready)
    return _worker(a.rate, a.seconds, a.priority, a.cpu_latency, robots)


if __name__ == "__main__":
    sys.exit(main())

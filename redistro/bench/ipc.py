"""``redistro bench ipc``: one feedback record (two 7-DOF robots), writer -> reader.

The same record crosses three ways in one run: a Local Data block (seqlock
snapshot, reader polling), multiprocessing.Pipe and multiprocessing.Queue.
The writer process stamps the record with CLOCK_MONOTONIC just before it
writes; the reader (this process) takes the latency when it holds a
consistent copy. Both processes are started fork+exec (multiprocessing
"spawn").
"""

from __future__ import annotations

import multiprocessing as mp
import time
from typing import Any

import numpy as np

from redistro.ipc import session as ipc_session
from redistro.localdata import LocalData
from redistro.localdata.layout import FEEDBACK

RECORD = np.dtype([("robot", FEEDBACK, (2,))])
NODE = "ipcbench"


def _fill(rec: np.ndarray[Any, Any], i: int) -> None:
    rec["robot"]["seq_src"] = i
    rec["robot"]["q_rad"] = i * 1e-3
    rec["robot"]["qd_rad_s"] = -i * 1e-3


def _ld_writer(session_id: str, samples: int, gap_s: float, start: Any) -> None:
    ld = LocalData.attach(session_id, NODE)
    blocks = [ld.writer("feedback", r, role="busy") for r in range(2)]
    rec = np.zeros((), dtype=RECORD)
    raw = rec.reshape(1).view(np.uint8)
    size = FEEDBACK.itemsize
    robot_bytes = [raw[r * size : (r + 1) * size] for r in range(2)]
    start.wait()
    for i in range(1, samples + 1):
        _fill(rec, i)
        rec["robot"]["stamp_ns"] = time.monotonic_ns()
        # the record is the two robots' feedback blocks, each published in one copy
        blocks[0].publish(robot_bytes[0])
        blocks[1].publish(robot_bytes[1])
        _pause(gap_s)
    ld.close()


def _pause(gap_s: float) -> None:
    """Pacing between samples (not synchronization), by spinning: a writer that
    slept would start every sample on a cold, just-woken CPU, and the figure
    would measure the wake-up instead of the transport. ``sleep(0)`` hands the
    GIL over on each turn, so multiprocessing.Queue's feeder thread can run."""
    end = time.perf_counter() + gap_s
    while time.perf_counter() < end:
        time.sleep(0)


def _pipe_writer(conn: Any, samples: int, gap_s: float, start: Any) -> None:
    rec = np.zeros((), dtype=RECORD)
    start.wait()
    for i in range(1, samples + 1):
        _fill(rec, i)
        rec["robot"]["stamp_ns"] = time.monotonic_ns()
        conn.send_bytes(rec.tobytes())
        _pause(gap_s)
    conn.close()


def _queue_writer(queue: Any, samples: int, gap_s: float, start: Any) -> None:
    rec = np.zeros((), dtype=RECORD)
    start.wait()
    for i in range(1, samples + 1):
        _fill(rec, i)
        rec["robot"]["stamp_ns"] = time.monotonic_ns()
        queue.put(rec.tobytes())
        _pause(gap_s)
    queue.close()
    queue.join_thread()


def _stats(lat_ns: list[int]) -> dict[str, float]:
    v = np.asarray(lat_ns, dtype=np.float64) / 1e3
    return {
        "median_us": round(float(np.median(v)), 2),
        "p99_us": round(float(np.percentile(v, 99)), 2),
        "max_us": round(float(v.max()), 2),
        "samples": int(v.size),
    }


def bench_localdata(ctx: Any, samples: int, gap_s: float, timeout_s: float) -> dict[str, Any]:
    with ipc_session.Session.create() as session:
        ld = LocalData.create(
            session.id,
            NODE,
            node_kind="bench",
            proc_names=["writer"],
            proc_roles=["busy"],
            proc_stages=[0],
            robot_names=["r1", "r2"],
            rate_hz=1.0,
            period_ns=10**9,
            heartbeat_limit_cycles=2,
            manifest=session.manifest,
        )
        try:
            blocks = [ld.block("feedback", r) for r in range(2)]
            start = ctx.Event()
            proc = ctx.Process(target=_ld_writer, args=(session.id, samples, gap_s, start))
            proc.start()
            lat: list[int] = []
            inconsistent = 0
            last = 0
            got = [np.zeros((), FEEDBACK), np.zeros((), FEEDBACK)]
            dst = [g.reshape(1).view(np.uint8) for g in got]
            start.set()
            deadline = time.monotonic() + timeout_s
            i = 0
            while i < samples and time.monotonic() < deadline:
                if blocks[1].seq == last:  # robot 2 is written last: it announces a record
                    continue
                blocks[1].read_into(dst[1])
                blocks[0].read_into(dst[0])
                now = time.monotonic_ns()
                last = blocks[1].seq
                i = int(got[1]["seq_src"])
                if int(got[0]["seq_src"]) < i or float(got[1]["q_rad"][0]) != i * 1e-3:
                    inconsistent += 1
                lat.append(now - int(got[1]["stamp_ns"]))
            proc.join(timeout=5)
            out = _stats(lat)
            out["torn_retries"] = ld.torn_reads()
            out["inconsistent"] = inconsistent
            out["missed"] = samples - len(lat)  # records overwritten before the reader looked
            return out
        finally:
            ld.close()
            ld.unlink()


def bench_pipe(ctx: Any, samples: int, gap_s: float) -> dict[str, Any]:
    reader, writer = ctx.Pipe(duplex=False)
    start = ctx.Event()
    proc = ctx.Process(target=_pipe_writer, args=(writer, samples, gap_s, start))
    proc.start()
    writer.close()
    lat = []
    start.set()
    for _ in range(samples):
        data = reader.recv_bytes()
        now = time.monotonic_ns()
        rec = np.frombuffer(data, dtype=RECORD)[0]
        lat.append(now - int(rec["robot"]["stamp_ns"][0]))
    proc.join(timeout=5)
    reader.close()
    return _stats(lat)


def bench_queue(ctx: Any, samples: int, gap_s: float) -> dict[str, Any]:
    queue = ctx.Queue()
    start = ctx.Event()
    proc = ctx.Process(target=_queue_writer, args=(queue, samples, gap_s, start))
    proc.start()
    lat = []
    start.set()
    for _ in range(samples):
        data = queue.get(timeout=10)
        now = time.monotonic_ns()
        rec = np.frombuffer(data, dtype=RECORD)[0]
        lat.append(now - int(rec["robot"]["stamp_ns"][0]))
    proc.join(timeout=5)
    queue.close()
    return _stats(lat)


def run(samples: int, gap_us: float) -> dict[str, Any]:
    ctx = mp.get_context("spawn")  # fork+exec: a fresh interpreter per writer
    gap_s = gap_us / 1e6
    ld = bench_localdata(ctx, samples, gap_s, timeout_s=30 + samples * gap_s * 4)
    pipe = bench_pipe(ctx, samples, gap_s)
    queue = bench_queue(ctx, samples, gap_s)
    return {
        "record": "feedback of two 7-DOF robots",
        "record_bytes": RECORD.itemsize,
        "samples": samples,
        "gap_us": gap_us,
        "localdata": ld,
        "pipe": pipe,
        "queue": queue,
        "speedup_median": {
            "vs_pipe": round(pipe["median_us"] / ld["median_us"], 1),
            "vs_queue": round(queue["median_us"] / ld["median_us"], 1),
        },
    }

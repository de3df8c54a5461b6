"""``redistro bench ipc``: robot feedback, writer -> reader, three ways.

The same record crosses three ways in one run: Local Data (one seqlocked
block per robot, reader polling), multiprocessing.Pipe and
multiprocessing.Queue. The record is the feedback of one robot (one block)
or of two (two blocks, as the SSC reads its group). The writer process stamps
the record with CLOCK_MONOTONIC just before it writes; the reader (this
process) takes the latency when it holds a consistent copy of the whole
record. Both processes are started fork+exec (multiprocessing "spawn").
"""

from __future__ import annotations

import multiprocessing as mp
import time
from typing import Any

import numpy as np

from redistro.ipc import session as ipc_session
from redistro.localdata import LocalData
from redistro.localdata.layout import FEEDBACK

NODE = "ipcbench"


def record_dtype(robots: int) -> np.dtype[Any]:
    return np.dtype([("robot", FEEDBACK, (robots,))])


def _fill(rec: np.ndarray[Any, Any], i: int) -> None:
    rec["robot"]["seq_src"] = i
    rec["robot"]["q_rad"] = i * 1e-3
    rec["robot"]["qd_rad_s"] = -i * 1e-3


def _stamps(raw: np.ndarray[Any, Any], robots: int) -> list[memoryview]:
    """Each robot's ``stamp_ns`` word in a record's bytes."""
    fields = FEEDBACK.fields
    assert fields is not None
    off = int(fields["stamp_ns"][1])
    mem = memoryview(raw)  # type: ignore[arg-type]
    size = FEEDBACK.itemsize
    return [mem[r * size + off : r * size + off + 8].cast("q") for r in range(robots)]


def _ld_writer(session_id: str, robots: int, samples: int, gap_s: float, start: Any) -> None:
    ld = LocalData.attach(session_id, NODE)
    blocks = [ld.writer("feedback", r, role="busy") for r in range(robots)]
    rec = np.zeros((), dtype=record_dtype(robots))
    raw = rec.reshape(1).view(np.uint8)
    size = FEEDBACK.itemsize
    parts = [memoryview(raw[r * size : (r + 1) * size]) for r in range(robots)]  # type: ignore[arg-type]
    stamps = _stamps(raw, robots)
    start.wait()
    for i in range(1, samples + 1):
        _fill(rec, i)
        now = time.monotonic_ns()
        for stamp in stamps:
            stamp[0] = now
        # each robot's feedback is one block, published in one copy
        for block, part in zip(blocks, parts, strict=True):
            block.publish(part)
        _pause(gap_s)
    for mv in (*stamps, *parts):
        mv.release()
    ld.close()


def _pause(gap_s: float) -> None:
    """Pacing between samples (not synchronization), by spinning: a writer that
    slept would start every sample on a cold, just-woken CPU, and the figure
    would measure the wake-up instead of the transport. ``sleep(0)`` hands the
    GIL over on each turn, so multiprocessing.Queue's feeder thread can run."""
    end = time.perf_counter() + gap_s
    while time.perf_counter() < end:
        time.sleep(0)


def _pipe_writer(conn: Any, robots: int, samples: int, gap_s: float, start: Any) -> None:
    rec = np.zeros((), dtype=record_dtype(robots))
    start.wait()
    for i in range(1, samples + 1):
        _fill(rec, i)
        rec["robot"]["stamp_ns"] = time.monotonic_ns()
        conn.send_bytes(rec.tobytes())
        _pause(gap_s)
    conn.close()


def _queue_writer(queue: Any, robots: int, samples: int, gap_s: float, start: Any) -> None:
    rec = np.zeros((), dtype=record_dtype(robots))
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


def bench_localdata(
    ctx: Any, robots: int, samples: int, gap_s: float, timeout_s: float
) -> dict[str, Any]:
    with ipc_session.Session.create() as session:
        ld = LocalData.create(
            session.id,
            NODE,
            node_kind="bench",
            proc_names=["writer"],
            proc_roles=["busy"],
            proc_stages=[0],
            robot_names=[f"r{r + 1}" for r in range(robots)],
            rate_hz=1.0,
            period_ns=10**9,
            heartbeat_limit_cycles=2,
            manifest=session.manifest,
        )
        try:
            blocks = [ld.block("feedback", r) for r in range(robots)]
            start = ctx.Event()
            args = (session.id, robots, samples, gap_s, start)
            proc = ctx.Process(target=_ld_writer, args=args)
            proc.start()
            lat: list[int] = []
            inconsistent = 0
            last = 0
            got = [np.zeros((), FEEDBACK) for _ in range(robots)]
            dst = [memoryview(g.reshape(1).view(np.uint8)) for g in got]  # type: ignore[arg-type]
            # the last robot is written last: its counter announces a record;
            # the reader then takes the blocks newest first
            announce = blocks[-1]
            order = list(zip(blocks, dst, strict=True))[::-1]
            start.set()
            deadline_ns = time.monotonic_ns() + int(timeout_s * 1e9)
            i = 0
            while i < samples:
                seq = announce.spin_until_changed(last, deadline_ns)
                if seq == last:
                    break  # the writer stopped early: report what arrived
                for block, into in order:
                    block.read_into(into)
                now = time.monotonic_ns()
                last = seq
                i = int(got[-1]["seq_src"])
                if int(got[0]["seq_src"]) < i or float(got[-1]["q_rad"][0]) != i * 1e-3:
                    inconsistent += 1
                lat.append(now - int(got[-1]["stamp_ns"]))
            proc.join(timeout=5)
            out = _stats(lat)
            out["torn_retries"] = ld.torn_reads()
            out["inconsistent"] = inconsistent
            out["missed"] = samples - len(lat)  # records overwritten before the reader looked
            for mv in dst:
                mv.release()
            return out
        finally:
            ld.close()
            ld.unlink()


def bench_pipe(ctx: Any, robots: int, samples: int, gap_s: float) -> dict[str, Any]:
    reader, writer = ctx.Pipe(duplex=False)
    start = ctx.Event()
    proc = ctx.Process(target=_pipe_writer, args=(writer, robots, samples, gap_s, start))
    proc.start()
    writer.close()
    lat = []
    dtype = record_dtype(robots)
    start.set()
    for _ in range(samples):
        data = reader.recv_bytes()
        now = time.monotonic_ns()
        rec = np.frombuffer(data, dtype=dtype)[0]
        lat.append(now - int(rec["robot"]["stamp_ns"][0]))
    proc.join(timeout=5)
    reader.close()
    return _stats(lat)


def bench_queue(ctx: Any, robots: int, samples: int, gap_s: float) -> dict[str, Any]:
    queue = ctx.Queue()
    start = ctx.Event()
    proc = ctx.Process(target=_queue_writer, args=(queue, robots, samples, gap_s, start))
    proc.start()
    lat = []
    dtype = record_dtype(robots)
    start.set()
    for _ in range(samples):
        data = queue.get(timeout=10)
        now = time.monotonic_ns()
        rec = np.frombuffer(data, dtype=dtype)[0]
        lat.append(now - int(rec["robot"]["stamp_ns"][0]))
    proc.join(timeout=5)
    queue.close()
    return _stats(lat)


def run(samples: int, gap_us: float, robots: int = 2) -> dict[str, Any]:
    ctx = mp.get_context("spawn")  # fork+exec: a fresh interpreter per writer
    gap_s = gap_us / 1e6
    timeout_s = 30 + samples * gap_s * 4
    ld = bench_localdata(ctx, robots, samples, gap_s, timeout_s)
    pipe = bench_pipe(ctx, robots, samples, gap_s)
    queue = bench_queue(ctx, robots, samples, gap_s)
    return {
        "record": f"feedback of {robots} 7-DOF robot{'s' if robots > 1 else ''}",
        "record_bytes": record_dtype(robots).itemsize,
        "blocks": robots,
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

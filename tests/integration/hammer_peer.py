"""A writer or reader process for the seqlock hammer test.

writer SESSION SECONDS: rewrites robot 0's feedback block as fast as it can;
    every value in the record is the write counter i (stamp, seq, q, qd, tau, wrench).
reader SESSION SECONDS: takes snapshots (a read that finds none within its budget
    is counted, not returned) and checks that every value in each is
    the same i; counts those that are not (must stay 0) and, as a control, the
    same check on copies taken without the protocol (raw_read), which do tear.
Prints one JSON line with the counts.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from redistro.errors import TornReadTimeout
from redistro.localdata import LocalData


def consistent(rec: np.void) -> bool:
    i = float(rec["seq_src"])
    values = np.concatenate(
        [rec["q_rad"], rec["qd_rad_s"], rec["tau_nm"], rec["wrench"], [float(rec["stamp_ns"])]]
    )
    return bool(np.all(values == i))


def writer(session_id: str, seconds: float) -> None:
    ld = LocalData.attach(session_id, "hammer")
    blk = ld.writer("feedback", 0, role="busy")
    end = time.monotonic() + seconds
    i = 0
    while time.monotonic() < end:
        i += 1
        with blk.write() as d:
            d["stamp_ns"] = i
            d["seq_src"] = i
            d["q_rad"] = i
            d["qd_rad_s"] = i
            d["tau_nm"] = i
            d["wrench"] = i
    print(json.dumps({"writes": i}), flush=True)
    ld.close()


def reader(session_id: str, seconds: float) -> None:
    ld = LocalData.attach(session_id, "hammer")
    blk = ld.block("feedback", 0)
    end = time.monotonic() + seconds
    snapshots = torn_returned = raw = raw_torn = 0
    last = 0
    went_back = 0
    timeouts = 0
    while time.monotonic() < end:
        try:
            rec = blk.read(budget_s=0.1)
        except TornReadTimeout:  # no snapshot within the budget (the writer held off
            timeouts += 1  # mid-write by a host stall): none returned, none torn
            continue
        snapshots += 1
        if not consistent(rec):
            torn_returned += 1
        i = int(rec["seq_src"])
        went_back += i < last
        last = i
        raw += 1
        if not consistent(blk.raw_read()):
            raw_torn += 1
    print(
        json.dumps(
            {
                "snapshots": snapshots,
                "torn_returned": torn_returned,
                "went_back": went_back,
                "retries": blk.torn,
                "timeouts": timeouts,
                "raw": raw,
                "raw_torn": raw_torn,
            }
        ),
        flush=True,
    )
    ld.close()


if __name__ == "__main__":
    role, sid, secs = sys.argv[1], sys.argv[2], float(sys.argv[3])
    (writer if role == "writer" else reader)(sid, secs)

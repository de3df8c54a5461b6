"""Two session logs compared cycle by cycle (``redistro log diff A B``, and
``redistro replay``'s report).

Each node's log holds one digest a cycle (``/<node>/digest``: the hash of
that cycle's logged data, wall-clock stamps aside). Two logs are the same
when every node logged as many cycles with the same digests. Otherwise
the digests tell how many of each node's cycles differ and the first; the
cycle channels then name the first channel and field that differ, and
both values. A log without digests (recorded before they were kept) is
compared on its channels alone.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from redistro.log.mcapfile import SessionLog, read_log

DIGEST_TOPIC = "/digest"  # a node's per-cycle digests: /<node>/digest


def compare_logs(a: Path, b: Path) -> dict[str, Any]:
    """``identical``, per node the cycles whose digests differ (``nodes``),
    and when they are not identical the first difference (cycle, topic,
    field, both values). Raises ValueError naming a log that is not one."""
    la, lb = read_log(a), read_log(b)
    # (a node's digests in one log only: a log from before they were kept,
    # compared on its channels; a node missing altogether, by its channels)
    nodes = {
        topic.split("/")[1]: _digests(la.arrays[topic], lb.arrays[topic])
        for topic in sorted(set(la.arrays) & set(lb.arrays))
        if topic.endswith(DIGEST_TOPIC)
    }
    first = first_difference(la, lb)
    same = first is None and all(n["differing"] == 0 for n in nodes.values())
    report: dict[str, Any] = {"identical": same, "nodes": nodes}
    if not same:
        report["first_difference"] = first or _first_by_digest(nodes)
    return report


def _digests(x: Any, y: Any) -> dict[str, Any]:
    """One node's digests in both logs: cycles, how many differ, the first."""
    if x is None or y is None:
        n = len(x if x is not None else y)
        return {"cycles": [0 if x is None else n, 0 if y is None else n], "differing": n,
                "first_cycle": 0}  # fmt: skip
    n = min(len(x), len(y))
    differ = np.asarray(x["digest"][:n] != y["digest"][:n]).reshape(n, -1).any(axis=1)
    count = int(differ.sum()) + abs(len(x) - len(y))
    out: dict[str, Any] = {"cycles": [len(x), len(y)], "differing": count}
    if differ.any():
        out["first_cycle"] = int(x["log_cycle"][int(np.argmax(differ))])
    elif count:
        longer = x if len(x) > len(y) else y
        out["first_cycle"] = int(longer["log_cycle"][n])
    return out


def _first_by_digest(nodes: dict[str, Any]) -> dict[str, Any]:
    """Where the digests differ but no cycle channel does (a channel's
    data beyond what both logs' schemas read alike): the node and cycle."""
    node, d = min(
        ((k, v) for k, v in nodes.items() if v["differing"]), key=lambda kv: kv[1]["first_cycle"]
    )
    return {"cycle": d["first_cycle"], "topic": f"/{node}{DIGEST_TOPIC}", "field": "digest",
            "recorded": d["cycles"][0], "replayed": d["cycles"][1]}  # fmt: skip


def first_difference(la: SessionLog, lb: SessionLog) -> dict[str, Any] | None:
    """The earliest cycle at which two logs' cycle channels differ
    (wall-clock stamps, timing and digest channels aside): its topic and
    field, and both values (``recorded``: the first log's)."""
    best: dict[str, Any] | None = None
    for topic in sorted(set(la.arrays) | set(lb.arrays)):
        if topic.endswith(("/timing", DIGEST_TOPIC)):
            continue
        found = _first_in(topic, la.arrays.get(topic), lb.arrays.get(topic))
        if found is not None and (best is None or found["cycle"] < best["cycle"]):
            best = found
    return best


def _first_in(topic: str, x: Any, y: Any) -> dict[str, Any] | None:
    if x is None or y is None:
        return {"cycle": 0, "topic": topic, "field": "(channel)", "recorded": x is not None,
                "replayed": y is not None}  # fmt: skip
    n = min(len(x), len(y))
    first: dict[str, Any] | None = None
    for name in x.dtype.names or ():
        if name.endswith("_ns") or name == "log_cycle":
            continue
        differ = np.asarray(x[name][:n] != y[name][:n]).reshape(n, -1).any(axis=1)
        if differ.any():
            i = int(np.argmax(differ))
            if first is None or i < first["row"]:
                first = {"row": i, "field": name, "recorded": _plain(x[name][i]),
                         "replayed": _plain(y[name][i])}  # fmt: skip
    if first is None and len(x) != len(y):
        first = {"row": n, "field": "(cycles)", "recorded": len(x), "replayed": len(y)}
    if first is None:
        return None
    row = int(first.pop("row"))
    cycles = x["log_cycle"] if row < len(x) else y["log_cycle"]
    cycle = int(cycles[min(row, len(cycles) - 1)]) if len(cycles) else 0
    return {"cycle": cycle, "topic": topic, **first}


def _plain(v: Any) -> Any:
    return v.tolist() if hasattr(v, "tolist") else v


def report_line(report: dict[str, Any], first: str = "recorded", second: str = "replayed") -> str:
    """One line: identical, or where they first differ and how many cycles do."""
    if report["identical"]:
        return "identical: true"
    d = report.get("first_difference")
    if not d:
        return "identical: false"
    nodes = report.get("nodes", {})
    counts = ", ".join(f"{k} {v['differing']} of {max(v['cycles'])}" for k, v in nodes.items())
    cycles = f"; cycles differing: {counts}" if counts else ""
    return (
        f"identical: false: first difference at cycle {d['cycle']}, {d['topic']} "
        f"{d['field']} ({first} {d['recorded']}, {second} {d['replayed']}){cycles}"
    )

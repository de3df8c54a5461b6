"""The exchange block (what a ddm reports per robot) as a report."""

from __future__ import annotations

from typing import Any


def exchange_report(ex: Any) -> dict[str, Any]:
    """A node's exchange block (one robot) as JSON: its counts, e-stop and
    command latency (the ddm writes it; the managers report it)."""
    out: dict[str, Any] = {
        k: int(ex[k])
        for k in (
            "updates",
            "sent",
            "dropped",
            "malformed",
            "duplicate",
            "out_of_order",
            "stale",
            "forged",
            "foreign",
            "latency_n",
        )
    }
    out["estop_in"] = bool(ex["estop_in"])
    out["estop_source"] = bytes(ex["estop_source"]).decode(errors="replace")
    out["link_lost"] = bool(ex["link_lost"])
    lat = [float(v) for v in ex["latency_us"]]
    out["command_latency_us"] = {"p50": lat[0], "p99": lat[1], "max": lat[2]}
    return out

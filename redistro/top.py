"""``redistro top``: a live view of the running sessions, read from their Local Data.

Per node: state, cycle, configured and measured rate, manager lateness,
overruns, e-stop, the starving index (an ESC fed by the SSC), the fault once
there is one; per process: pid, role, state, scheduling, heartbeat age
(cycles since it last signed), lateness and busy time of its last cycle,
overruns and skipped cycles. The session's other processes (the plant, the
log writers) are listed from the owner's process tree. ``--once --json``
prints one sample for scripts. Reading never writes: the view attaches to
the segments and takes seqlocked snapshots like any reader.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from pathlib import Path
from typing import Any

from redistro.errors import ConfigError, IPCError, LayoutError

STATES = {0: "none", 1: "init", 2: "routine", 3: "cleanup", 4: "idle"}


def sched_text(policy: int, priority: int, nice: int) -> str:
    """A process's scheduling, from its proc row (policy: POLICY_CODES)."""
    from redistro.ipc.sched import POLICY_CODES

    name = {v: k for k, v in POLICY_CODES.items()}.get(policy, "?")
    if name == "SCHED_RR":
        return f"rr/{priority}"
    if name == "nice":
        return f"nice/{nice}"
    return "batch" if name == "SCHED_BATCH" else name


def _cmdline(pid: int) -> list[str]:
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return []
    return [a.decode(errors="replace") for a in raw.split(b"\0") if a]


def _descendants(pid: int) -> list[int]:
    from redistro.ipc.signals import children_of

    out: list[int] = []
    todo = [pid]
    while todo:
        p = todo.pop()
        kids = children_of(p)
        out += kids
        todo += kids
    return out


def _what(pid: int) -> str:
    args = _cmdline(pid)
    if "redistro.process" in args:
        i = args.index("redistro.process")
        return args[i + 1] if i + 1 < len(args) else "process"
    return os.path.basename(args[0]) if args else "?"


def _node(session_id: str, node: str) -> dict[str, Any] | None:
    from redistro.localdata.view import NodeView

    try:
        view = NodeView.attach(session_id, node)
    except LayoutError as exc:
        return {"node": node, "state": f"unreadable ({exc})", "processes": []}
    except (IPCError, OSError, ValueError):
        return None
    try:
        st = view.static
        m = view.manager()
        cycle = int(m["cycle"])
        due = int(m["tick_due_ns"])
        out: dict[str, Any] = {
            "node": node,
            "kind": view.kind,
            "state": STATES.get(int(m["state"]), "?"),
            "cycle": cycle,
            "rate_hz": float(st["rate_hz"]),
            "measured_hz": None,
            "manager_pid": int(m["pid"]),
            "manager_late_us": round((int(m["tick_ns"]) - due) / 1e3, 1) if due else None,
            "overruns": int(m["overruns"]),
            "estop": bool(m["estop"]),
            "fault": bytes(m["fault_reason"]).decode(errors="replace") or None,
            "fault_text": bytes(m["fault_text"]).decode(errors="replace") or None,
            "heartbeat_limit_cycles": int(st["heartbeat_limit_cycles"]),
            "starving_index": None,
            "processes": [],
        }
        if out["kind"] == "esc":
            sent = int(view.read("starving_sent")["count"])
            got = int(view.read("starving_delivered")["count"])
            if sent:
                out["starving_index"] = sent - got
        procs = view.procs()
        stages = [int(s) for s in st["proc_stage"]]
        for j, (name, role) in enumerate(procs):
            r = view.read("proc", j)
            wake, done, hb = int(r["wake_ns"]), int(r["done_ns"]), int(r["heartbeat_cycle"])
            out["processes"].append(
                {
                    "name": name,
                    "role": role,
                    "pid": int(r["pid"]),
                    "state": STATES.get(int(r["state"]), "?"),
                    "sched": sched_text(
                        int(r["sched_policy"]), int(r["sched_priority"]), int(r["nice"])
                    ),
                    "heartbeat_age_cycles": max(0, cycle - hb) if hb else None,
                    "late_us": round((wake - due) / 1e3, 1)
                    if stages[j] >= 0 and hb == cycle and wake
                    else None,
                    "busy_us": round((done - wake) / 1e3, 1) if done >= wake > 0 else None,
                    "cycles": int(r["cycles"]),
                    "overruns": int(r["overruns"]),
                    "skipped": int(r["skipped"]),
                }
            )
        return out
    except Exception:  # the node ended while we looked: skip it
        return None
    finally:
        view.close()


def sample(only: str | None = None) -> dict[str, Any]:
    """One look at every live session (or only that one)."""
    from redistro.ipc import names
    from redistro.ipc.session import live_sessions

    sessions = []
    for sid in live_sessions():
        if only and sid != only:
            continue
        directory = names.runtime_dir() / sid
        nodes: list[dict[str, Any]] = []
        owner = 0
        for spec_path in sorted(directory.glob("*.spec.json")):
            node = spec_path.name[: -len(".spec.json")]
            with contextlib.suppress(OSError, ValueError):
                owner = owner or int(json.loads(spec_path.read_text()).get("owner_pid", 0))
            info = _node(sid, node)
            nodes.append(info or {"node": node, "state": "not running", "processes": []})
        known = {p["pid"] for n in nodes for p in n["processes"]} | {
            n.get("manager_pid") for n in nodes
        }
        others = []
        if owner:
            for pid in _descendants(owner):
                if pid not in known:
                    others.append({"pid": pid, "what": _what(pid)})
        sessions.append(
            {"session": sid, "owner_pid": owner or None, "nodes": nodes, "other_processes": others}
        )
    if only and not sessions:
        raise ConfigError(f"top: no running session {only}")
    return {"sessions": sessions}


def measure(only: str | None, interval_s: float) -> dict[str, Any]:
    """Two samples ``interval_s`` apart: the second, with the measured rates."""
    first = sample(only)
    t0 = time.monotonic()
    time.sleep(interval_s)  # the sampling interval of a rate, not a synchronization
    second = sample(only)
    dt = time.monotonic() - t0
    before = {
        (s["session"], n["node"]): n.get("cycle") for s in first["sessions"] for n in s["nodes"]
    }
    for s in second["sessions"]:
        for n in s["nodes"]:
            c0 = before.get((s["session"], n["node"]))
            if c0 is not None and n.get("cycle") is not None:
                n["measured_hz"] = round((n["cycle"] - c0) / dt, 1)
    return second


def render(doc: dict[str, Any]) -> Any:
    """The tables of ``doc``; the names and texts a session wrote (a fault's
    text may quote a task's or a segment's name) are printed as they are,
    escaped: never read as markup."""
    from rich.console import Group
    from rich.text import Text

    parts: list[Any] = []
    if not doc["sessions"]:
        parts.append(Text("no running session"))
    for s in doc["sessions"]:
        parts.append(Text(f"session {s['session']} (owner pid {s['owner_pid']})", style="bold"))
        for n in s["nodes"]:
            if "cycle" not in n:
                parts.append(Text(f"{n['node']}: {n['state']}"))
            else:
                parts.append(_node_table(n))
        if s["other_processes"]:
            others = ", ".join(f"{o['what']} ({o['pid']})" for o in s["other_processes"])
            parts.append(Text("other processes: " + others))
    return Group(*parts)


def _node_table(n: dict[str, Any]) -> Any:
    """One node's table: its manager's line, then a line per process."""
    from rich.markup import escape
    from rich.table import Table

    estop = "[red]E-STOP[/red]" if n.get("estop") else "ok"
    starving = n.get("starving_index")
    title = (
        f"{n['node']} {n.get('state')} cycle {n.get('cycle')} "
        f"{n.get('measured_hz') or '-'}/{n.get('rate_hz', '-')} Hz, "
        f"manager late {n.get('manager_late_us')} us, overruns {n.get('overruns')}, "
        f"starving {'-' if starving is None else starving}"
        f", {estop}"
    )
    if n.get("fault"):
        title += f" [red]{escape(str(n['fault']))}: {escape(str(n.get('fault_text')))}[/red]"
    # short headings and no column rules: fits an 80-column terminal
    t = Table(
        title=title,
        title_justify="left",
        expand=False,
        box=None,
        header_style="bold underline",
        padding=(0, 0, 0, 1),
        pad_edge=False,
    )
    heads = ("name", "pid", "state", "sched", "hb age", "late us", "busy us")
    for c in (*heads, "cycles", "overruns", "skip"):
        t.add_column(c, justify="left" if c == "name" else "right", no_wrap=True)
    manager = (str(n.get("manager_pid", "")), n.get("state", ""), "", "")
    t.add_row("manager", *manager, str(n.get("manager_late_us")), "", str(n.get("cycle")),
              str(n.get("overruns")), "")  # fmt: skip
    limit = n.get("heartbeat_limit_cycles", 0)
    for p in n["processes"]:
        age = p["heartbeat_age_cycles"]
        age_s = (
            "-"
            if age is None
            else (f"[red]{age}[/red]" if limit and age > limit // 2 else str(age))
        )
        t.add_row(
            p["name"], str(p["pid"]), p["state"], p["sched"], age_s,
            str(p["late_us"] if p["late_us"] is not None else "-"),
            str(p["busy_us"] if p["busy_us"] is not None else "-"),
            str(p["cycles"]), str(p["overruns"]), str(p["skipped"]),
        )  # fmt: skip
    return t


def run_top(session: str | None, once: bool, as_json: bool, interval_s: float) -> int:
    if interval_s <= 0:
        raise ConfigError(f"--interval: expected > 0, got {interval_s}")
    if once:
        doc = measure(session, min(interval_s, 0.5))
        if as_json:
            print(json.dumps(doc, indent=1))
        else:
            from rich.console import Console

            Console().print(render(doc))
        return 0
    import signal

    from rich.live import Live

    # the entry point blocked these for the runtime; a viewer just ends on them
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})

    with Live(render(sample(session)), auto_refresh=False) as live:
        try:
            while True:
                live.update(render(measure(session, interval_s)), refresh=True)
        except KeyboardInterrupt:
            pass
    return 0


def run_zenoh_top(endpoints: list[str], cfg: Any, as_json: bool, interval_s: float) -> int:
    """Every robot group seen through these zenoh sessions: each node alive
    (its liveliness token) and its last status (host, manager pid, records
    taken, e-stop, link lost). One look; the nodes may be on any host."""
    from redistro.ddm import zenoh_transport as zt

    if interval_s <= 0:
        raise ConfigError(f"--interval: expected > 0, got {interval_s}")
    users = cfg.ddm.zenoh.users_file
    if not users:
        raise ConfigError("top --zenoh: ddm.zenoh.users_file: the viewer's password is needed")
    for e in endpoints:
        proto, _, addr = e.partition("/")
        if proto not in ("tcp", "udp", "tls", "quic") or ":" not in addr:
            raise ConfigError(f"--zenoh {e}: expected an endpoint like tcp/host:port")
    looks = []
    for e in endpoints:
        if e.startswith("tls/"):
            from redistro.session.preflight import check_zenoh_tls

            check_zenoh_tls(cfg, needed=True)
        tls = zt.tls_settings(cfg) if e.startswith("tls/") else None
        try:
            looks.append(zt.look(e, users, min(max(interval_s, 0.5), 5.0), tls))
        except ValueError as exc:
            raise ConfigError(f"top --zenoh: {exc}") from None
    if as_json:
        print(json.dumps({"zenoh": looks}, indent=1))
        return 0
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    console = Console()
    for look in looks:
        if not look["groups"]:
            console.print(escape(f"{look['endpoint']}: no group seen"))
        for group, nodes in look["groups"].items():
            title = escape(f"group {group} (through {look['endpoint']})")
            t = Table(title=title, title_justify="left")
            for c in ("node", "alive", "host", "pid", "updates", "e-stop", "link"):
                t.add_column(c)
            for n in nodes:
                t.add_row(
                    escape(str(n["node"])),
                    "yes" if n["alive"] else "[red]no[/red]",
                    escape(str(n.get("host", "-"))),
                    str(n.get("pid", "-")),
                    ",".join(str(u) for u in n.get("updates", [])) or "-",
                    "[red]E-STOP[/red]" if n.get("estop") else "-",
                    "[red]lost[/red]" if n.get("lost") else "ok",
                )
            console.print(t)
    return 0

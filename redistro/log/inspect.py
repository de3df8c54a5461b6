"""``redistro log summary|plot|export RUN``: a run folder read back.

RUN is a run folder, a session id under ``session.runs_dir``, or a
``session.mcap`` file. The figures follow the paper's: joint positions,
velocities, accelerations and torques; wrist force and torque in the tool
and the world frame; end-effector position and orientation; and per
process, histograms of the cycle timing.

Past the house's ~400 lines: each figure is a short function, and they
share the one reading of the log.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np

from redistro import files
from redistro.errors import ConfigError
from redistro.log.mcapfile import SESSION_LOG, SessionLog, read_log

MAX_POINTS = 5000  # per plotted series (the kinematics is redone per point)
NODE_COLUMNS = (
    "node",
    "result",
    "cycles",
    "rate_hz",
    "overruns",
    "lateness_p99_us",
    "logged",
    "dropped",
)


def resolve_run(arg: str, runs_dir: str) -> tuple[Path, Path]:
    """(run folder, session log) of RUN; ConfigError naming it when there is none."""
    p = Path(arg)
    if not p.exists() and (Path(runs_dir) / arg).exists():
        p = Path(runs_dir) / arg
    if p.is_file():
        if p.suffix != ".mcap":
            raise ConfigError(f"{arg}: not a run folder or a .mcap file")
        return p.parent, p
    if not p.is_dir():
        raise ConfigError(f"{arg}: no such run folder (nor a session id under {runs_dir})")
    mc = p / SESSION_LOG
    if not mc.exists():
        raise ConfigError(f"{arg}: no {SESSION_LOG} in this run folder")
    return p, mc


def load(arg: str, runs_dir: str) -> tuple[Path, SessionLog, dict[str, Any]]:
    run, path = resolve_run(arg, runs_dir)
    try:
        sl = read_log(path)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    summary: dict[str, Any] = {}
    sp = run / "summary.json"
    if sp.exists():
        from redistro.config.inputs import load_json, read_text

        try:
            summary = load_json(read_text(sp, "summary", limit=16 << 20))
        except ValueError as exc:
            raise ConfigError(f"{sp}: not valid JSON ({exc})") from None
        if not isinstance(summary, dict):
            raise ConfigError(f"{sp}: expected a JSON object, got a {type(summary).__name__}")
        from redistro.log.shapes import SUMMARY, check

        check(summary, SUMMARY, str(sp))
    return run, sl, summary


def robot_names(sl: SessionLog) -> list[str]:
    """Robots with a feedback topic (``/<robot>/feedback``)."""
    return sorted(
        parts[1]
        for parts in (t.split("/") for t in sl.arrays)
        if len(parts) == 3 and not parts[0] and parts[1] and parts[2] == "feedback"
    )


def _node_of(topic: str) -> str:
    """The node (or robot) a topic ``/<node>/...`` belongs to."""
    parts = topic.split("/")
    return parts[1] if len(parts) > 2 else topic


def board_time(sl: SessionLog, robot: str) -> np.ndarray[Any, Any]:
    """Seconds on the boards' sample clock since the first logged sample."""
    fb = sl.arrays[f"/{robot}/feedback"]
    hz = float(sl.meta("redistro.meta").get("physics_hz", 1000.0))
    step = fb["step"].astype(np.float64)
    return (step - step[0]) / hz if len(step) else step


# -- summary --


def summary_rows(run: Path, sl: SessionLog, summary: dict[str, Any]) -> dict[str, Any]:
    """Everything ``log summary`` shows, as data (also its --json)."""
    nodes = summary.get("nodes", {})
    rec = summary.get("log", {}).get("nodes", {})
    node_rows = []
    for name, n in nodes.items():
        r = rec.get(name, {})
        node_rows.append(
            {
                "node": name,
                "result": n.get("result"),
                "cycles": n.get("cycles"),
                "rate_hz": n.get("rate_hz"),
                "overruns": n.get("overruns"),
                "lateness_p99_us": (n.get("lateness_us") or {}).get("p99"),
                "logged": r.get("recorded"),
                "dropped": r.get("dropped"),
            }
        )
    faults = []
    for topic, evs in sorted(sl.events.items()):
        node = _node_of(topic)
        for e in evs:
            if topic.endswith("/events") and e.get("event") in ("fault", "estop", "guard trip"):
                faults.append(
                    {
                        "node": node,
                        "cycle": e.get("cycle"),
                        "what": e.get("event"),
                        "text": e.get("text") or e.get("reason", ""),
                    }
                )
            elif topic.endswith("/messages") and e.get("level") in ("ERROR", "CRITICAL"):
                faults.append(
                    {
                        "node": node,
                        "cycle": e.get("cycle"),
                        "what": e.get("level"),
                        "text": f"{e.get('process')}: {e.get('text')}",
                    }
                )
    segments = summary.get("segments") or []
    if not segments:
        for topic, evs in sorted(sl.events.items()):
            if topic.endswith("/segments"):
                segments += [
                    {"name": e.get("name"), "robot": e.get("robot"), "cycle": e.get("cycle")}
                    for e in evs
                    if e.get("name")
                ]
    return {
        "run": str(run),
        "task": summary.get("task") or sl.meta("redistro.meta").get("task"),
        "kind": summary.get("kind"),
        "result": summary.get("result"),
        "reason": summary.get("reason", ""),
        "started": summary.get("started"),
        "ended": summary.get("ended"),
        "segments": segments,
        "nodes": node_rows,
        "faults": faults,
        "topics": dict(sorted(sl.counts.items())),
        "inserted": summary.get("inserted"),
        "insertion_depth_m": summary.get("insertion_depth_m"),
    }


def print_summary(rows: dict[str, Any]) -> None:
    """The summary as tables; every name and text from the run is printed as
    it is (escaped: a task named ``[/x]`` is not rich markup)."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    def e(value: Any) -> str:
        return escape(str(value))

    con = Console()
    head = (
        f"[bold]{e(rows['task'])}[/bold] ({e(rows['kind'])}): "
        f"result [bold]{e(rows['result'])}[/bold]"
    )
    if rows["reason"]:
        head += f" - {e(rows['reason'])}"
    con.print(head)
    con.print(e(f"run {rows['run']}, {rows['started']} to {rows['ended']}"))
    if rows.get("inserted") is not None:
        depth = rows.get("insertion_depth_m")
        shown = "-" if depth is None else f"{depth * 1e3:.2f} mm"
        con.print(f"inserted: {e(rows['inserted'])}, depth {shown}")
    if rows["segments"]:
        t = Table(title="segments")
        keys = [
            k
            for k in ("name", "robot", "scheme", "duration_s", "cycle")
            if any(k in s for s in rows["segments"])
        ]
        for k in (*keys, "final error"):
            t.add_column(k)
        for s in rows["segments"]:
            fe = s.get("final_pose_error") or {}
            pos, rot = fe.get("position_m"), fe.get("orientation_rad")
            err = "" if pos is None or rot is None else f"{pos * 1e3:.2f} mm / {rot:.4f} rad"
            t.add_row(*[e(s.get(k, "")) for k in keys], err)
        con.print(t)
    t = Table(title="nodes")
    for k in NODE_COLUMNS:
        t.add_column(k)
    for n in rows["nodes"]:
        t.add_row(*["-" if n.get(k) is None else e(n[k]) for k in NODE_COLUMNS])
    con.print(t)
    t = Table(title="faults")
    for k in ("node", "cycle", "what", "text"):
        t.add_column(k)
    for f in rows["faults"]:
        t.add_row(e(f["node"]), e(f["cycle"]), e(f["what"]), e(f["text"]))
    if not rows["faults"]:
        t.add_row("-", "-", "none", "")
    con.print(t)
    t = Table(title="log")
    t.add_column("topic")
    t.add_column("messages", justify="right")
    for topic, n in rows["topics"].items():
        t.add_row(e(topic), str(n))
    con.print(t)


# -- export --


def export_csv(sl: SessionLog, out: Path) -> list[Path]:
    """One CSV per topic: binary channels flattened (arrays as name_1..name_n),
    JSON channels with the union of their keys. Every row starts with the log
    time [ns]. Each file is written whole under a fresh name, then renamed
    (:mod:`redistro.files`), in a folder checked safe."""
    files.make_folder(out, "--csv")
    written: list[Path] = []
    for topic, arr in sorted(sl.arrays.items()):
        path = out / (topic.strip("/").replace("/", "_") + ".csv")
        cols: list[tuple[str, np.ndarray[Any, Any]]] = [("log_time_ns", sl.log_times[topic])]
        assert arr.dtype.names is not None
        for name in arr.dtype.names:
            v = arr[name]
            if v.ndim == 1:
                cols.append((name, v))
            elif (
                arr.dtype[name].base.kind == "u"
                and arr.dtype[name].base.itemsize == 1
                and name.endswith(("text", "quantity", "source"))
            ):
                cols.append(
                    (name, np.array([bytes(r).rstrip(b"\0").decode(errors="replace") for r in v]))
                )
            else:
                for k in range(v.shape[1]):
                    cols.append((f"{name}_{k + 1}", v[:, k]))
        with files.writing(path) as f:
            w = csv.writer(f)
            w.writerow([c[0] for c in cols])
            for i in range(len(arr)):
                w.writerow([_cell(c[1][i]) for c in cols])
        written.append(path)
    for topic, evs in sorted(sl.events.items()):
        path = out / (topic.strip("/").replace("/", "_") + ".csv")
        keys: list[str] = ["log_time_ns"]
        for e in evs:
            keys += [k for k in e if k not in keys]
        with files.writing(path) as f:
            dw = csv.DictWriter(f, fieldnames=keys)
            dw.writeheader()
            for e in evs:
                dw.writerow(e)
        written.append(path)
    return written


def _cell(v: Any) -> Any:
    if isinstance(v, np.floating):
        return repr(float(v))
    if isinstance(v, np.integer):
        return int(v)
    return v


# -- plots --


def continuous_rotvec(rot: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Rotation vectors made continuous in time: r and (|r| - 2 pi) r/|r| are
    the same rotation; near pi (the peg pointing down) each sample takes the
    one nearer the previous, so the curve does not jump between +pi and -pi."""
    out = rot.copy()
    for i in range(1, len(out)):
        r = out[i]
        n = float(np.linalg.norm(r))
        if n < 1e-9:
            continue
        alt = r * (n - 2 * np.pi) / n
        if np.linalg.norm(alt - out[i - 1]) < np.linalg.norm(r - out[i - 1]):
            out[i] = alt
    return out


def _stride(n: int) -> int:
    return max(1, -(-n // MAX_POINTS))


def plot_run(sl: SessionLog, out: Path) -> list[Path]:
    """Write the PNG set; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files.make_folder(out, "--out")
    p = _Plots(plt, out)
    for r in robot_names(sl):
        fb = sl.arrays[f"/{r}/feedback"]
        if len(fb) >= 3:
            p.joints(sl, r, fb)
            p.tcp(sl, r, fb)
    believed = sl.meta("redistro.meta").get("hole_xyz_m")
    for r in robot_names(sl):
        fig = _hole_plane(plt, sl.arrays.get(f"/{r}/plan"), believed, r)
        if fig is not None:
            p.save(fig, f"{r}-hole-plane.png")
    plans = [
        sl.arrays[f"/{r}/plan"] for r in robot_names(sl) if len(sl.arrays.get(f"/{r}/plan", ()))
    ]
    if plans and "arms_clearance_m" in (plans[0].dtype.names or ()):
        p.clearance(plans[0])
    if len(plans) == 2:
        p.carry(plans[0], plans[1])
    nodes = sl.nodes()
    for topic, tm in sorted(sl.arrays.items()):
        if topic.endswith("/timing") and len(tm):
            p.timing(_node_of(topic), tm, list(nodes.get(_node_of(topic), {}).get("processes", [])))
    return p.written


class _Plots:
    """The PNG set of one session log, figure by figure."""

    def __init__(self, plt: Any, out: Path) -> None:
        self.plt, self.out = plt, out
        self.written: list[Path] = []

    def save(self, fig: Any, name: str) -> None:
        fig.tight_layout()
        path = self.out / name
        with files.writing(path, text=False) as f:
            fig.savefig(f, dpi=90, format="png")
        self.plt.close(fig)
        self.written.append(path)

    def clearance(self, plan: Any) -> None:
        """The SSC watch's nearest two arms' links and nearest link to the
        work-cell over task time, against the trip and the load check's."""
        from redistro.config.model import MIN_CLEARANCE_M, TRIP_M

        k = _stride(len(plan))
        t = plan["t_s"][::k]
        fig, ax = self.plt.subplots(figsize=(8, 4))
        for name, label in (
            ("arms_clearance_m", "arm to arm"),
            ("cell_clearance_m", "to the work-cell"),
        ):
            v = plan[name][::k] * 1e3
            ax.plot(t, np.where(np.isfinite(v), v, np.nan), lw=0.9, label=label)
        ax.axhline(TRIP_M * 1e3, color="r", lw=0.8, ls="--", label="e-stop under")
        ax.axhline(MIN_CLEARANCE_M * 1e3, color="0.5", lw=0.8, ls=":", label="load check")
        ax.set_xlabel("task time [s]")
        ax.set_ylabel("nearest [mm]")
        ax.set_title("the arms' clearance, as the SSC's watch last measured it")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        self.save(fig, "arms-clearance.png")

    def carry(self, a: Any, b: Any) -> None:
        """A carry with both hands (the cycles a position move has a goal
        wrench: the squeeze): the object as the controller sees it (the
        point between the hands and the line's yaw) and each hand's
        squeeze against its goal. Nothing when no segment carries."""
        n = min(len(a), len(b))
        a, b = a[:n], b[:n]
        ran = (a["stamp_ns"] != 0) & (b["stamp_ns"] != 0)  # (since the task's start)
        a, b = a[ran], b[ran]
        goal = np.linalg.norm(a["wrench_goal"][:, :3], axis=1)
        on = (a["scheme"] == 2) & (goal > 0)
        if not on.any():
            return
        k = _stride(len(a))
        t = a["t_s"][::k]
        mid = (a["tcp_xyz_m"] + b["tcp_xyz_m"])[::k] / 2
        line = (b["tcp_xyz_m"] - a["tcp_xyz_m"])[::k]
        yaw = np.degrees(np.unwrap(np.arctan2(line[:, 1], line[:, 0])))
        first = int(np.argmax(on[::k]))  # (the carry's start: the reference)
        fig, axes = self.plt.subplots(3, 1, figsize=(8, 8), sharex=True)
        for j, axis in enumerate("xyz"):
            m0 = mid[first, j]
            axes[0].plot(t, mid[:, j] - m0, lw=0.9, label=f"{axis} - {m0:.3f} m")
        axes[0].set_ylabel("hands' midpoint [m]")
        axes[1].plot(t, yaw - yaw[first], lw=0.9)
        axes[1].set_ylabel("the hands' line, yaw [deg]")
        for rec, label in ((a, "r1"), (b, "r2")):
            g = rec["wrench_goal"][::k, :3]
            gn = np.linalg.norm(g, axis=1)
            f = np.einsum("ij,ij->i", rec["wrench_task"][::k, :3], g) / np.where(gn > 0, gn, 1)
            axes[2].plot(t, np.where(gn > 0, f, np.nan), lw=0.8, label=f"{label} squeeze")
        axes[2].plot(t, np.where(on[::k], goal[::k], np.nan), "k--", lw=0.8, label="goal")
        axes[2].set_ylabel("internal force [N]")
        axes[2].set_xlabel("task time [s]")
        for ax in axes:
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=8)
        axes[2].legend(fontsize=8)
        axes[0].set_title("a carry with both hands: the object and the squeeze")
        self.save(fig, "carry.png")

    def joint_plot(self, t: Any, series: list[tuple[str, Any]], ylabel: str, title: str) -> Any:
        fig, axes = self.plt.subplots(7, 1, figsize=(8, 11), sharex=True)
        for j, ax in enumerate(axes):
            for label, v in series:
                ax.plot(t, v[:, j], lw=0.8, label=label)
            ax.set_ylabel(f"J{j + 1}")
            ax.grid(alpha=0.3)
        axes[0].set_title(f"{title} [{ylabel}]")
        if len(series) > 1:
            axes[0].legend(loc="upper right", fontsize=7)
        axes[-1].set_xlabel("time on the boards' clock [s]")
        return fig

    def xyz_pair(
        self, t: Any, top: tuple[Any, str, str], bottom: tuple[Any, str, str], title: str
    ) -> Any:
        """Two panels of x, y, z series: (values n x 3, label prefix, y label) each."""
        fig, axes = self.plt.subplots(2, 1, figsize=(8, 6), sharex=True)
        for ax, (v, prefix, ylabel) in zip(axes, (top, bottom), strict=True):
            for k, ax_name in enumerate("xyz"):
                ax.plot(t, v[:, k], lw=0.8, label=f"{prefix}{ax_name}")
            ax.set_ylabel(ylabel)
            ax.legend(loc="upper right", fontsize=7)
            ax.grid(alpha=0.3)
        axes[0].set_title(title)
        axes[1].set_xlabel("time on the boards' clock [s]")
        return fig

    def joints(self, sl: SessionLog, r: str, fb: Any) -> None:
        """Joint positions, velocities, accelerations and torques."""
        s = _stride(len(fb))
        t_all = board_time(sl, r)
        t = t_all[::s]
        # acceleration: the velocity's slope on the boards' clock (steps may repeat
        # when the plant is late: those samples are left out of the difference)
        keep = np.concatenate([[True], np.diff(t_all) > 0])
        tk, qdk = t_all[keep], fb["qd_rad_s"][keep]
        qdd = np.gradient(qdk, tk, axis=0) if len(tk) > 2 else np.zeros_like(qdk)
        sk = _stride(len(tk))
        for key, unit, what in (("q_rad", "rad", "positions"), ("qd_rad_s", "rad/s", "velocities")):
            fig = self.joint_plot(t, [(key.split("_")[0], fb[key][::s])], unit, f"{r} joint {what}")
            self.save(fig, f"{r}-joint-{what}.png")
        fig = self.joint_plot(tk[::sk], [("qdd", qdd[::sk])], "rad/s^2", f"{r} joint accelerations")
        self.save(fig, f"{r}-joint-accelerations.png")
        cmd = sl.arrays.get(f"/{r}/command")
        if cmd is None:
            cmd = sl.arrays.get(f"/{r}/guard")
        series = [("measured", fb["tau_nm"][::s])]
        if cmd is not None and len(cmd) == len(fb):
            series.insert(0, ("commanded", cmd["tau_nm"][::s]))
        self.save(self.joint_plot(t, series, "N m", f"{r} joint torques"), f"{r}-joint-torques.png")

    def tcp(self, sl: SessionLog, r: str, fb: Any) -> None:
        """Kinematics: the TCP's pose and the wrist's wrench, tool and world frames."""
        from redistro.control.cartesian import matrix_to_rotvec
        from redistro.control.dynamics import ArmModel
        from redistro.robotmodel import Peg

        s = _stride(len(fb))
        t, q, w = board_time(sl, r)[::s], fb["q_rad"][::s], fb["wrench"][::s]
        info = sl.robots().get(r, {})
        peg = info.get("peg")
        model = ArmModel(Peg(*peg) if peg else None, info.get("base_xyz_m"))
        pos, rot, w_world = np.zeros((len(q), 3)), np.zeros((len(q), 3)), np.zeros_like(w)
        for i in range(len(q)):
            kin = model.kinematics(np.ascontiguousarray(q[i], dtype=np.float64))
            pos[i] = kin.p
            rot[i] = matrix_to_rotvec(kin.R)
            w_world[i, :3] = kin.R @ w[i, :3]
            w_world[i, 3:] = kin.R @ w[i, 3:]
        rot = continuous_rotvec(rot)
        for frame, ww in (("tool", w), ("world", w_world)):
            top, bottom = (ww[:, :3], "F", "force [N]"), (ww[:, 3:], "T", "torque [N m]")
            fig = self.xyz_pair(t, top, bottom, f"{r} wrist force and torque, {frame} frame")
            self.save(fig, f"{r}-wrench-{frame}.png")
        top, bottom = (pos, "", "position [m]"), (rot, "r", "rotation vector [rad]")
        fig = self.xyz_pair(t, top, bottom, f"{r} end-effector (TCP) pose, world frame")
        self.save(fig, f"{r}-end-effector.png")

    def timing(self, node: str, tm: Any, procs: list[str]) -> None:
        """A node's cycle timing: lateness and busy time per process."""
        n = tm["late_us"].shape[1]
        procs += [f"p{j}" for j in range(len(procs), n)]
        fig, axes = self.plt.subplots(1, 2, figsize=(10, 4))
        tick = tm["tick_late_us"][np.isfinite(tm["tick_late_us"])]
        if len(tick):
            axes[0].hist(tick, bins=60, histtype="step", label="manager", log=True)
        for j in range(n):
            for ax, key in ((axes[0], "late_us"), (axes[1], "busy_us")):
                v = tm[key][:, j]
                v = v[np.isfinite(v)]
                if len(v):
                    ax.hist(v, bins=60, histtype="step", label=procs[j], log=True)
        axes[0].set_xlabel("lateness after the tick [us]")
        axes[1].set_xlabel("busy per cycle (woke to signed) [us]")
        for ax in axes:
            ax.set_ylabel("cycles")
            ax.legend(fontsize=7)
        fig.suptitle(f"{node} cycle timing ({len(tm)} cycles)")
        self.save(fig, f"{node}-timing.png")


def _hole_plane(plt: Any, plan: Any, believed: Any, robot: str) -> Any:
    """The tip's path in the hole's plane over a force segment's search
    (from the contact on), by phase, with the search's goal: millimetres
    from the hole's believed centre. None when the robot never searched."""
    from redistro.control.search import Phase

    if plan is None or len(plan) == 0 or "phase" not in (plan.dtype.names or ()):
        return None
    on = plan["phase"] >= Phase.SETTLE
    if not on.any():
        return None
    tcp = plan["tcp_xyz_m"][on]
    phase = plan["phase"][on]
    goal = plan["search_xy_m"][on] * 1e3
    cx, cy = (believed[0], believed[1]) if believed else (tcp[0, 0], tcp[0, 1])
    x, y = (tcp[:, 0] - cx) * 1e3, (tcp[:, 1] - cy) * 1e3
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.plot(goal[:, 0], goal[:, 1], lw=0.6, color="0.6", label="search goal")
    for ph in (Phase.SETTLE, Phase.SEARCH, Phase.IN_HOLE, Phase.NOT_FOUND):
        k = phase == ph
        if k.any():
            ax.plot(x[k], y[k], ".", ms=1.5, label=f"tip: {ph.name.lower().replace('_', ' ')}")
    ax.plot([0], [0], "k+", ms=12, label="believed centre")
    ax.set_aspect("equal")
    ax.set_xlabel("x from the hole's believed centre [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_title(f"{robot}: the tip in the hole's plane, from the contact on")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=7, markerscale=4)
    return fig

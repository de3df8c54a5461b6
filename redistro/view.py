"""``redistro view RUN``: a recorded run in the browser, in 3D (viser).

The page draws both arms from their URDF (meshes as their bounding boxes,
as in the log's ``/robot_description``) at the logged joint positions, the
work-cell as the controller believed it (the hole in blue) and the hole
where the plant really had it (red, from ``plant.json``), each tool's
goal frame and its wrist force as an arrow. Its panel gives the task, the
result, each segment's figures and each node's health (overruns,
heartbeats, DDM latency), and a timeline: a slider over the SSC's logged
cycles, play and pause, and the speed.

Everything comes from the run folder (``summary.json``, ``session.mcap``,
``plant.json``); nothing is computed but the arms' forward kinematics, in
pure Python (:class:`redistro.log.scene.Arm`). The server binds loopback;
on any other address each browser first gives a token (``view_gate.py``).
A live view whose user can read the session's key has the operator's
buttons (``operator_panel.py``).
"""

from __future__ import annotations

import contextlib
import json
import math
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from redistro.errors import ConfigError, TornReadTimeout, clipped
from redistro.localdata.view import SessionViews
from redistro.log.scene import quat_mul, quat_rotvec

FORCE_M_PER_N = 0.01  # an arrow's length per newton of wrist force
SPEEDS = ("0.25", "0.5", "1", "2", "4")
LOOPBACK = ("127.0.0.1", "localhost", "::1")
Pose = tuple[float, float, float, float, float, float, float]  # x, y, z, qx, qy, qz, qw


@dataclass
class Visual:
    link: str
    size: tuple[float, float, float]
    pose: Pose  # in the link's frame
    rgba: tuple[float, float, float, float]


@dataclass
class Recorded:
    """What a run folder holds for the view."""

    run: Path
    summary: dict[str, Any]
    meta: dict[str, Any]
    true_hole: list[float] | None
    robots: list[str]
    q: dict[str, np.ndarray[Any, Any]]  # per robot: cycles x 7
    force: dict[str, np.ndarray[Any, Any]]  # per robot: cycles x 3 (sensor frame)
    goal: dict[str, np.ndarray[Any, Any]]  # per robot: cycles x 6 (xyz, rotation vector)
    segment: np.ndarray[Any, Any]  # the SSC's running segment (1-based), per cycle
    cycles: np.ndarray[Any, Any]
    rate_hz: float

    @classmethod
    def load(cls, arg: str) -> Recorded:
        """The run in folder ``arg``; ConfigError (one line) when it is not one."""
        from redistro.log.mcapfile import read_log

        run = Path(arg)
        where = clipped(arg)
        if not run.is_dir():
            raise ConfigError(f"view: {where}: no such run folder")
        try:
            summary = json.loads((run / "summary.json").read_text())
        except (OSError, ValueError):
            raise ConfigError(
                f"view: {where}: not a run folder (no readable summary.json)"
            ) from None
        if not (run / "session.mcap").is_file():
            raise ConfigError(f"view: {where}: the run has no session log (session.mcap)")
        try:
            sl = read_log(run / "session.mcap")
        except ValueError as exc:
            raise ConfigError(f"view: {exc}") from None
        meta = sl.meta("redistro.meta")
        robots = [r for r in sl.robots() if f"/{r}/feedback" in sl.arrays]
        if not robots or not isinstance(summary, dict):
            raise ConfigError(f"view: {where}: the log has no robot's feedback to draw")
        return cls._from_log(run, summary, meta, robots, sl)

    @classmethod
    def _from_log(
        cls, run: Path, summary: dict[str, Any], meta: dict[str, Any], robots: list[str], sl: Any
    ) -> Recorded:
        fb = {r: sl.arrays[f"/{r}/feedback"] for r in robots}
        n = min(len(a) for a in fb.values())
        plans = {r: sl.arrays.get(f"/{r}/plan") for r in robots}
        goal = {}
        for r in robots:
            p = plans[r]
            if p is not None and len(p) >= n:
                goal[r] = np.hstack([p["goal_xyz_m"][:n], p["goal_rot_xyz"][:n]])
        first = next((p for p in plans.values() if p is not None and len(p) >= n), None)
        segment = first["segment"][:n] if first is not None else np.zeros(n, dtype=np.uint8)
        try:
            hole = json.loads((run / "plant.json").read_text()).get("hole") or {}
            true_hole = [float(v) for v in hole["xyz_m"]]
        except (OSError, ValueError, KeyError, TypeError):
            true_hole = None
        rate = float(sl.nodes().get("ssc", {}).get("rate_hz") or 200.0)
        return cls(
            run=run,
            summary=summary,
            meta=meta,
            true_hole=true_hole,
            robots=robots,
            q={r: np.asarray(fb[r]["q_rad"][:n], dtype=float) for r in robots},
            force={r: np.asarray(fb[r]["wrench"][:n, :3], dtype=float) for r in robots},
            goal=goal,
            segment=np.asarray(segment),
            cycles=np.asarray(fb[robots[0]]["log_cycle"][:n]),
            rate_hz=rate if math.isfinite(rate) and rate > 0 else 200.0,
        )


class Live:
    """A running session's data for the view: each ESC's feedback and the
    SSC's plan, read from their Local Data (a read-only attach, as ``top``
    and the ROS 2 bridge do; nothing written, no cycle waits) at most 30
    times a second, into one frame the view draws."""

    def __init__(
        self, session_id: str, cfg: Any, task: Any, robots: list[str], ssc_robots: list[str]
    ) -> None:
        """ssc_robots: the SSC's robots, in its order (none: no SSC to command)."""
        from redistro.log.recorder import robots_meta

        self.sid, self.robots = session_id, robots
        self.meta = robots_meta(cfg, robots)
        self.meta["hole_xyz_m"] = list(cfg.workcell.hole.xyz_m)
        self.meta["segments"] = [{"name": g.name} for g in getattr(task, "segments", [])]
        self.true_hole: list[float] | None = None  # (the controller's side never sees it)
        self.summary: dict[str, Any] = {"task": getattr(task, "task", "?"), "result": "running"}
        self.rate_hz = float(cfg.ssc.rate_hz)
        self.q = {r: np.zeros((1, 7)) for r in robots}
        self.force = {r: np.zeros((1, 3)) for r in robots}
        self.goal = {r: np.zeros((1, 6)) for r in robots}
        self.segment = np.zeros(1, dtype=np.uint8)
        self.cycles = np.zeros(1, dtype=np.int64)
        self.paused = False
        self.t_s = 0.0  # the task's time [s]
        self.views = SessionViews(session_id)
        self.lock = threading.Lock()  # (one poll at a time: a view per browser, with a token)
        from redistro.operator_panel import client_for

        self.ssc_robots = ssc_robots
        self.client = client_for(session_id) if ssc_robots else None

    def poll(self) -> None:
        """The nodes' latest data into the frame (a node not up yet, or this
        reader held off inside a read by a loaded host: as it was, until the
        next poll)."""
        with self.lock, contextlib.suppress(TornReadTimeout):
            self._poll()

    def _poll(self) -> None:
        for r in self.robots:
            esc = self.views.get(f"esc.{r}")
            if esc is not None:
                fb = esc.read("feedback", 0)
                self.q[r][0] = fb["q_rad"]
                self.force[r][0] = fb["wrench"][:3]
        ssc = self.views.get("ssc")
        if ssc is not None:
            for i, r in enumerate(self.robots):
                plan = ssc.read("plan", i)
                self.goal[r][0, :3], self.goal[r][0, 3:] = plan["goal_xyz_m"], plan["goal_rot_xyz"]
                if i == 0:
                    self.segment[0] = int(plan["segment"])
                    self.paused = bool(plan["paused"])
                    self.t_s = float(plan["t_s"])
            self.cycles[0] = ssc.cycle()

    def alive(self) -> bool:
        from redistro.ipc.session import live_sessions

        return self.sid in live_sessions()

    def close(self) -> None:
        self.views.close()


def live_session(session: str | None) -> Live:
    """The running session named (or the only one); ConfigError when none."""
    from redistro.ros2bridge import node_specs
    from redistro.ssc.ctl import session_dir

    session, directory = session_dir(session, "view --live")
    specs = node_specs(directory, 30.0, "view --live")
    first = specs.get("ssc") or next(iter(specs.values()))
    robots = sorted({r for sp in specs.values() if sp.kind == "esc" for r in sp.robots})
    ssc = list(specs["ssc"].robots) if "ssc" in specs else []
    return Live(session, first.cfg(), first.task() if first.task_data else None, robots, ssc)


def check_address(bind: str, port: int) -> None:
    """The address the page is served on, decided before anything starts:
    loopback, or an IP address of this host (then the page asks for a token)."""
    import ipaddress

    if bind != "localhost":
        try:
            ipaddress.ip_address(bind)
        except ValueError:
            raise ConfigError(
                f"view: --bind {clipped(bind)}: expected an IP address of this host"
            ) from None
    if not 1 <= port <= 65535:
        raise ConfigError(f"view: --port {port}: expected 1-65535")
    family = socket.AF_INET6 if ":" in bind else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((bind, port))
        except OSError as exc:
            what = f"--bind {clipped(bind)} --port {port}"
            raise ConfigError(f"view: {what}: {exc.strerror or exc}") from None


def run_view(arg: str | None, port: int, bind: str, live: str | None = None) -> int:
    """Serve the page until interrupted (Ctrl-C, SIGTERM), or, live, until
    the session ends. Off loopback, each browser first gives the token
    printed here (``view_gate.py``)."""
    if (arg is None) == (live is None):
        raise ConfigError("view: give a run folder, or --live [SESSION] (not both)")
    check_address(bind, port)
    rec: Any = Recorded.load(arg) if arg is not None else live_session(live or None)
    import viser

    server = viser.ViserServer(host=bind, port=port, verbose=False)
    what = f"session {rec.sid}" if isinstance(rec, Live) else str(rec.run)
    view, gate = None, None
    if bind in LOOPBACK:
        view = View(server, rec)
    else:
        from redistro.view_gate import Gate

        gate = Gate(server, lambda client: View(server, rec, client))
        print(f"token: {gate.token} (the page asks for it)", flush=True)
    print(f"view of {what} on http://{bind}:{port}/ (Ctrl-C ends it)", flush=True)
    try:
        if view is not None:
            view.wait()
        else:
            _wait(rec)
    finally:
        if view is not None:
            view.stop()
        if gate is not None:
            gate.close()
        server.stop()
        if isinstance(rec, Live):
            rec.close()
    return 0


def _wait(rec: Recorded | Live) -> None:
    """Until a stop signal or, live, the session's end."""
    import signal

    from redistro.ipc import signals

    stops = frozenset({signal.SIGINT, signal.SIGTERM, signal.SIGHUP})
    while signals.wait(stops, 0.5) is None:
        if isinstance(rec, Live) and not rec.alive():
            return


def _mul(a: Pose, b: Pose) -> Pose:
    """The pose a then b (b expressed in a's frame)."""
    ax, ay, az, qx, qy, qz, qw = a
    bx, by, bz = b[:3]
    # rotate b's translation by a's rotation: v + 2 w (u x v) + 2 u x (u x v)
    tx, ty, tz = 2 * (qy * bz - qz * by), 2 * (qz * bx - qx * bz), 2 * (qx * by - qy * bx)
    rx = bx + qw * tx + (qy * tz - qz * ty)
    ry = by + qw * ty + (qz * tx - qx * tz)
    rz = bz + qw * tz + (qx * ty - qy * tx)
    return (ax + rx, ay + ry, az + rz, *quat_mul(a[3:], b[3:]))


def _wxyz(p: Pose) -> tuple[float, float, float, float]:
    return (p[6], p[3], p[4], p[5])


class Kinematics:
    """Every link's pose in the world at joint positions q, per robot."""

    def __init__(self, rec: Recorded | Live) -> None:
        from redistro.log.scene import Arm

        robots = rec.meta.get("robots", {})
        self.arms = {r: Arm(r, robots.get(r, {}).get("peg")) for r in rec.robots}
        self.bases = {r: tuple(robots.get(r, {}).get("base_xyz_m", (0, 0, 0))) for r in rec.robots}

    def links(self, robot: str, q: Any) -> dict[str, Pose]:
        arm = self.arms[robot]
        x, y, z = self.bases[robot]
        poses: dict[str, Pose] = {arm.base: (x, y, z, 0.0, 0.0, 0.0, 1.0)}
        steps = [
            (p, c, t) for (p, c, *_), t in zip(arm.moving, arm.transforms(list(q)), strict=True)
        ]
        steps += arm.fixed
        for _ in range(len(steps)):
            left = []
            for parent, child, t in steps:
                if parent in poses:
                    poses[child] = _mul(poses[parent], t)
                else:
                    left.append((parent, child, t))
            if not left:
                break
            steps = left
        return poses


def visuals(kin: Kinematics, rec: Recorded | Live) -> list[Visual]:
    """Each link's boxes (the group URDF's, meshes as bounding boxes)."""
    import xml.etree.ElementTree as ET

    from redistro.log.scene import group_urdf
    from redistro.robotmodel import quat_rpy

    bases = {r: list(kin.bases[r]) for r in rec.robots}
    root = ET.fromstring(group_urdf(kin.arms, bases).split("\n", 1)[1])
    out = []
    for link in root.iter("link"):
        for vis in link.findall("visual"):
            box = vis.find("geometry/box")
            if box is None:
                continue
            o = vis.find("origin")
            xyz = [float(v) for v in (o.get("xyz", "0 0 0") if o is not None else "0 0 0").split()]
            rpy = [float(v) for v in (o.get("rpy", "0 0 0") if o is not None else "0 0 0").split()]
            color = vis.find("material/color")
            rgba = [
                float(v)
                for v in str(color.get("rgba") if color is not None else "0.6 0.6 0.65 1").split()
            ]
            size = tuple(float(v) for v in str(box.get("size")).split())
            pose = (*xyz, *quat_rpy(*rpy))
            out.append(Visual(str(link.get("name")), size, pose, tuple(rgba)))  # type: ignore[arg-type]
    return out


class View:
    """The page of one recorded run (the scene, the panel, the timeline) or
    of a running session (the scene and the panel, followed live)."""

    def __init__(self, server: Any, rec: Recorded | Live, api: Any = None) -> None:
        """api: where the page is drawn: the server (every browser sees it)
        or one client (a browser that gave the token)."""
        self.server, self.rec = server, rec
        self.api = server if api is None else api
        self.kin = Kinematics(rec)
        self.frame = 0
        self.playing = False
        self.speed = 1.0
        self.stopping = threading.Event()
        self.ended = threading.Event()  # (live: the session ended)
        self._scene()
        self._panel()
        self.show(0)
        self.player = threading.Thread(target=self._play, name="view-player", daemon=True)
        self.player.start()

    def _scene(self) -> None:
        sc, rec = self.api.scene, self.rec
        sc.set_up_direction("+z")
        sc.add_grid("/ground", width=2.0, height=2.0, position=(0.5, 0.0, 0.0))
        self.nodes: dict[str, Any] = {}
        for i, v in enumerate(visuals(self.kin, rec)):
            if v.link not in self.nodes:
                self.nodes[v.link] = sc.add_frame(f"/robots/{v.link}", show_axes=False)
            rgb = tuple(int(255 * c) for c in v.rgba[:3])
            sc.add_box(f"/robots/{v.link}/v{i}", color=rgb, dimensions=v.size,
                       position=v.pose[:3], wxyz=_wxyz(v.pose))  # fmt: skip
        cell = rec.meta.get("workcell") or {}
        top = float(cell.get("table_top_m", 0.0))
        if "table_half_xy_m" in cell:
            hx, hy = cell["table_half_xy_m"]
            sc.add_box("/workcell/table", color=(200, 200, 190), dimensions=(2 * hx, 2 * hy, 0.02),
                       position=(float(cell.get("table_x_m", 0.5)), 0.0, top - 0.01))  # fmt: skip
        believed = rec.meta.get("hole_xyz_m")
        if believed is not None:  # (the hole's mouth: a blue disc where it was believed)
            sc.add_cylinder("/workcell/hole_believed", radius=0.02, height=0.002,
                            color=(40, 90, 230), position=tuple(believed))  # fmt: skip
        if rec.true_hole is not None:  # (and a red one where the plant had it)
            sc.add_cylinder("/workcell/hole_true", radius=0.012, height=0.004,
                            color=(230, 40, 40), position=tuple(rec.true_hole))  # fmt: skip
        for name, obj in (cell.get("objects") or {}).items():
            x, y = obj["xy_m"]
            size = obj["size_xyz_m"]
            sc.add_box(f"/workcell/{name}", color=(170, 140, 90), dimensions=tuple(size),
                       position=(x, y, top + size[2] / 2), opacity=0.6)  # fmt: skip
        self.goals = {r: sc.add_frame(f"/goals/{r}", axes_length=0.06, axes_radius=0.003)
                      for r in rec.goal}  # fmt: skip
        self.arrows: dict[str, Any] = {}
        camera = self.api.initial_camera if self.api is self.server else self.api.camera
        camera.position = (1.9, -1.4, 1.3)
        camera.look_at = (0.55, 0.0, 0.35)

    def _panel(self) -> None:
        gui, rec = self.api.gui, self.rec
        if isinstance(rec, Live):  # (no timeline: the session's now)
            if rec.client is not None:  # (the session's key is ours: the operator's buttons)
                from redistro.operator_panel import OperatorPanel

                self.operator = OperatorPanel(gui, rec.client, rec.ssc_robots)
            self.status = gui.add_markdown(self._status(0))
            gui.add_markdown(run_text(rec))
            return
        gui.add_markdown(run_text(rec))
        n = len(rec.cycles)
        self.slider = gui.add_slider("cycle", min=0, max=max(1, n - 1), step=1, initial_value=0)
        self.play_button = gui.add_button("Play")
        self.speed_menu = gui.add_dropdown("speed", options=SPEEDS, initial_value="1")
        self.status = gui.add_markdown(self._status(0))

        self.slider.on_update(self._moved)
        self.play_button.on_click(self._play_pause)
        self.speed_menu.on_update(self._speed)

    def _moved(self, _event: Any) -> None:
        if int(self.slider.value) != self.frame:
            self.show(int(self.slider.value))

    def _play_pause(self, _event: Any) -> None:
        self.playing = not self.playing
        self.play_button.label = "Pause" if self.playing else "Play"

    def _speed(self, _event: Any) -> None:
        self.speed = float(self.speed_menu.value)

    def _status(self, k: int) -> str:
        rec = self.rec
        seg = int(rec.segment[k]) if len(rec.segment) else 0
        names = [str(g.get("name")) for g in rec.meta.get("segments", [])]
        name = names[seg - 1] if 0 < seg <= len(names) else ("before" if seg == 0 else "after")
        if isinstance(rec, Live):  # (a tenth of a second: the panel redrawn 10 times a second)
            paused = " · **paused**" if rec.paused else ""
            return f"t = {rec.t_s:.1f} s · segment: {name}{paused}"
        t = k / rec.rate_hz
        return f"**cycle {int(rec.cycles[k])}** · t = {t:.2f} s · segment: {name}"

    def show(self, k: int) -> None:
        """Draw logged cycle ``k`` (an index into the SSC's cycles)."""
        rec = self.rec
        k = max(0, min(k, len(rec.cycles) - 1))
        self.frame = k
        sc = self.api.scene
        with self.api.atomic():
            for r in rec.robots:
                poses = self.kin.links(r, rec.q[r][k])
                for link, pose in poses.items():
                    node = self.nodes.get(link)
                    if node is not None:
                        node.position, node.wxyz = pose[:3], _wxyz(pose)
                tool = next((p for n, p in poses.items() if n.endswith("tool")), None)
                if tool is None:
                    tool = poses[list(poses)[-1]]
                f = rec.force[r][k]
                fx, fy, fz = (float(v) * FORCE_M_PER_N for v in f)
                tip = _mul(tool, (fx, fy, fz, 0.0, 0.0, 0.0, 1.0))
                pts = np.array([[tool[:3], tip[:3]]], dtype=np.float32)
                drawn = self.arrows.get(r)
                # (an arrow is drawn anew: only when it moved by 2 mm or more)
                if drawn is None or float(np.abs(drawn - pts).max()) >= 0.002:
                    self.arrows[r] = pts
                    sc.add_arrows(f"/forces/{r}", points=pts, colors=(250, 160, 20),
                                  shaft_radius=0.004, head_radius=0.01,
                                  head_length=0.02)  # fmt: skip
                if r in self.goals:
                    g = rec.goal[r][k]
                    rot = quat_rotvec(float(g[3]), float(g[4]), float(g[5]))
                    self.goals[r].position = tuple(float(v) for v in g[:3])
                    self.goals[r].wxyz = (rot[3], rot[0], rot[1], rot[2])
            status = self._status(k)
            if status != self.status.content:
                self.status.content = status
        if not isinstance(rec, Live) and int(self.slider.value) != k:
            self.slider.value = k

    def _play(self) -> None:
        period = 1.0 / 30  # at most 30 pictures a second
        if isinstance(self.rec, Live):
            self._follow(self.rec, period)
            return
        while not self.stopping.wait(period):
            if not self.playing:
                continue
            step = max(1, round(self.speed * self.rec.rate_hz * period))
            nxt = self.frame + step
            if nxt >= len(self.rec.cycles) - 1:
                nxt = len(self.rec.cycles) - 1
                self.playing = False
                self.play_button.label = "Play"
            self.show(nxt)

    def _follow(self, live: Live, period: float) -> None:
        """The running session, drawn at most 30 times a second, until it ends."""
        alive_at = 0.0
        while not self.stopping.wait(period):
            now = time.monotonic()
            if now >= alive_at:
                if not live.alive():
                    self.status.content = "the session has ended"
                    self.ended.set()
                    return
                alive_at = now + 1.0
            live.poll()
            self.show(0)

    def wait(self) -> None:
        import signal

        from redistro.ipc import signals

        stops = frozenset({signal.SIGINT, signal.SIGTERM, signal.SIGHUP})
        while not self.ended.is_set() and signals.wait(stops, 0.2) is None:
            pass

    def stop(self) -> None:
        self.stopping.set()
        self.player.join(timeout=2.0)


def run_text(rec: Recorded | Live) -> str:
    """The panel's text: the task, the result, the segments, the nodes' health."""
    s = rec.summary
    lines = [f"### {s.get('task', '?')}", f"result: **{s.get('result', '?')}**"]
    if s.get("reason"):
        lines.append(f"({s['reason']})")
    if "inserted" in s:
        lines.append(f"inserted: {s['inserted']}")
    lines.append("")
    lines.append("| segment | robot | scheme | s | pose error mm |")
    lines.append("| --- | --- | --- | ---: | ---: |")
    for seg in s.get("segments", []):
        err = (seg.get("final_pose_error") or {}).get("position_m")
        e = f"{err * 1e3:.2f}" if isinstance(err, int | float) else "-"
        lines.append(f"| {seg.get('name')} | {seg.get('robot')} | {seg.get('scheme')} | "
                     f"{seg.get('duration_s', 0):.2f} | {e} |")  # fmt: skip
    lines.append("")
    lines.append("| node | cycles | overruns | missed heartbeats | DDM command p50 µs |")
    lines.append("| --- | ---: | ---: | ---: | ---: |")
    ddm = s.get("ddm") or {}
    for name, n in (s.get("nodes") or {}).items():
        lat = (ddm.get(name) or {}).get("command_latency_us") or {}
        p50 = lat.get("p50", "-") if isinstance(lat, dict) else "-"
        p50 = f"{p50:.0f}" if isinstance(p50, int | float) else p50
        lines.append(f"| {name} | {n.get('cycles')} | {n.get('overruns')} | "
                     f"{n.get('missed_heartbeats')} | {p50} |")  # fmt: skip
    return "\n".join(lines)


def wait_served(port: int, timeout_s: float = 30.0) -> bool:
    """Whether something answers on 127.0.0.1:port within the timeout."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket() as s:
            s.settimeout(0.5)
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return True
        time.sleep(0.05)  # polling a condition with a deadline
    return False

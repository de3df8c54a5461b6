"""The running group as ROS 2 topics over Zenoh, with rmw_zenoh's conventions.

``redistro bridge [SESSION]`` (or ``--set ros2.bridge=true`` on a session)
attaches to the nodes' Local Data from outside, read-only (seqlocked
snapshots, as ``redistro top``), at most ``ros2.rate_hz`` times a second,
and publishes on a zenoh session of its own, listening on ``ros2.listen``:

- ``/<robot>/joint_states`` (``sensor_msgs/msg/JointState``) and
  ``/<robot>/wrench`` (``geometry_msgs/msg/WrenchStamped``): each ESC's
  measured feedback, as the session log has them;
- ``/ssc/segment`` (``std_msgs/msg/String``): the SSC's running segment,
  when it changes and once a second.

As rmw_zenoh does: each sample on ``<domain>/<topic>/<DDS type>/<type
hash>``, CDR with its encapsulation header, an attachment (sequence number,
source time stamp, the publisher's 16-byte GID); a liveliness token for the
node and one per publisher under ``@ros2_lv``, so a ROS 2 machine's graph
(``ros2 topic list``) shows them. Nothing reaches the group from here: the
bridge has no subscriber and no link to the DDMs, and its session's access
rules refuse every sample that comes in. No node does more work per cycle.
"""

from __future__ import annotations

import json
import os
import signal
import struct
import time
import uuid
from dataclasses import dataclass, field
from typing import Any

from redistro.errors import ConfigError
from redistro.localdata.view import SessionViews
from redistro.log import ros2

NODE_NAME = "redistro_bridge"
STRING = "std_msgs/msg/String"
# reliable, volatile, keep last 10 (rmw_zenoh's compact QoS text: defaults left empty)
QOS = "::,10:,:,:,,"
ATTACHMENT = struct.Struct("<qqB16s")  # sequence, source time [ns], GID length, GID


def dds_type(msgtype: str) -> str:
    """``sensor_msgs/msg/JointState`` -> ``sensor_msgs::msg::dds_::JointState_``."""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def type_hash(msgtype: str) -> str:
    """The type's REP-2011 hash (``RIHS01_<sha256>``) from its definition."""
    from redistro.log.scene import full_store

    return str(full_store().hash_rihs01(msgtype))


def mangle(name: str) -> str:
    """A name in a liveliness token: ``/`` as ``%`` (``%`` alone: empty)."""
    return name.replace("/", "%") if name not in ("", "/") else "%"


@dataclass
class Topic:
    """One publisher: its key, its liveliness token, its sequence."""

    name: str
    msgtype: str
    entity: int
    domain: int
    gid: bytes = field(default_factory=lambda: uuid.uuid4().bytes)
    seq: int = 0
    pub: Any = None

    @property
    def key(self) -> str:
        h = type_hash(self.msgtype)
        return f"{self.domain}/{self.name.lstrip('/')}/{dds_type(self.msgtype)}/{h}"

    def token(self, zid: str) -> str:
        return (
            f"@ros2_lv/{self.domain}/{zid}/0/{self.entity}/MP/%/%/{NODE_NAME}/"
            f"{mangle(self.name)}/{dds_type(self.msgtype)}/{type_hash(self.msgtype)}/{QOS}"
        )

    def put(self, payload: bytes, now_ns: int) -> None:
        self.seq += 1
        self.pub.put(payload, attachment=ATTACHMENT.pack(self.seq, now_ns, 16, self.gid))


def session_settings(listen: list[str], domain: int) -> dict[str, Any]:
    """The bridge's zenoh session: a peer on its endpoints, no scouting,
    access rules that let out only its own topics and graph tokens."""
    out_keys = [f"{domain}/**", f"@ros2_lv/{domain}/**"]
    return {
        "mode": "peer",
        "listen/endpoints": listen,
        "connect/endpoints": [],
        "scouting/multicast/enabled": False,
        "scouting/gossip/enabled": False,
        "transport/shared_memory/enabled": False,  # (a /dev/shm file outlives the process)
        "access_control": {
            "enabled": True,
            "default_permission": "deny",
            "rules": [
                {
                    "id": "out",
                    "messages": ["put", "liveliness_token", "declare_liveliness_subscriber"],
                    "flows": ["egress"],
                    "permission": "allow",
                    "key_exprs": out_keys,
                },
                {
                    "id": "interest",  # a subscriber's interest, a graph query, from ROS 2
                    "messages": [
                        "declare_subscriber",
                        "liveliness_token",
                        "declare_liveliness_subscriber",
                        "liveliness_query",
                        "query",
                        "reply",
                    ],
                    "flows": ["ingress", "egress"],
                    "permission": "allow",
                    "key_exprs": out_keys,
                },
            ],
            "subjects": [{"id": "all"}],
            "policies": [{"rules": ["out", "interest"], "subjects": ["all"]}],
        },
    }


class Bridge:
    """One running session's topics (``run`` publishes until it ends)."""

    PER_ROBOT = (("joint_states", ros2.JOINT_STATE), ("wrench", ros2.WRENCH_STAMPED))

    def __init__(self, session_id: str, cfg: Any, task: Any, robots: list[str]) -> None:
        from redistro.localdata.layout import FEEDBACK
        from redistro.robotmodel import JOINT_NAMES

        self.sid, self.cfg = session_id, cfg
        self.robots = robots
        self.segments = [s.name for s in getattr(task, "segments", [])] if task else []
        d = cfg.ros2.domain_id
        self.topics: dict[str, Topic] = {}
        types = [(f"/{r}/{k}", t) for r in robots for k, t in self.PER_ROBOT]
        for i, (name, msgtype) in enumerate([*types, ("/ssc/segment", STRING)]):
            self.topics[name] = Topic(name, msgtype, i + 1, d)
        fields = FEEDBACK.fields
        assert fields is not None
        offsets = {k: 8 + int(fields[k][1]) for k in ("q_rad", "qd_rad_s", "tau_nm", "wrench")}
        self.packers = {r: ros2.Feedback(r, list(JOINT_NAMES), offsets) for r in robots}
        self.views = SessionViews(session_id)
        self.last: dict[str, int] = {}
        self.segment = ("", 0)
        self.published = 0

    def tick(self, now_ns: int) -> None:
        """One look at the nodes: what changed goes out."""
        for r in self.robots:
            view = self.views.get(f"esc.{r}")
            if view is None:
                continue
            fb = view.read("feedback", 0)
            stamp = int(fb["stamp_ns"])
            if stamp == self.last.get(r) or stamp == 0:
                continue
            self.last[r] = stamp
            packed = int(view.cycle()).to_bytes(8, "little") + fb.tobytes()
            p = self.packers[r]
            self.topics[f"/{r}/joint_states"].put(p.joint_state(packed, now_ns), now_ns)
            self.topics[f"/{r}/wrench"].put(p.wrench(packed, now_ns), now_ns)
            self.published += 2
        ssc = self.views.get("ssc")
        if ssc is not None and self.robots:
            k = int(ssc.read("plan", 0)["segment"])
            name = self.segments[k - 1] if 0 < k <= len(self.segments) else ""
            text = json.dumps({"index": k, "name": name})
            if text != self.segment[0] or now_ns - self.segment[1] >= 1_000_000_000:
                self.segment = (text, now_ns)
                self.topics["/ssc/segment"].put(ros2.event(text), now_ns)
                self.published += 1

    def run(self, stop: list[bool]) -> int:
        """Publish until the session ends or ``stop`` is set."""
        import zenoh

        from redistro.ddm.zenoh_transport import open_session
        from redistro.ipc.session import live_sessions

        cfg = self.cfg.ros2
        try:
            s = open_session(session_settings(list(cfg.listen), cfg.domain_id))
        except zenoh.ZError as exc:
            raise ConfigError(f"ros2.listen: {cfg.listen}: {str(exc).split(' at ')[0]}") from exc
        try:
            zid = str(s.info.zid())
            node = f"@ros2_lv/{cfg.domain_id}/{zid}/0/0/NN/%/%/{NODE_NAME}"
            tokens = [s.liveliness().declare_token(node)]
            for t in self.topics.values():
                t.pub = s.declare_publisher(t.key, congestion_control=zenoh.CongestionControl.DROP)
                tokens.append(s.liveliness().declare_token(t.token(zid)))
            period = 1.0 / cfg.rate_hz
            next_t = time.monotonic()
            next_alive = 0.0
            while not stop[0]:
                now = time.monotonic()
                if now >= next_alive:
                    if self.sid not in live_sessions():
                        break
                    next_alive = now + 1.0
                self.tick(time.time_ns())
                next_t = max(next_t + period, now)
                time.sleep(max(0.0, next_t - time.monotonic()))
            for tok in tokens:
                tok.undeclare()
        finally:
            self.views.close()
            s.close()
        return 0


def run_bridge(session: str | None, listen: list[str] | None = None, wait_s: float = 30.0) -> int:
    """``redistro bridge``: the session named (or the only one running),
    its config from its nodes' specs (``listen``: other endpoints)."""
    import dataclasses

    from redistro.config.checks import endpoint_problem
    from redistro.ipc import names
    from redistro.ipc.session import live_sessions

    for i, e in enumerate(listen or []):
        if endpoint_problem(e):
            raise ConfigError(f"bridge: --listen[{i}]: {endpoint_problem(e)}")
    live = live_sessions()
    if session is None:
        if len(live) != 1:
            raise ConfigError(
                f"bridge: {len(live)} sessions running; name one ({', '.join(live) or 'none'})"
            )
        session = live[0]
    if session not in live:
        raise ConfigError(f"bridge: no running session {session}")
    specs = node_specs(names.runtime_dir() / session, wait_s)
    first = specs.get("ssc") or next(iter(specs.values()))
    cfg = first.cfg()
    if listen:
        cfg = dataclasses.replace(cfg, ros2=dataclasses.replace(cfg.ros2, listen=list(listen)))
    task = first.task() if first.task_data else None
    robots = sorted({r for sp in specs.values() if sp.kind == "esc" for r in sp.robots})
    stop = [False]

    def end(*_: object) -> None:
        stop[0] = True

    signal.signal(signal.SIGINT, end)
    signal.signal(signal.SIGTERM, end)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    print(f"bridge {session}: ROS 2 topics on {', '.join(cfg.ros2.listen)}", flush=True)
    return Bridge(session, cfg, task, robots).run(stop)


def node_specs(directory: os.PathLike[str], wait_s: float, who: str = "bridge") -> dict[str, Any]:
    """The session's node specs by node (waited for while its nodes start)."""
    from pathlib import Path

    from redistro.process.spec import NodeSpec

    deadline = time.monotonic() + wait_s
    while True:
        out: dict[str, Any] = {}
        for p in sorted(Path(directory).glob("*.spec.json")):
            try:
                out[p.name[: -len(".spec.json")]] = NodeSpec.load(p)
            except (OSError, ValueError):
                continue
        if any(sp.kind == "esc" for sp in out.values()) or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    if not out:
        raise ConfigError(f"{who}: the session's nodes are not up ({directory})")
    return out

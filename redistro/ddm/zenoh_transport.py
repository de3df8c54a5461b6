"""The DDM over Eclipse Zenoh: a robot group's records as pub/sub samples.

Each ddm opens one zenoh session. The SSC's ddm publishes each robot's
command at ``redistro/<group>/<robot>/command`` and subscribes to every
robot's ``.../feedback`` (one subscriber for them all); an ESC's ddm the
other way round, for its own robot. The samples are the same signed records
as on the other transports (checked and admitted by the ddm, never
pickled). The usual record is taken whole in zenoh's thread, through the
ddm's answer (``Transport.answer_with``): an ESC's command admitted and
answered with the newest feedback in the RX thread that read it, the
SSC's feedback admitted in zenoh-python's callback thread. Anything else
goes to an inbox and wakes the ddm through an eventfd. Each ddm declares a
liveliness token (``redistro/<group>/<node>/alive``): a peer whose token
goes is a lost link, as a closed socket is. The start-up meeting point, the
starving index and the group's e-stop work as over sockets: they are in the
records.

Every session authenticates with a user and password (``<node>@<group>``,
from ``ddm.zenoh.users_file`` or the session's own file): a session with
the wrong password is refused at the door, so its peers report it missing.
With ``ddm.zenoh.access_control`` the session that accepts connections
(the SSC's, by default: zenoh's authentication names the side that
connects, and the rules name users) refuses what each peer may not send:
it takes each robot's feedback only from that robot's ESC and sends that
ESC only its robot's commands (:func:`access_rules`); zenoh drops a refused
sample before it reaches any ddm. An ESC that only connects has no other
peer.

Zenoh starts threads of its own: like numpy's, they exist only in a process
whose signals are already blocked (every entry point blocks them first).
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import threading
import time
import zlib
from collections import deque
from collections.abc import Callable, Collection, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from redistro.ddm.transport import ANSWERED, REPLY_OWED, Accelerator, Links, Transport
from redistro.errors import TransportError

if TYPE_CHECKING:
    from redistro.config import Config

SESSION_USERS = "zenoh.users"  # a session's users file, in its runtime directory
PREFIX = "redistro"
# what every session exchanges with its peers besides the records: the
# subscriptions and the liveliness tokens (link-loss detection, redistro top)
DECLARATIONS = [
    "declare_subscriber",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
    "reply",
]


def group_of(cfg: Config, link: str) -> str:
    return cfg.ddm.zenoh.group or link


def user_of(node: str, group: str) -> str:
    return f"{node}@{group}"


def command_key(group: str, robot: str) -> str:
    return f"{PREFIX}/{group}/{robot}/command"


def feedback_key(group: str, robot: str) -> str:
    return f"{PREFIX}/{group}/{robot}/feedback"


def alive_key(group: str, node: str) -> str:
    return f"{PREFIX}/{group}/{node}/alive"


def status_key(group: str, node: str) -> str:
    return f"{PREFIX}/{group}/{node}/status"


VIEWER = "top"  # the user ``redistro top --zenoh`` connects as
STATUS_EVERY = 256  # ddm steps between two status reports (~1 s at 200 Hz, both ways)
RETRY_S = 0.2  # a client whose door is not up yet tries again this often
# A peer's records and its liveliness token's loss come in two of
# zenoh-python's threads, so the loss can overtake the records the peer put
# just before it closed: the link is lost once no record came for this long
# after its token went (a suite's load delayed them past the loss).
LOSS_GRACE_S = 0.1


def ssc_port(cfg: Config, group: str) -> int:
    """Where the SSC's session listens: ``ddm.zenoh.port``, else derived,
    below the ESCs' socket ports and Linux's ephemeral ports (32768-60999:
    a connection made anywhere on the host may take one of those as its
    own, and the listen then fails with EADDRINUSE)."""
    return cfg.ddm.zenoh.port or 13000 + zlib.crc32(f"zenoh/{group}".encode()) % 8000


# -- users --


def new_users_file(path: Path | str, group: str, nodes: Iterable[str]) -> None:
    """A users file for one group's nodes and a viewer (random passwords,
    mode 0600, created, never overwritten)."""
    users = [*(user_of(n, group) for n in nodes), VIEWER]
    lines = "".join(f"{u}:{secrets.token_hex(16)}\n" for u in users)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    try:
        os.write(fd, lines.encode())
    finally:
        os.close(fd)


def read_users(path: Path | str) -> dict[str, str]:
    """user -> password from a users file (``name:password`` lines; a
    private file: :func:`redistro.ddm.record.read_private`). ValueError
    naming what is wrong."""
    from redistro.ddm.record import read_private

    users: dict[str, str] = {}
    for n, line in enumerate(read_private(path, "users", 1 << 16).splitlines(), 1):
        if not line.strip():
            continue
        user, sep, password = line.strip().partition(":")
        if not sep or not user or not password:
            raise ValueError(f"{path}: line {n}: expected name:password")
        users[user] = password
    return users


# -- the session's configuration --


def access_rules(group: str, node: str, kind: str, robots: list[str]) -> dict[str, Any]:
    """The ``access_control`` block of one node's session: deny by default;
    the declarations every peer of the group makes; the SSC takes each
    robot's feedback from that robot's ESC and sends it its commands; an
    ESC takes its robot's commands from the SSC and sends it its feedback."""
    # declarations (subscriptions, liveliness) on any redistro key: a
    # viewer's subscription across groups (redistro/*/*/status) must reach
    # the ESCs, or their clients never send it what it asks for; data are
    # allowed key by key below
    rules: list[dict[str, Any]] = [
        {
            "id": "declarations",
            "permission": "allow",
            "flows": ["ingress", "egress"],
            "messages": DECLARATIONS,
            "key_exprs": [f"{PREFIX}/**"],
        }
    ]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    if kind == "ssc":
        peers = {r: user_of(f"esc.{r}", group) for r in robots}
    else:
        peers = {robots[0]: user_of("ssc", group)}
    for r, user in peers.items():
        ingress = feedback_key(group, r) if kind == "ssc" else command_key(group, r)
        egress = command_key(group, r) if kind == "ssc" else feedback_key(group, r)
        rules += [
            {
                "id": f"in.{r}",
                "permission": "allow",
                "flows": ["ingress"],
                "messages": ["put"],
                "key_exprs": [ingress],
            },
            {
                "id": f"out.{r}",
                "permission": "allow",
                "flows": ["egress"],
                "messages": ["put"],
                "key_exprs": [egress],
            },
        ]
        subjects.append({"id": f"peer.{r}", "usernames": [user]})
        policies.append(
            {"rules": ["declarations", f"in.{r}", f"out.{r}"], "subjects": [f"peer.{r}"]}
        )
    # the nodes' status: each peer's own comes in, every one goes out to a
    # viewer (``redistro top --zenoh``), who sends nothing
    rules += [
        {
            "id": "status.in",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["put"],
            "key_exprs": [status_key(group, n) for n in _peer_nodes(kind, robots)],
        },
        {
            "id": "status.out",
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["put"],
            "key_exprs": [status_key(group, "*")],
        },
    ]
    for policy in policies:
        policy["rules"].append("status.in")
    # a viewer declares and asks, and gets only this group's status
    subjects.append({"id": "viewer", "usernames": [VIEWER]})
    policies.append({"rules": ["declarations", "status.out"], "subjects": ["viewer"]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def _peer_nodes(kind: str, robots: list[str]) -> list[str]:
    return [f"esc.{r}" for r in robots] if kind == "ssc" else ["ssc"]


def _settings(user: str, users_file: str, *, scouting: bool) -> dict[str, Any]:
    """What every session of the project sets: scouting, no shared memory,
    and ``user``'s password from ``users_file`` (ValueError: none there)."""
    users = read_users(users_file)
    if user not in users:
        raise ValueError(f"{users_file}: no password for {user}")
    return {
        "scouting/multicast/enabled": scouting,
        "scouting/gossip/enabled": scouting,
        # the opening does not wait for its peers: a peer whose connect
        # endpoint is not up yet (another group's SSC still starting) waited
        # scouting's default 500 ms inside zenoh.open, in the ddm's routine
        # (25 heartbeats missed at 200 Hz); zenoh connects in the background
        "scouting/delay": 0,
        # records of a few hundred bytes, between hosts: no zenoh shared
        # memory (on by default, it leaves a /dev/shm/*.zenoh file per process)
        "transport/shared_memory/enabled": False,
        "transport/auth/usrpwd": {
            "user": user,
            "password": users[user],
            "dictionary_file": str(users_file),
        },
    }


def tls_settings(cfg: Config) -> dict[str, Any]:
    """zenoh's TLS settings from ``ddm.zenoh.tls``: the group's CA only,
    this node's certificate both ways (mutual TLS when ``mtls``)."""
    t = cfg.ddm.zenoh.tls
    return {
        "transport/link/tls/root_ca_certificate": t.ca_file,
        "transport/link/tls/listen_certificate": t.cert_file,
        "transport/link/tls/listen_private_key": t.key_file,
        "transport/link/tls/connect_certificate": t.cert_file,
        "transport/link/tls/connect_private_key": t.key_file,
        "transport/link/tls/enable_mtls": t.mtls,
        "transport/link/tls/verify_name_on_connect": t.verify_name,
    }


def client_settings(
    endpoint: str, user: str, users_file: str, tls: dict[str, Any] | None = None
) -> dict[str, Any]:
    """A client session of ``user`` through the session listening at
    ``endpoint`` (which routes for it), without scouting; ``tls``: the
    settings of :func:`tls_settings` (a ``tls/`` endpoint)."""
    out = _settings(user, users_file, scouting=False)
    out.update({"mode": "client", "connect/endpoints": [endpoint]})
    out.update(tls or {})
    return out


def session_config(
    cfg: Config, group: str, node: str, kind: str, robots: list[str], users_file: str
) -> dict[str, Any]:
    """The zenoh configuration of one node's session, as a dict (JSON5
    values at their keys): mode, endpoints, scouting, authentication and
    the access rules."""
    z = cfg.ddm.zenoh
    listen, connect = list(z.listen), list(z.connect)
    if not listen and not connect:
        proto = "tls" if z.tls.cert_file else "tcp"
        if kind == "ssc":
            listen = [f"{proto}/{cfg.ddm.listen_host}:{ssc_port(cfg, group)}"]
        else:
            # (with TLS, the name its certificate gives the SSC's host)
            host = "localhost" if proto == "tls" else "127.0.0.1"
            connect = [f"{proto}/{host}:{ssc_port(cfg, group)}"]
    out = _settings(user_of(node, group), users_file, scouting=z.scouting)
    if any(e.startswith("tls/") for e in (*listen, *connect)):
        out.update(tls_settings(cfg))
    # the SSC's session accepts the group's and routes for them (a peer);
    # the ESCs' are ``ddm.zenoh.mode`` (clients by default: through it)
    out["mode"] = "peer" if kind == "ssc" else z.mode
    out["listen/endpoints"] = listen
    out["connect/endpoints"] = connect
    if z.access_control and listen:
        # the rules name users, and zenoh's user/password authentication
        # names the side that connects: they sit where sessions are
        # accepted (the SSC's, by default; an ESC that listens gets them too)
        out["access_control"] = access_rules(group, node, kind, robots)
    return out


# zenoh's runtime, unless the user set it (``ZENOH_RUNTIME``): one thread,
# zenoh's RX runtime's, that the others hand their work to. A node's
# process has one link (an ESC's) or a few, records of a few hundred bytes,
# and two vCPUs. With a thread per runtime, an ESC's answer woke three (RX
# read the command, TX wrote the reply, and the application runtime's timer
# turned): now the reply is written by the thread that read the command,
# after its callback, and an ESC's process wakes once per command
RUNTIME = (
    "(rx: (worker_threads: 1), tx: (handover: rx), app: (handover: rx),"
    " acc: (handover: rx), net: (handover: rx))"
)


def open_session(settings: dict[str, Any]) -> Any:
    # (read once, when the process's first session starts zenoh's runtime)
    os.environ.setdefault("ZENOH_RUNTIME", RUNTIME)
    import zenoh

    conf = zenoh.Config()
    for key, value in settings.items():
        conf.insert_json5(key, json.dumps(value))
    return zenoh.open(conf)


def _keep_thread_state(ident: int, kept: set[int]) -> None:
    """Keep the calling thread's Python thread state (one of zenoh's, in a
    callback). Each callback takes the interpreter's lock through
    ``PyGILState_Ensure``; a thread that no Python code started gets a new
    thread state each time, made and freed around every record. One more
    ``Ensure`` that is never released keeps it: the bare zenoh path (a
    reply made in the callback, 8 robots at 200 Hz) went from 2.1-2.7 % to
    1.3-2.0 % of a vCPU per replier."""
    import ctypes

    kept.add(ident)
    ctypes.pythonapi.PyGILState_Ensure()


class ZenohTransport(Transport):
    """One node's side: ``kind`` ``ssc`` (every robot of ``robots``) or
    ``esc`` (its one robot); ``gids`` maps each robot's name to the group-wide
    index the ddm sends with."""

    drops_when_congested = True

    def __init__(
        self,
        settings: dict[str, Any],
        *,
        group: str,
        node: str,
        kind: str,
        robots: list[str],
        gids: dict[str, int],
        connect_timeout_s: float = 30.0,
        lossless: bool = False,
    ) -> None:
        """lossless: the records' publishers block rather than drop when
        congested (lockstep: the tick waits for every record anyway; a
        dropped one would hold it, and the run would no longer repeat)."""
        self.kind = kind
        self.group = group
        self.drops_when_congested = not lossless
        self.replies = kind == "esc"  # as the socket transport's ESC side
        self.robots = list(robots)
        self.names = {gids[r]: r for r in robots}
        self.inbox: deque[bytes] = deque()
        self.efd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        self.deadline = time.monotonic() + connect_timeout_s
        self.connect_timeout_s = connect_timeout_s
        self.closed = False
        # the peers' liveliness: robot -> seen / lost why (the SSC: one per
        # ESC robot; an ESC: its SSC, under its own robot)
        self.seen: set[str] = set()
        self.lost: dict[str, str] = {}
        self.leaving: dict[str, float] = {}  # robot -> when its token went
        self.settings = settings
        self.node = node
        self.gids = gids
        self.peer_of = (
            {alive_key(group, f"esc.{r}"): r for r in robots}
            if kind == "ssc"
            else {alive_key(group, "ssc"): robots[0]}
        )
        self.pubs: dict[int, Any] = {}
        self.links = _ZenohLinks(self)
        self.accelerator = _ZenohAccelerator(self)
        self.answer: Callable[[bytes], int] | None = None  # (accelerator.answer_with)
        self.compiled: Callable[..., Any] | None = None  # ... made compiled
        self.answerer: Any = None  # the compiled answer, once made
        self.kept: set[int] = set()  # zenoh's threads that keep a Python thread state
        self.session: Any = None
        self.why_not = ""
        self.next_try = 0.0
        self.new_threads = False
        # the session (and zenoh's threads) opens at the first receive: in
        # a ddm that is the Routine, after the process took its real-time
        # priority, which zenoh's threads are then given (left at the normal
        # policy they ran behind every real-time process: 400-460 us p50
        # command latency in the main job)

    def _open(self) -> bool:
        """The node's session and its declarations. A client needs its peer
        at the door: until the SSC's session is up, every receive tries
        again (every RETRY_S), as a connecting socket does."""
        import zenoh

        now = time.monotonic()
        if now < self.next_try:
            return False
        self.next_try = now + RETRY_S
        try:
            s = open_session(self.settings)
        except zenoh.ZError as exc:
            self.why_not = str(exc).split(" at ")[0]
            return False
        group, robots, gids = self.group, self.robots, self.gids
        cc = (
            zenoh.CongestionControl.DROP
            if self.drops_when_congested
            else zenoh.CongestionControl.BLOCK
        )
        express = {"congestion_control": cc, "express": True}
        if self.kind == "ssc":
            self.pubs = {
                gids[r]: s.declare_publisher(command_key(group, r), **express) for r in robots
            }
            # every robot's feedback through one subscriber: one thread of
            # zenoh-python's takes a burst's records in turn, where one per
            # robot woke eight threads (the access rules still take each
            # robot's only from its ESC; another robot's the ddm ignores)
            # (its callback stays in zenoh-python's own thread: in the RX
            # thread it would hold the group's network while the ddm, sending
            # the commands, holds the interpreter)
            take = self._record_handler(None)  # (the SSC's answer puts no reply)
            self.subs = [s.declare_subscriber(feedback_key(group, "*"), take)]
        else:
            r = robots[0]
            self.pubs = {gids[r]: s.declare_publisher(feedback_key(group, r), **express)}
            # an ESC that answers in zenoh's thread: the command is taken
            # and answered in the RX thread that read it, without the hand-off
            # to zenoh-python's callback thread and the ddm's wake; by the
            # ddm's compiled answer when it has one (this path its fallback)
            take = self._record_handler(self.pubs[gids[r]].put)
            if self.answer is not None:
                take = zenoh.handlers.Callback(take, indirect=False)
            self.subs = [s.declare_subscriber(command_key(group, r), take)]
        self.status_pub = s.declare_publisher(status_key(group, self.node))
        self.links.status_every = STATUS_EVERY
        self.token = s.liveliness().declare_token(alive_key(group, self.node))
        self.alive = [
            s.liveliness().declare_subscriber(key, self._liveliness, history=True)
            for key in self.peer_of
        ]
        self.session = s
        # zenoh's threads deliver the records: at the ddm's own priority
        from redistro.ipc import sched

        sched.share_with_threads()
        return True

    @classmethod
    def for_node(
        cls,
        cfg: Config,
        session_id: str,
        link: str,
        node: str,
        kind: str,
        robots: list[str],
        key: bytes,
    ) -> ZenohTransport:
        """The node's session from ``ddm.zenoh`` (users file: the config's,
        else the session's own in its runtime folder)."""
        from redistro.ipc.session import Manifest

        group = group_of(cfg, link)
        users = cfg.ddm.zenoh.users_file or str(
            Manifest.for_session(session_id).directory / SESSION_USERS
        )
        try:
            settings = session_config(cfg, group, node, kind, robots, users)
        except ValueError as exc:
            raise TransportError(f"zenoh: {exc}") from None
        index = list(cfg.robots)
        return cls(
            settings,
            group=group,
            node=node,
            kind=kind,
            robots=robots,
            gids={r: index.index(r) for r in robots},
            connect_timeout_s=cfg.ddm.connect_timeout_s,
            lossless=cfg.session.clock == "lockstep",
        )

    # -- zenoh's threads --

    def _record_handler(self, put: Any) -> Any:
        """What the subscriber hands each sample to: the ddm's compiled
        answer, made now (``put`` sends its reply), else :meth:`_take`."""
        if self.compiled is None:
            return self._take
        self.answerer = self.compiled(put, self.inbox, self._take_raw, self._wake)
        return self.answerer

    def _take(self, sample: Any) -> None:
        ident = threading.get_ident()
        if ident not in self.kept:
            _keep_thread_state(ident, self.kept)
        self._take_raw(sample.payload.to_bytes())

    def _take_raw(self, raw: bytes) -> None:
        answer = self.answer
        inbox = self.inbox
        if answer is not None and not inbox and not self.closed:
            # (with records still queued, this one queues behind them: the
            # ddm admits them in order, and a newer one admitted first would
            # make the older refused as out of order)
            done = answer(raw)
            if done == ANSWERED:
                return
            if done == REPLY_OWED:
                self._wake()
                return
        inbox.append(raw)
        if len(inbox) == 1:
            # the first of a burst wakes the ddm; a later one finds an earlier
            # record still there, so the ddm, which empties the inbox, has
            # not yet finished taking it and takes this one too
            self._wake()

    def _wake(self) -> None:
        if not self.closed:  # (the eventfd closes after the session)
            with contextlib.suppress(OSError):
                os.eventfd_write(self.efd, 1)

    def _liveliness(self, sample: Any) -> None:
        import zenoh

        robot = self.peer_of.get(str(sample.key_expr))
        if robot is None:
            return
        if sample.kind == zenoh.SampleKind.PUT:
            self.seen.add(robot)
            self.leaving.pop(robot, None)
            self.new_threads = True  # a peer's link: zenoh's threads for it
        elif robot in self.seen:
            self.leaving[robot] = time.monotonic()  # lost after LOSS_GRACE_S
        self._wake()

    def _settle_losses(self) -> None:
        """A peer whose token went LOSS_GRACE_S ago, with no record of
        its left in the inbox, is a lost link (the ddm's thread)."""
        if self.inbox:
            return
        now = time.monotonic()
        for robot, since in list(self.leaving.items()):
            if now - since >= LOSS_GRACE_S and self.leaving.pop(robot, None) is not None:
                self.lost[robot] = "closed by the peer, or out of reach (its liveliness token went)"

    # -- the ddm's side --

    def send(self, record: bytes, robot: int) -> None:
        if self.closed:
            raise TransportError("zenoh: the session is closed")
        pub = self.pubs.get(robot)
        name = self.names.get(robot)
        if pub is None or name in self.lost:
            return  # not connected yet, not this node's robot, or its link is lost
        pub.put(record)

    def receive(self, ready: Collection[int] | None = None) -> list[bytes]:
        if self.closed:
            raise TransportError("zenoh: the session is closed")
        if self.session is None and not self._open():
            if time.monotonic() > self.deadline:
                raise TransportError(
                    f"zenoh: cannot reach the group's door within {self.connect_timeout_s:g} s: "
                    f"{self.why_not}"
                )
            return []
        if ready is None or self.efd in ready:  # (a system call: only when it rang)
            with contextlib.suppress(BlockingIOError):
                os.eventfd_read(self.efd)
        if self.new_threads:  # from this (the ddm's) thread, which has the priority
            from redistro.ipc import sched

            self.new_threads = False
            sched.share_with_threads()
        out: list[bytes] = []
        inbox = self.inbox
        while inbox:
            out.append(inbox.popleft())
        if not out:
            if self.leaving:
                self._settle_losses()
            peers = set(self.peer_of.values())
            if peers and set(self.lost) >= peers:
                why = "; ".join(f"{r}: {w}" for r, w in sorted(self.lost.items()))
                raise TransportError(f"zenoh link lost: {why}")
            if not self.seen and time.monotonic() > self.deadline:
                raise TransportError(
                    f"zenoh: no peer of group {self.group} within {self.connect_timeout_s:g} s "
                    "(not running, out of reach, or refused: a wrong user or password)"
                )
        return out

    def fds(self) -> list[int]:
        return [] if self.closed else [self.efd]

    def connected(self) -> bool:
        """Every peer's liveliness token seen (tests and tools)."""
        if self.session is None and not self._open():
            return False
        return set(self.peer_of.values()) <= self.seen

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        if self.answerer is not None:
            self.answerer.close()  # (zenoh's thread may still be in a callback)
        if self.session is not None:
            with contextlib.suppress(Exception):
                self.session.close()
        os.close(self.efd)


class _ZenohLinks(Links):
    """The peers' liveliness, and the node's status for viewers."""

    def __init__(self, t: ZenohTransport) -> None:
        self.t = t

    def status(self, doc: dict[str, object]) -> None:
        t = self.t
        if not t.closed and t.session is not None:
            t.status_pub.put(json.dumps(doc, separators=(",", ":")))

    def lost_links(self) -> dict[int, str]:
        t = self.t
        if t.leaving:
            t._settle_losses()
        if t.kind != "ssc" or set(t.lost) >= set(t.peer_of.values()):
            return {}
        gid = {r: g for g, r in t.names.items()}
        return {gid[r]: w for r, w in t.lost.items()}


class _ZenohAccelerator(Accelerator):
    """Records come on zenoh's threads: the ddm answers there."""

    def __init__(self, t: ZenohTransport) -> None:
        self.t = t

    def answer_with(
        self,
        answer: Callable[[bytes], int],
        compiled: Callable[[Any, Any, Any, Any], Callable[[Any], None]] | None = None,
    ) -> bool:
        t = self.t
        if t.session is not None:
            return False  # (the subscriber is declared at the opening)
        t.answer = answer
        t.compiled = compiled
        return True


# -- viewers --


def look(
    endpoint: str, users_file: str, seconds: float = 1.5, tls: dict[str, Any] | None = None
) -> dict[str, Any]:
    """What a viewer sees through one session's door (``endpoint``): every
    group's nodes alive (their liveliness tokens) and the last status each
    published within ``seconds``. Connects as the viewer user."""
    settings = client_settings(endpoint, VIEWER, users_file, tls)
    status: dict[tuple[str, str], Any] = {}

    def take(sample: Any) -> None:
        parts = str(sample.key_expr).split("/")
        with contextlib.suppress(ValueError):
            status[(parts[1], parts[2])] = json.loads(sample.payload.to_bytes())

    session = open_session(settings)
    try:
        sub = session.declare_subscriber(f"{PREFIX}/*/*/status", take)
        time.sleep(seconds)  # a viewer's look: the statuses published meanwhile
        alive: set[tuple[str, str]] = set()
        for reply in session.liveliness().get(f"{PREFIX}/*/*/alive", timeout=seconds):
            if reply.ok is not None:
                parts = str(reply.ok.key_expr).split("/")
                alive.add((parts[1], parts[2]))
        sub.undeclare()
    finally:
        session.close()
    groups: dict[str, list[dict[str, Any]]] = {}
    for group, node in sorted(alive | set(status)):
        doc = dict(status.get((group, node), {}))
        doc.update({"node": node, "alive": (group, node) in alive})
        groups.setdefault(group, []).append(doc)
    return {"endpoint": endpoint, "groups": groups}

"""Message passing over TCP: the SSC's ddm sends, the ESC's ddm receives and replies.

An ESC ddm *listens* (``listen=(host, port)``) and takes one peer, the SSC
ddm. The peer is pinned: once the ddm found the connection's records to be
this run's (the handshake's proof, :mod:`redistro.ddm.handshake`, and the
records signed with the run's key), a new connection is refused and
counted; a connection that has not authenticated within ``HANDSHAKE_S``,
or sends a record that fails the key, is dropped (and a new connection may
take its place). The SSC ddm *connects* to one ESC per robot
(``peers={robot: (host, port)}``), without blocking: the connections are
made in ``receive`` (each ESC may start after the SSC, on another host),
retried every 50 ms until ``connect_timeout_s``; a link the ESC gave up
before any record of this run came over it is made again, within the same
time; a record for a robot not yet connected is dropped and counted.
``hello``: a record a connecting side sends first on every connection (the
contract tests'; the ddm says hello itself). Records are fixed size, so the
stream is cut into whole records by length. Sockets are non-blocking after
connect, with TCP_NODELAY; a record that finds the send buffer full is
dropped and counted (the peer is not reading).
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import socket
import time
import zlib
from collections.abc import Collection
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from redistro.ddm.record import SIZE
from redistro.ddm.transport import Accelerator, Links, Transport
from redistro.errors import TransportError

if TYPE_CHECKING:
    from redistro.config import Config


class _Link:
    def __init__(self, sock: socket.socket, name: str) -> None:
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.sock = sock
        self.fd = sock.fileno()
        self.name = name
        self.buf = bytearray()

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()


RETRY_S = 0.05
RECV_BYTES = 65536
MAX_RECORDS = 64  # per link and receive(): a flooding peer cannot hold the ddm
HANDSHAKE_S = 2.0  # a connection must authenticate within this


@dataclass
class _Pending:
    """A connection to a peer not made yet."""

    addr: tuple[str, int]
    name: str
    sock: socket.socket | None = None
    next_try: float = 0.0
    error: str = "no answer"


def esc_port(cfg: Config, link: str, robot: str) -> int:
    """Where the ESC of ``robot`` listens: from config, else derived from the
    link id, below Linux's ephemeral ports (32768-60999: a connection made
    anywhere on the host may take one of those as its own, and the ESC's
    ddm then failed to listen with EADDRINUSE, once in a few dozen sessions)."""
    port = cfg.ddm.esc_ports.get(robot, 0)
    return port or 21000 + zlib.crc32(f"{link}/{robot}".encode()) % 11000


class SocketTransport(Transport):
    def __init__(
        self,
        *,
        listen: tuple[str, int] | None = None,
        peers: dict[int, tuple[str, int]] | None = None,
        connect_timeout_s: float = 5.0,
        hello: bytes = b"",
        authenticate: bool = False,
    ) -> None:
        """hello: the signed record a connecting side sends first on every
        connection; authenticate: a listening side whose owner checks the
        records' key (the ddm) pins its peer as described above; without it
        the first connection is the peer at once (the transport alone, as in
        its contract tests)."""
        if (listen is None) == (peers is None):
            raise ValueError("a socket transport either listens or connects to peers")
        self.server: socket.socket | None = None
        self.conns: dict[int, _Link] = {}  # robot -> link (client side)
        self.links = _SocketLinks(self)
        self.accel = self.accelerator = _SocketAccelerator(self)
        self.peer: _Link | None = None  # the one peer (server side)
        self.peer_since = 0.0  # when it connected
        self.pinned = False  # it has authenticated
        self.authenticate = authenticate
        self.refused_count = 0
        self.hello = hello
        self.dropped_full = 0
        self.lost: str | None = None  # why a link was lost (raised by the next receive)
        self.lost_robots: dict[int, str] = {}  # connecting side: robot -> why its link was lost
        # connecting side: robots whose link brought records of this run: a
        # link lost before that (the ESC gave it up for a newcomer, before
        # the handshake) is made again until the connect deadline
        self.proven: set[int] = set()
        if listen is not None:
            srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            srv.bind(listen)
            srv.listen(4)
            srv.setblocking(False)
            self.server = srv
        self.pending: dict[int, _Pending] = {}
        self.addresses: dict[int, tuple[tuple[str, int], str]] = {}  # robot -> (address, name)
        self._receives = 0
        self.generation = 0  # bumped whenever a peer or a link comes or goes
        self.closed = False
        self.rx = bytearray(MAX_RECORDS * SIZE)  # the listening side's usual receive
        self.rx_view = memoryview(self.rx)
        self.dropped_unconnected = 0
        self.deadline = time.monotonic() + connect_timeout_s
        for robot, (host, port) in (peers or {}).items():
            name = f"{host}:{port}"
            try:
                info = socket.getaddrinfo(host, port, socket.AF_INET, socket.SOCK_STREAM)
            except OSError as exc:
                raise TransportError(f"cannot connect to {name}: {exc.strerror or exc}") from None
            addr = info[0][4]
            self.addresses[robot] = ((str(addr[0]), int(addr[1])), name)
            self.pending[robot] = _Pending(*self.addresses[robot])
        self._progress()

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
    ) -> SocketTransport:
        """An ESC listens on its robot's port (``ddm.listen_host``); the SSC
        connects to every robot's ESC (``ddm.esc_hosts``), while running: an
        ESC may start later."""
        if kind == "esc":
            listen = (cfg.ddm.listen_host, esc_port(cfg, link, robots[0]))
            return cls(listen=listen, authenticate=True)
        index = list(cfg.robots)
        return cls(
            peers={
                index.index(r): (cfg.ddm.esc_hosts.get(r, "127.0.0.1"), esc_port(cfg, link, r))
                for r in robots
            },
            connect_timeout_s=cfg.ddm.connect_timeout_s,
        )

    @property
    def address(self) -> tuple[str, int]:
        """Where a listening transport listens (its port, when 0 was asked)."""
        assert self.server is not None
        host, port = self.server.getsockname()[:2]
        return str(host), int(port)

    def connected(self) -> bool:
        """Every peer connected (a listening transport: its peer has connected)."""
        if self.server is not None:
            self._accept()
            return self.peer is not None
        self._progress()
        return not self.pending

    def _progress(self) -> None:
        """Advance the connections not made yet; past the deadline, fail."""
        now = time.monotonic()
        for robot, p in list(self.pending.items()):
            if p.sock is None and now >= p.next_try:
                sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                sock.setblocking(False)
                err = sock.connect_ex(p.addr)
                if err in (0, errno.EINPROGRESS, errno.EALREADY, errno.EWOULDBLOCK):
                    p.sock = sock
                else:
                    sock.close()
                    p.error, p.next_try = os.strerror(err), now + RETRY_S
            if p.sock is not None:
                _, writable, _ = select.select([], [p.sock], [], 0)
                if writable:
                    err = p.sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
                    if err == 0 and self_connected(p.sock):
                        err = errno.EADDRINUSE  # its port taken by itself: try again
                    if err == 0:
                        link = self.conns[robot] = _Link(p.sock, p.name)
                        del self.pending[robot]
                        self.generation += 1
                        if self.hello:
                            with contextlib.suppress(OSError):
                                link.sock.send(self.hello)
                        continue
                    p.sock.close()
                    p.sock = None
                    p.error, p.next_try = os.strerror(err), now + RETRY_S
            if now > self.deadline:
                raise TransportError(f"cannot connect to {p.name}: {p.error}")

    def _accept(self) -> None:
        assert self.server is not None
        while True:
            try:
                sock, addr = self.server.accept()
            except BlockingIOError:
                return
            if self.peer is not None and self.pinned:
                with contextlib.suppress(OSError):
                    sock.close()
                self.refused_count += 1
                continue
            if self.peer is not None:  # never authenticated: the newcomer may be the SSC
                self.peer.close()
            self.peer = _Link(sock, f"{addr[0]}:{addr[1]}")
            self.generation += 1
            self.peer_since = time.monotonic()
            self.pinned = not self.authenticate

    def _drop_unauthenticated(self) -> None:
        if self.server is not None and self.peer is not None and not self.pinned:
            self.peer.close()
            self.peer = None
            self.generation += 1
            self.refused_count += 1

    def send(self, record: bytes, robot: int) -> None:
        link = self.peer if self.server is not None else self.conns.get(robot)
        if link is None:
            if self.server is None and robot not in self.lost_robots:
                self.dropped_unconnected += 1
            return  # no peer (the SSC not connected, this robot's ESC not yet, or lost)
        try:
            sent = link.sock.send(record)
        except BlockingIOError:
            sent = -errno.EAGAIN
        except OSError as exc:
            sent = -(exc.errno or errno.EIO)
        self._sent(link, sent, len(record))

    def _sent(self, link: _Link, sent: int, size: int) -> None:
        if sent in (-errno.EAGAIN, -errno.EWOULDBLOCK):
            self.dropped_full += 1  # the peer is not reading
        elif sent < 0:
            return  # the loss shows in the next receive (with what came before it)
        elif sent != size:  # a partial record would desynchronise the stream
            raise TransportError(f"link to {link.name}: short send ({sent} of {size})")

    def receive(self, ready: Collection[int] | None = None) -> list[bytes]:
        """Every whole record that arrived. A link that failed or was closed
        still delivers what came before the end (the last record a peer sends
        before it closes is often its e-stop). The listening side has one
        peer: its loss is raised (by the next call when records came with
        it). The connecting side loses one robot's link at a time
        (``lost_robots``) and goes on with the others; it raises when every
        link is lost."""
        if self.lost is not None:
            raise TransportError(self.lost)
        self.accel.taken = 0
        peer = self.peer
        if peer is not None and self.pinned and (self._receives + 1) & 63 and not peer.buf:
            usual = self._receive_usual(peer, ready)
            if usual is not None:
                return usual
        out: list[bytes] = []
        for robot, link in self._links_to_read(ready).items():
            why = self._read(link, out)
            if why is not None:
                self._link_lost(robot, link, why)
        lost = self._lost_now()  # (a link's loss, just now)
        if lost is not None and not out:
            raise TransportError(lost)
        return out

    def _lost_now(self) -> str | None:
        return self.lost

    def _receive_usual(self, peer: _Link, ready: Collection[int] | None) -> list[bytes] | None:
        """The usual case of a listening side: its pinned peer sent whole
        records (one recv into a buffer kept for it, no link to find). None:
        the general path takes the receive on."""
        self._receives += 1
        if ready is not None and peer.fd not in ready:
            return []  # woken by something else: nothing came
        if self.accel.admit is not None:
            left: list[bytes] = []
            got = self.accel.kernel_recv(peer, left)  # (a part record went into peer.buf)
            if got == -errno.EAGAIN or got > 0:
                if not peer.buf:
                    return left
                self.accel.taken = 0  # (a part record: the general path has them all)
            else:
                self._receives -= 1  # the general path sees the end or the error itself
            return None
        try:
            got = peer.sock.recv_into(self.rx)
        except BlockingIOError:
            return []
        except OSError:
            got = -1
        if got > 0 and got % SIZE == 0 and got < len(self.rx):
            rx = self.rx_view
            return [bytes(rx[at : at + SIZE]) for at in range(0, got, SIZE)]
        if got > 0:  # a part record, or more to come: the general path
            peer.buf += self.rx_view[:got]
        else:
            self._receives -= 1  # the general path sees the end or the error itself
        return None

    def _links_to_read(self, ready: Collection[int] | None) -> dict[int, _Link]:
        """The links this receive reads (a listening side: its one peer,
        after any connection waiting; a connecting side: those ready)."""
        if self.server is None:
            if self.pending:
                self._progress()
            return {r: link for r, link in self.conns.items() if ready is None or link.fd in ready}
        self._receives += 1
        silent = time.monotonic() - self.peer_since > HANDSHAKE_S
        if self.peer is not None and not self.pinned and silent:
            self._drop_unauthenticated()  # silent, or never proved the key
        if self.peer is None or not self._receives & 63 or not self.pinned:
            self._accept()  # a connection waiting
        return {0: self.peer} if self.peer is not None else {}

    def _read(self, link: _Link, out: list[bytes]) -> str | None:
        """What came on ``link``, its whole records into ``out``: None, or
        why the link is lost (what came before the end is delivered)."""
        why = None
        if self.accel.admit is not None and not link.buf:
            # the usual case: whole records, admitted by the kernel as they come
            got = self.accel.kernel_recv(link, out)
            if got == -errno.EAGAIN or (got > 0 and not link.buf):
                return None
            if got == 0:
                why = f"link to {link.name} lost: closed by the peer"
            elif got < 0:
                why = f"link to {link.name} lost: {os.strerror(-got)}"
        budget = MAX_RECORDS * SIZE
        while why is None:
            room = budget - len(link.buf)
            if room <= 0:
                break  # the rest waits in the socket for the next receive
            try:
                chunk = link.sock.recv(min(RECV_BYTES, room))
            except BlockingIOError:
                break
            except OSError as exc:
                why = f"link to {link.name} lost: {exc.strerror or exc}"
                break
            if not chunk:
                why = f"link to {link.name} lost: closed by the peer"
                break
            link.buf += chunk
            if len(chunk) < min(RECV_BYTES, room):
                break  # all there was (the ddm's poll wakes it again for more)
        n = len(link.buf) // SIZE
        out += [bytes(link.buf[i * SIZE : (i + 1) * SIZE]) for i in range(n)]
        del link.buf[: n * SIZE]
        return why

    def _link_lost(self, robot: int, link: _Link, why: str) -> None:
        if self.server is not None and not self.pinned:
            link.close()
            self.peer = None  # an unauthenticated connection went: no loss
            self.generation += 1
        elif self.server is not None:
            self.lost = why
        elif robot not in self.proven and time.monotonic() < self.deadline:
            self.conns.pop(robot).close()
            self.generation += 1
            addr, name = self.addresses[robot]
            self.pending[robot] = _Pending(addr, name, next_try=time.monotonic() + RETRY_S)
        else:
            self.conns.pop(robot).close()
            self.generation += 1
            self.lost_robots[robot] = why
            if not self.conns and not self.pending:
                self.lost = "; ".join(self.lost_robots.values())

    @property
    def replies(self) -> bool:  # type: ignore[override]
        """The listening side (an ESC) answers each command with its feedback."""
        return self.server is not None

    def fds(self) -> list[int]:
        out = []
        if self.server is not None:
            # with its peer pinned, a newcomer must not wake the ddm (a waiting
            # connection keeps the listening socket readable): it is refused
            # within 64 receives
            if self.peer is None or not self.pinned:
                out.append(self.server.fileno())
            if self.peer is not None:
                out.append(self.peer.fd)
        else:
            out += [link.fd for link in self.conns.values()]
        return out

    def close(self) -> None:
        self.closed = True
        self.generation += 1
        for link in self.conns.values():
            link.close()
        for p in self.pending.values():
            if p.sock is not None:
                with contextlib.suppress(OSError):
                    p.sock.close()
        if self.peer is not None:
            self.peer.close()
        if self.server is not None:
            with contextlib.suppress(OSError):
                self.server.close()


class _SocketLinks(Links):
    """The socket transport's connections (see the module's text)."""

    def __init__(self, t: SocketTransport) -> None:
        self.t = t

    def authenticated(self, robot: int | None = None) -> None:
        t = self.t
        if t.server is not None and t.peer is not None:
            t.pinned = True
        elif robot is not None:
            t.proven.add(robot)

    def drop_unauthenticated(self) -> None:
        self.t._drop_unauthenticated()

    def refused(self) -> int:
        return self.t.refused_count

    def can_send(self, robot: int) -> bool:
        t = self.t
        if t.server is not None:
            return t.peer is not None
        return robot in t.conns

    def lost_links(self) -> dict[int, str]:
        return self.t.lost_robots


def self_connected(sock: socket.socket) -> bool:
    """A TCP self-connect: connecting on loopback to a port no one listens
    on yet, the socket's own ephemeral port came out as the peer's (it
    would hold the peer's port)."""
    try:
        return bool(sock.getsockname() == sock.getpeername())
    except OSError:
        return False


class _SocketAccelerator(Accelerator):
    """The ddm's kernels on this transport's sockets: each whole record
    admitted as it arrives (ddm_recv), sent (ddm_send), an ESC's step in
    one call (ddm_reply)."""

    def __init__(self, t: SocketTransport) -> None:
        self.t = t
        self.admit: tuple[Any, Any, Any] | None = None  # the ddm_recv kernel, its plan, state
        self.got: int | None = None  # a recv ddm_reply made that the next receive takes on
        self.taken = 0

    @property
    def generation(self) -> int:
        return self.t.generation

    @property
    def rx(self) -> Any:
        return self.t.rx

    def admit_with(self, call: Any, plan: Any, state: Any) -> bool:
        self.admit = (call, plan, state)
        return True

    def send_fd(self, robot: int) -> int:
        t = self.t
        link = t.peer if t.server is not None else t.conns.get(robot)
        return -1 if link is None or t.closed else link.fd

    def send_result(self, robot: int, result: int) -> None:
        t = self.t
        link = t.peer if t.server is not None else t.conns.get(robot)
        if link is not None:
            t._sent(link, result, SIZE)

    def reply_fd(self, ready: Collection[int] | None) -> int:
        """The pinned peer's socket when this receive is the usual one (a
        listening side whose peer sent whole records so far, woken by it):
        the ddm may take the whole step in one kernel call (``ddm_reply``;
        counted as this transport's receive) and hand back what it did not
        take whole (:meth:`received`); else -1."""
        t = self.t
        peer = t.peer
        if (
            t.lost is None
            and peer is not None
            and t.pinned
            and (t._receives + 1) & 63
            and not peer.buf
            and (ready is None or peer.fd in ready)
        ):
            t._receives += 1
            return peer.fd
        return -1

    def received(self, got: int) -> bool:
        """What ``ddm_reply`` received from the peer of :meth:`reply_fd`
        (into ``rx``, its whole records offered to the admitting kernel):
        True when the receive is done with (whole records, every one
        admitted); else the next receive takes it on, as if it had made
        that recv itself."""
        assert self.admit is not None
        state = self.admit[2]
        whole = got > 0 and got % SIZE == 0 and got < len(self.t.rx)
        if whole and int(state["mask"]) == (1 << (got // SIZE)) - 1:
            return True
        self.t._receives -= 1  # (the next receive counts itself)
        self.got = got
        return False

    def kernel_recv(self, link: _Link, out: list[bytes]) -> int:
        """One recv from ``link`` by the admitting kernel, its whole records
        admitted (counted in ``taken``) or put in ``out``. Returns the
        bytes received (0: closed) or -errno; a part record, or a full
        buffer (more to come), goes into ``link.buf`` for the general path.
        A recv ``ddm_reply`` made (:meth:`received`) is taken instead."""
        assert self.admit is not None
        call, plan, state = self.admit
        t = self.t
        got: int | None = self.got
        if got is None:
            got = call(plan, t.rx, link.fd)
        else:
            self.got = None
        if got > 0 and got % SIZE == 0 and got < len(t.rx):
            n, mask = got // SIZE, int(state["mask"])
            if mask == (1 << n) - 1:
                self.taken += n
            else:
                self.taken += bin(mask).count("1")
                rx = t.rx_view
                out += [bytes(rx[k * SIZE : (k + 1) * SIZE]) for k in range(n) if not mask >> k & 1]
        elif got > 0:
            link.buf += t.rx_view[:got]
        return got

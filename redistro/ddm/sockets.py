"""Message passing over TCP: the SSC's ddm sends, the ESC's ddm receives and replies.

An ESC ddm *listens* (``listen=(host, port)``) and takes one peer, the SSC
ddm (a new connection replaces the old one: the SSC may reconnect); the SSC
ddm *connects* to one ESC per robot (``peers={robot: (host, port)}``).
Records are fixed size, so the stream is cut into whole records by length.
Sockets are non-blocking after connect, with TCP_NODELAY; a record that
finds the send buffer full is dropped and counted (the peer is not reading).
"""

from __future__ import annotations

import contextlib
import socket
import time

from redistro.ddm.record import SIZE
from redistro.ddm.transport import Transport
from redistro.errors import TransportError


class _Link:
    def __init__(self, sock: socket.socket, name: str) -> None:
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.sock = sock
        self.name = name
        self.buf = bytearray()

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()


class SocketTransport(Transport):
    def __init__(
        self,
        *,
        listen: tuple[str, int] | None = None,
        peers: dict[int, tuple[str, int]] | None = None,
        connect_timeout_s: float = 5.0,
    ) -> None:
        if (listen is None) == (peers is None):
            raise ValueError("a socket transport either listens or connects to peers")
        self.server: socket.socket | None = None
        self.links: dict[int, _Link] = {}  # robot -> link (client side)
        self.peer: _Link | None = None  # the one peer (server side)
        self.dropped_full = 0
        if listen is not None:
            srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            srv.bind(listen)
            srv.listen(4)
            srv.setblocking(False)
            self.server = srv
        for robot, addr in (peers or {}).items():
            self.links[robot] = _Link(
                self._connect(addr, connect_timeout_s), f"{addr[0]}:{addr[1]}"
            )

    @property
    def address(self) -> tuple[str, int]:
        """Where a listening transport listens (its port, when 0 was asked)."""
        assert self.server is not None
        host, port = self.server.getsockname()[:2]
        return str(host), int(port)

    @staticmethod
    def _connect(addr: tuple[str, int], timeout_s: float) -> socket.socket:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                return socket.create_connection(
                    addr, timeout=max(0.05, deadline - time.monotonic())
                )
            except OSError as exc:
                if time.monotonic() > deadline:
                    raise TransportError(
                        f"cannot connect to {addr[0]}:{addr[1]}: {exc.strerror or exc}"
                    ) from None
                time.sleep(0.05)  # the peer's ddm may not listen yet (retry to the deadline)

    def _accept(self) -> None:
        assert self.server is not None
        while True:
            try:
                sock, addr = self.server.accept()
            except BlockingIOError:
                return
            if self.peer is not None:
                self.peer.close()
            self.peer = _Link(sock, f"{addr[0]}:{addr[1]}")

    def send(self, record: bytes, robot: int) -> None:
        link = self.peer if self.server is not None else self.links.get(robot)
        if link is None:
            return  # no peer yet (the server side before the SSC connects)
        try:
            sent = link.sock.send(record)
        except BlockingIOError:
            self.dropped_full += 1
            return
        except OSError as exc:
            raise TransportError(f"link to {link.name} lost: {exc.strerror or exc}") from None
        if sent != len(record):  # a partial record would desynchronise the stream
            raise TransportError(f"link to {link.name}: short send ({sent} of {len(record)})")

    def receive(self) -> list[bytes]:
        if self.server is not None:
            self._accept()
            links = [self.peer] if self.peer is not None else []
        else:
            links = list(self.links.values())
        out: list[bytes] = []
        for link in links:
            while True:
                try:
                    chunk = link.sock.recv(65536)
                except BlockingIOError:
                    break
                except OSError as exc:
                    raise TransportError(
                        f"link to {link.name} lost: {exc.strerror or exc}"
                    ) from None
                if not chunk:
                    raise TransportError(f"link to {link.name} lost: closed by the peer")
                link.buf += chunk
            n = len(link.buf) // SIZE
            out += [bytes(link.buf[i * SIZE : (i + 1) * SIZE]) for i in range(n)]
            del link.buf[: n * SIZE]
        return out

    def close(self) -> None:
        for link in self.links.values():
            link.close()
        if self.peer is not None:
            self.peer.close()
        if self.server is not None:
            with contextlib.suppress(OSError):
                self.server.close()

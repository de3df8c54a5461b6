"""A simulated reflective-memory network, in the style of SCRAMNet / GE reflective memory.

Each node has its own memory card: a SysV shared-memory segment with one
slot per (record kind, robot). A write to a node's card is broadcast to
every other node's card: the records a node writes in one step (the
SSC's commands for every robot) go out together, as one UDP datagram to a
multicast group on loopback (and to configured peers on other hosts), at
most ``BATCH`` records a datagram (1 284 bytes: one Ethernet frame between
hosts); ``receive`` drains the datagrams that arrived, writes each record
that proves authentic into this node's card, and hands the ddm the latest
record of every slot written, read back from the card (as the paper's DDM
reads its SCRAMNet memory). A record that fails the check (``verify_with``:
the ddm's keys) never touches the card: it is handed to the ddm as it came,
to be counted (``forged``), whatever source it claims, this node's own
included. A node sends from a socket of its own that is not a member of the
group, so its own writes do not come back to wake it; an authentic record
of its own that a peer on another host sends back is not written again.
Nobody blocks and nobody waits for anybody: a card always holds the latest
record of each slot, whoever wrote it last: a record overwritten before
the ddm read it is lost to it, as on the real network, and counted
(``superseded``). Each slot is seqlocked (a
counter, odd while written) so a reader never takes a torn copy. Hellos
(the handshake's records) have no slot: they are broadcast and handed over.

The host's UDP may lose a datagram where a real card never loses a write.
In real time the next cycle's record takes its place; in lockstep the tick
waits for it. There (``resend_after_s``) a node that wrote nothing for that
long writes its own slots' latest records again: a lost write costs the
tick that long, not the run. A card that holds a record already takes the
same record written again as no news (nothing handed to the ddm, nothing
counted), as a memory does.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import time
import zlib
from collections.abc import Callable, Collection
from typing import TYPE_CHECKING

from redistro.ddm.record import SIZE
from redistro.ddm.transport import Links, Transport
from redistro.errors import IPCError, TransportError
from redistro.ipc.session import Manifest
from redistro.ipc.sysv import Card
from redistro.localdata.layout import MAX_ROBOTS

if TYPE_CHECKING:
    from redistro.config import Config

KINDS = 2
MAX_DATAGRAMS = 256  # per receive(): a flood waits in the socket for the next
BATCH = 4  # records per datagram at most (1 284 bytes)
SLOT = 8 + SIZE  # seq (u8) + one record
DEFAULT_GROUP = "239.255.68.68"
_SOURCE = slice(8, 24)  # the record header's source field
RESEND_S = 0.05  # lockstep: a node's last writes again after this long without one


def group_port(session_id: str) -> int:
    """A UDP port derived from the session id (nodes of one session meet there)."""
    return 40000 + zlib.crc32(session_id.encode()) % 20000


class ReflectiveTransport(Transport):
    latest_only = True

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
    ) -> ReflectiveTransport:
        """Every node alike: its own memory card, the group's multicast
        address (``ddm.group``, ``ddm.port``) and the hosts in ``ddm.peers``."""
        peers = []
        for p in cfg.ddm.peers:
            host, _, port = p.rpartition(":")
            peers.append((host, int(port)))
        return cls(
            session_id,
            node,
            link=link,
            group=cfg.ddm.group,
            port=cfg.ddm.port,
            peers=peers,
            manifest=Manifest.for_session(session_id),
            resend_after_s=RESEND_S if cfg.session.clock == "lockstep" else 0.0,
        )

    def __init__(
        self,
        session_id: str,
        node: str,
        *,
        link: str = "",
        group: str = DEFAULT_GROUP,
        port: int = 0,
        peers: list[tuple[str, int]] | None = None,
        manifest: Manifest | None = None,
        resend_after_s: float = 0.0,
    ) -> None:
        """resend_after_s: after this long without a write, write this
        node's slots' latest records again (0: never; lockstep)."""
        self.node = node
        self.source = node.encode()[:16].ljust(16, b"\0")
        self.group = (group, port or group_port(link or session_id))
        self.peers = list(peers or [])
        self.card = Card.create_new(KINDS * MAX_ROBOTS * SLOT, manifest)
        self.seqs = [0] * (KINDS * MAX_ROBOTS)
        # per slot: records overwritten on the card before a receive handed them over
        self.superseded_at = [0] * (KINDS * MAX_ROBOTS)
        self.pending: list[bytes] = []  # written this step, not yet sent (flush)
        self.resend_ns = int(resend_after_s * 1e9)
        self.own: dict[int, tuple[int, int]] = {}  # the slots this node writes -> (kind, robot)
        self.flushed_ns = 0  # when its writes last went out
        self.resent = 0  # records written again (resend_after_s)
        self.check: Callable[[bytes], bool] | None = None  # (links.verify_with)
        self.links = _Links(self)
        try:
            # no peers on other hosts: only the group's datagrams on loopback
            # are received (bound to the group address, joined on lo)
            self.sock = _multicast_socket(*self.group, any_source=bool(self.peers))
            self.out = _sending_socket()
        except OSError as exc:
            with contextlib.suppress(AttributeError):
                self.sock.close()
            self.card.close()
            self.card.remove()
            raise TransportError(f"reflective memory network: {exc.strerror or exc}") from None

    @staticmethod
    def _slot(record: bytes, robot: int) -> int:
        kind = record[6]
        if not 1 <= kind <= KINDS or not 0 <= robot < MAX_ROBOTS:
            raise ValueError(f"no card slot for kind {kind}, robot {robot}")
        return (kind - 1) * MAX_ROBOTS + robot

    def _write_card(self, slot: int, record: bytes) -> None:
        at = slot * SLOT
        seq = self.seqs[slot] + 1
        self.card.write(struct.pack("<Q", seq), at)  # odd: being written
        self.card.write(record, at + 8)
        self.card.write(struct.pack("<Q", seq + 1), at)
        self.seqs[slot] = seq + 1

    def _holds(self, slot: int, record: bytes) -> bool:
        """The card's slot holds ``record`` already (only this node writes
        its card: no seqlock needed)."""
        return self.seqs[slot] > 0 and self.card.read(SIZE, slot * SLOT + 8) == record

    @property
    def superseded(self) -> int:
        """Records of every slot overwritten before a receive handed them over."""
        return sum(self.superseded_at)

    def superseded_of(self, kind: int, robot: int) -> int:
        """Records of (kind, robot) overwritten before a receive handed them over."""
        return self.superseded_at[(kind - 1) * MAX_ROBOTS + robot]

    def read_card(self, kind: int, robot: int) -> bytes | None:
        """The latest record of (kind, robot) on this node's card (None: never written)."""
        at = ((kind - 1) * MAX_ROBOTS + robot) * SLOT
        for _ in range(100):
            s1 = struct.unpack("<Q", self.card.read(8, at))[0]
            if s1 == 0:
                return None
            if s1 & 1:
                continue
            data = self.card.read(SIZE, at + 8)
            if struct.unpack("<Q", self.card.read(8, at))[0] == s1:
                return data
        raise IPCError(f"card slot {kind}/{robot}: no consistent copy")

    def send(self, record: bytes, robot: int) -> None:
        """Write ``record`` to this node's card (a hello has no slot); it goes
        out to the others' with the step's other writes, at ``links.flush``."""
        if 1 <= record[6] <= KINDS:
            slot = self._slot(record, robot)
            self._write_card(slot, record)
            self.own[slot] = (record[6], robot)
        self.pending.append(record)

    def _flush(self) -> None:
        pending = self.pending
        if pending and self.resend_ns:
            self.flushed_ns = time.monotonic_ns()
        for at in range(0, len(pending), BATCH):
            datagram = b"".join(pending[at : at + BATCH])
            for addr in (self.group, *self.peers):
                try:
                    self.out.sendto(datagram, addr)
                except BlockingIOError:
                    pass  # the network is a broadcast medium: a lost update is a lost update
                except OSError as exc:
                    pending.clear()
                    raise TransportError(
                        f"reflective memory network: {exc.strerror or exc}"
                    ) from None
        pending.clear()

    def _resend(self) -> None:
        """This node's slots' latest records, out again (lockstep)."""
        for kind, robot in self.own.values():
            latest = self.read_card(kind, robot)
            if latest is not None:
                self.pending.append(latest)
                self.resent += 1
        self._flush()

    def receive(self, ready: Collection[int] | None = None) -> list[bytes]:
        """Records refused by the check (as they came), hellos, and the latest
        record of each card slot that authentic records wrote."""
        if self.resend_ns and self.own and time.monotonic_ns() - self.flushed_ns > self.resend_ns:
            self._resend()
        out: list[bytes] = []
        written: dict[int, tuple[int, int]] = {}  # slot -> (kind, robot)
        check = self.check
        for _ in range(MAX_DATAGRAMS):  # a flood waits for the next receive
            try:
                data = self.sock.recv(BATCH * SIZE + 1)
            except BlockingIOError:
                break
            except OSError as exc:
                raise TransportError(f"reflective memory network: {exc.strerror or exc}") from None
            if len(data) % SIZE or len(data) > BATCH * SIZE:
                out.append(data)  # not whole records: the ddm counts it malformed
                continue
            for at in range(0, len(data), SIZE):
                rec = data[at : at + SIZE] if len(data) > SIZE else data
                if check is not None and not check(rec):
                    out.append(rec)  # never in the card: the ddm counts it
                    continue
                if rec[_SOURCE] == self.source:
                    continue  # our own write, back from a peer on another host
                kind, robot = rec[6], rec[7]
                if 1 <= kind <= KINDS and robot < MAX_ROBOTS:
                    slot = self._slot(rec, robot)
                    if self._holds(slot, rec):
                        continue  # the card has it: written again (a resend), nothing new
                    self._write_card(slot, rec)
                    if slot in written:
                        self.superseded_at[slot] += 1  # (a node that fell behind reads the latest)
                    written[slot] = (kind, robot)
                else:
                    out.append(rec)  # a hello
        for kind, robot in written.values():
            latest = self.read_card(kind, robot)
            if latest is not None:
                out.append(latest)
        return out

    def fds(self) -> list[int]:
        return [self.sock.fileno()]

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()
        with contextlib.suppress(OSError):
            self.out.close()
        self.card.close()
        self.card.remove()


def _sending_socket() -> socket.socket:
    """Where a node's writes leave from: not bound to the group's port nor a
    member of it, so the host's multicast loop does not hand them back."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    try:
        _on_loopback(s)
    except OSError:
        s.close()
        raise
    return s


def _multicast_socket(group: str, port: int, any_source: bool = False) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        s.bind(("" if any_source else group, port))
        lo = socket.inet_aton("127.0.0.1")
        s.setsockopt(
            socket.IPPROTO_IP,
            socket.IP_ADD_MEMBERSHIP,
            struct.pack("4s4s", socket.inet_aton(group), lo),
        )
        _on_loopback(s)
    except OSError:
        s.close()
        raise
    return s


def _on_loopback(s: socket.socket) -> None:
    """A socket's multicast writes: out on loopback, looped back to the
    host's members, never routed beyond; it never blocks."""
    s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
    s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
    s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
    s.setblocking(False)


class _Links(Links):
    """The card's links: authentic records are stored (``verify_with``), a
    step's writes go out together (``flush``)."""

    def __init__(self, t: ReflectiveTransport) -> None:
        self.t = t

    def verify_with(self, check: Callable[[bytes], bool]) -> bool:
        self.t.check = check
        return True

    def flush(self) -> None:
        self.t._flush()

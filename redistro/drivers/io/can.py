"""The CAN backplane: the same register banks carried in CAN FD frames (python-can).

Frames (11-bit identifiers, 64-byte CAN FD payloads):

- ``0x100 | address``  controller -> board: a board's ``out`` bank (write);
- ``0x200 | address``  controller -> board: read request;
- ``0x300 | address``  board -> controller: the board's ``in`` bank (reply).

A bank longer than one frame is split into segments. Every frame starts with a
6-byte header: sequence number (u16), segment index (u8), segment count (u8),
CRC-16 of the segment's payload (u16). A frame with a bad length, CRC, segment
index or an unknown sequence is counted and dropped, never trusted. Every send
and receive has a timeout; a bus error or a board that does not answer in time
is an :class:`~redistro.errors.IOFault`.

Every write and every reply is signed with the plant's CAN key (``can.key``
in the plant session's runtime folder, made fresh by each plant at start,
read by the drivers): an HMAC-SHA256 over the frame's function, address,
64-bit sequence number and bank. A write's payload is the sequence number,
the bank and the tag (32 bytes); a reply's is the bank and the tag's first
16 bytes (HMAC-SHA256-128, as RFC 4868's truncation), its number being the
request's, which the driver knows: a reply then fits the frames it took
unsigned plus at most one (a driver's read of r2's boards: 13 frames, 11
unsigned, 16 with the full tag and the number). The header's 16-bit number
only matches segments.

- A write's sequence number is the driver's: strictly growing, never below
  the monotonic clock in ns when written (``next_seq``), so it never wraps
  and a later driver beside the same plant starts above every earlier one.
  The chassis takes a write only when its tag holds and its number is above
  the last one it took for that board: a write captured at any time and
  sent again (whatever the sequence did since), or one from another run
  (another key), never reaches a register (counted in ``forged``), and
  never moves what the chassis expects of the genuine writer.
- A read request carries the driver's next number; the reply's tag covers
  it, so a reply that is forged, or captured and sent again (another
  request's), is not taken (``bad_frames``).

The ``udp_multicast`` bus joins its group and sends on loopback only
(``plant.can.loopback_only``). Every socket on the bus takes every frame,
its own included; the chassis' takes a larger buffer (``PLANT_RCVBUF``):
a datagram that finds a socket's buffer full is lost, and a lost write to
the DIO board (a brake) is not sent again.

One file past the house's ~400 lines: the frame format, the signed write and
the checked read are one protocol, and split they would each need the others.
"""

from __future__ import annotations

import binascii
import hmac
import socket
import struct
import time
import zlib
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from redistro.drivers.io.backplane import Backplane, BoardPort
from redistro.drivers.io.registers import BANKS, BoardType
from redistro.errors import IOFault

if TYPE_CHECKING:
    from redistro.config.model import PlantConfig

FRAME = 64
HEAD = struct.Struct("<HBBH")
PAYLOAD = FRAME - HEAD.size
WRITE, READ, REPLY = 0x100, 0x200, 0x300
PLANT_RCVBUF = 4 << 20  # the chassis' socket buffer: every frame of the bus comes in
LATE_BATCH = 64  # frames a late plant still takes before its next step
INVENTORY = 0x7F0  # controller -> chassis: who is there?
INVENTORY_REPLY = 0x7F1  # chassis -> controller: (address u8, type u8) pairs
TAG = 32  # a write's HMAC-SHA256
REPLY_TAG = 16  # a reply's, truncated (HMAC-SHA256-128)
SEQ = struct.Struct("<Q")  # the 64-bit sequence number that starts a signed payload
KEY_FILE = "can.key"  # in the plant session's runtime folder
_SIGNED = struct.Struct("<HBQ")  # what the tag covers before the bank: function, address, seq


def write_tag(key: bytes, address: int, seq: int, bank: bytes) -> bytes:
    return hmac.digest(key, _SIGNED.pack(WRITE, address, seq) + bank, "sha256")


def reply_tag(key: bytes, address: int, seq: int, bank: bytes) -> bytes:
    return hmac.digest(key, _SIGNED.pack(REPLY, address, seq) + bank, "sha256")[:REPLY_TAG]


def signed(seq: int, bank: bytes, tag: bytes) -> bytes:
    """A signed payload: sequence number, bank, tag."""
    return SEQ.pack(seq) + bank + tag


def unsigned(whole: bytes) -> tuple[int, bytes, bytes]:
    """(sequence number, bank, tag) of a signed payload."""
    return SEQ.unpack_from(whole)[0], whole[SEQ.size : -TAG], whole[-TAG:]


def key_path(session_id: str) -> Path:
    from redistro.ipc.session import Manifest

    return Manifest.for_session(session_id).directory / KEY_FILE


def plant_key(session_id: str) -> bytes:
    """The plant's CAN key: made once by the plant (mode 0600), read after."""
    from redistro.ddm import record as wire

    path = key_path(session_id)
    try:
        return wire.new_key(path)
    except FileExistsError:
        return wire.load_key(path)


def driver_key(session_id: str) -> bytes:
    from redistro.ddm import record as wire

    try:
        return wire.load_key(key_path(session_id))
    except ValueError as exc:
        raise IOFault(f"CAN: no key of the plant of session {session_id}: {exc}") from None


def frames_for(seq: int, payload: bytes) -> list[bytes]:
    """Split a bank into frames (each exactly FRAME bytes)."""
    chunks = [payload[i : i + PAYLOAD] for i in range(0, max(len(payload), 1), PAYLOAD)]
    out = []
    for i, chunk in enumerate(chunks):
        head = HEAD.pack(seq & 0xFFFF, i, len(chunks), binascii.crc_hqx(chunk, 0xFFFF))
        out.append((head + chunk).ljust(FRAME, b"\0"))
    return out


class Reassembly:
    """Collects the segments of one bank; validates each frame."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.count = -(-size // PAYLOAD) if size else 1
        self.seq = -1
        self.parts: dict[int, bytes] = {}
        self.bad = 0

    def add(self, data: bytes | bytearray, want_seq: int | None = None) -> bytes | None:
        """Add a frame; the whole bank once every segment of one sequence arrived."""
        if len(data) < HEAD.size:
            self.bad += 1
            return None
        seq, index, count, crc = HEAD.unpack_from(data)
        if count != self.count or index >= count:
            self.bad += 1
            return None
        lo = index * PAYLOAD
        n = min(PAYLOAD, self.size - lo)
        chunk = bytes(data[HEAD.size : HEAD.size + n])
        if len(chunk) != n or binascii.crc_hqx(chunk, 0xFFFF) != crc:
            self.bad += 1
            return None
        if want_seq is not None and seq != want_seq & 0xFFFF:
            return None  # a late reply to an earlier request: not an error, not ours
        if seq != self.seq:
            self.seq, self.parts = seq, {}
        self.parts[index] = chunk
        if len(self.parts) == self.count:
            whole = b"".join(self.parts[i] for i in range(self.count))
            self.parts = {}
            self.seq = -1
            return whole
        return None


def open_bus(
    interface: str,
    channel: str,
    port: int,
    session_id: str,
    loopback_only: bool = True,
    rcvbuf: int = 0,
) -> Any:
    """rcvbuf: the udp_multicast socket's receive buffer [bytes] (0: the
    system's default; the kernel caps it at net.core.rmem_max)."""
    import can

    kwargs: dict[str, Any] = {"interface": interface, "fd": True}
    if interface == "udp_multicast":
        from can.interfaces.udp_multicast import UdpMulticastBus

        kwargs["channel"] = channel or UdpMulticastBus.DEFAULT_GROUP_IPv4
        kwargs["port"] = port or session_port(session_id)
    elif interface == "virtual":
        kwargs["channel"] = channel or f"redistro-{session_id}"
        kwargs["receive_own_messages"] = False
    else:
        kwargs["channel"] = channel or "can0"
    try:
        bus = can.Bus(**kwargs)
    except (can.CanError, OSError) as exc:
        raise IOFault(f"CAN {interface} {kwargs['channel']}: cannot open ({exc})") from None
    if interface == "udp_multicast" and loopback_only:
        _loopback_only(bus, str(kwargs["channel"]))
    if interface == "udp_multicast" and rcvbuf:
        sock = getattr(getattr(bus, "_multicast", None), "_socket", None)
        if sock is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    return bus


def _loopback_only(bus: Any, group: str) -> None:
    """python-can's udp_multicast joins its group on every interface (the
    default route's): here it leaves that membership, joins on loopback and
    sends there, so the bus never leaves the machine."""
    sock = getattr(getattr(bus, "_multicast", None), "_socket", None)
    if sock is None or ":" in group:
        raise IOFault("CAN udp_multicast: cannot restrict the bus to loopback (IPv4 only)")
    g, lo = socket.inet_aton(group), socket.inet_aton("127.0.0.1")
    try:
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_DROP_MEMBERSHIP, g + struct.pack("@I", 0))
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, g + lo)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, lo)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
    except OSError as exc:
        raise IOFault(f"CAN udp_multicast: cannot join {group} on loopback ({exc})") from None


def session_port(session_id: str) -> int:
    """A UDP port per session, so that concurrent sessions never share a bus."""
    return 20000 + zlib.crc32(session_id.encode()) % 20000


def _message(arbitration_id: int, data: bytes) -> Any:
    import can

    return can.Message(arbitration_id=arbitration_id, data=data, is_fd=True, is_extended_id=False)


class CanBackplane(Backplane):
    """The controller's end: requests banks, writes banks, waits with deadlines."""

    @classmethod
    def from_config(cls, plant: PlantConfig, session_id: str) -> CanBackplane:
        """The bus of ``plant.can`` (interface, channel, port, loopback only)."""
        c = plant.can
        return cls(
            session_id,
            plant.io_timeout_ms / 1e3,
            interface=c.interface,
            channel=c.channel,
            port=c.port,
            loopback_only=c.loopback_only,
        )

    def __init__(
        self,
        session_id: str,
        timeout_s: float,
        *,
        interface: str = "udp_multicast",
        channel: str = "",
        port: int = 0,
        bus: Any = None,
        key: bytes | None = None,
        loopback_only: bool = True,
    ) -> None:
        """key: the plant's CAN key (None: read from the plant session's folder)."""
        self.timeout_s = timeout_s
        self.key = key if key is not None else driver_key(session_id)
        self.bus = (
            bus
            if bus is not None
            else open_bus(interface, channel, port, session_id, loopback_only)
        )
        self._own_bus = bus is None
        self._types: dict[int, BoardType] | None = None
        self._rx: dict[int, Reassembly] = {}
        self._recs: dict[int, np.ndarray[Any, Any]] = {}
        self._seq = 0
        self.bad_frames = 0  # frames refused: malformed, or a reply whose tag failed
        self.resent = 0  # read requests sent a second time
        self.writes = 0  # banks written

    def next_seq(self) -> int:
        """The next sequence number: above the last, and never below the
        monotonic clock [ns] (so it never wraps, and a driver started later
        beside the same plant begins above every number of this one)."""
        self._seq = max(self._seq + 1, time.monotonic_ns())
        return self._seq

    def _send(self, arbitration_id: int, data: bytes) -> None:
        import can

        try:
            self.bus.send(_message(arbitration_id, data), timeout=self.timeout_s)
        except can.CanError as exc:
            raise IOFault(f"CAN send 0x{arbitration_id:03x} failed: {exc}") from None

    def _recv(self, deadline: float) -> Any:
        import can

        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return None
        try:
            return self.bus.recv(timeout=remaining)
        except can.CanError as exc:
            raise IOFault(f"CAN receive failed: {exc}") from None

    def inventory(self) -> dict[int, BoardType]:
        if self._types is None:
            self._send(INVENTORY, bytes(FRAME))
            deadline = time.monotonic() + self.timeout_s * 5
            while True:
                msg = self._recv(deadline)
                if msg is None:
                    raise IOFault(f"CAN: no chassis answered within {self.timeout_s * 5e3:.0f} ms")
                if msg.arbitration_id == INVENTORY_REPLY:
                    data = bytes(msg.data)
                    n = data[0]
                    pairs = [(data[1 + 2 * i], data[2 + 2 * i]) for i in range(n)]
                    self._types = {a: BoardType(t) for a, t in pairs}
                    break
        return dict(self._types)

    def read(self, addresses: list[int]) -> dict[int, np.ndarray[Any, Any]]:
        types = self.inventory()
        seq = self.next_seq()
        request = (HEAD.pack(seq & 0xFFFF, 0, 1, 0) + SEQ.pack(seq)).ljust(FRAME, b"\0")
        for a in addresses:
            if a not in types:
                raise IOFault(f"no board at address {a} in the chassis")
            if a not in self._rx:
                din = BANKS[types[a]][0]
                self._rx[a] = Reassembly(din.itemsize + REPLY_TAG)
                self._recs[a] = np.zeros((), din)
            self._send(READ | a, request)
        pending = set(addresses)
        out: dict[int, np.ndarray[Any, Any]] = {}
        start = time.monotonic()
        deadline = start + self.timeout_s
        resend_at: float | None = start + self.timeout_s / 2
        while pending:
            msg = self._recv(deadline if resend_at is None else resend_at)
            if msg is None and resend_at is not None and time.monotonic() < deadline:
                # a lost datagram or a late step: ask once more within the budget
                self.resent += len(pending)
                for a in pending:
                    self._send(READ | a, request)
                resend_at = None
                continue
            if msg is None:
                missing = ", ".join(str(a) for a in sorted(pending))
                raise IOFault(
                    f"CAN: board(s) {missing} did not answer within {self.timeout_s * 1e3:.0f} ms"
                )
            fn, a = msg.arbitration_id & 0x700, msg.arbitration_id & 0xFF
            if fn != REPLY or a not in pending:
                continue  # requests, writes, other robots' replies share the bus
            rx = self._rx[a]
            before = rx.bad
            whole = rx.add(msg.data, want_seq=seq)
            self.bad_frames += rx.bad - before
            if whole is not None:
                bank, tag = whole[:-REPLY_TAG], whole[-REPLY_TAG:]
                if not hmac.compare_digest(tag, reply_tag(self.key, a, seq, bank)):
                    self.bad_frames += 1  # forged, or an old reply sent again: not taken
                    continue
                rec = self._recs[a]
                rec.reshape(1).view(np.uint8)[:] = np.frombuffer(bank, np.uint8)
                out[a] = rec
                pending.discard(a)
        return out

    def write(self, address: int, record: np.ndarray[Any, Any]) -> None:
        seq = self.next_seq()
        bank = record.tobytes()
        for frame in frames_for(seq, signed(seq, bank, write_tag(self.key, address, seq, bank))):
            self._send(WRITE | address, frame)
        self.writes += 1

    def close(self) -> None:
        if self._own_bus:
            self.bus.shutdown()


class CanPort(BoardPort):
    """The chassis' end: answers read requests and takes writes between steps."""

    def __init__(self, boards: dict[int, BoardType], bus: Any, key: bytes = b"") -> None:
        self.bus = bus
        self.key = key
        self.types = dict(boards)
        self._in = {a: np.zeros((), BANKS[t][0]) for a, t in boards.items()}
        self._out = {a: np.zeros((), BANKS[t][1]) for a, t in boards.items()}
        self._rx = {a: Reassembly(SEQ.size + BANKS[t][1].itemsize + TAG) for a, t in boards.items()}
        self._last_seq: dict[int, int] = {}
        self.bad_frames = 0
        self.forged = 0  # writes refused: the tag did not match, or not a newer sequence number
        self.taken = 0  # writes that reached their registers
        self.requests = 0

    def outputs(self, address: int) -> np.ndarray[Any, Any]:
        return self._out[address]

    def publish(self, address: int, record: np.ndarray[Any, Any]) -> None:
        self._in[address][...] = record

    def _reply(self, address: int, seq: int) -> None:
        """The board's ``in`` bank, signed over the request's number."""
        import can

        bank = self._in[address].tobytes()
        for frame in frames_for(seq, bank + reply_tag(self.key, address, seq, bank)):
            try:
                self.bus.send(_message(REPLY | address, frame), timeout=0.005)
            except can.CanError:
                return  # the controller will time out and see an I/O fault

    def handle(self, msg: Any) -> None:
        ident = msg.arbitration_id
        if ident == INVENTORY:
            pairs = sorted(self.types.items())
            data = bytes([len(pairs)]) + b"".join(bytes([a, int(t)]) for a, t in pairs)
            self.bus.send(_message(INVENTORY_REPLY, data.ljust(FRAME, b"\0")), timeout=0.005)
            return
        fn, a = ident & 0x700, ident & 0xFF
        if a not in self.types or fn not in (READ, WRITE):
            return
        data = bytes(msg.data)
        if fn == READ:
            if len(data) < HEAD.size + SEQ.size:
                self.bad_frames += 1
                return
            self.requests += 1
            self._reply(a, SEQ.unpack_from(data, HEAD.size)[0])
            return
        rx = self._rx[a]
        before = rx.bad
        whole = rx.add(data)
        self.bad_frames += rx.bad - before
        if whole is None:
            return
        seq, bank, tag = unsigned(whole)
        fresh = seq > self._last_seq.get(a, -1)
        if not (fresh and hmac.compare_digest(tag, write_tag(self.key, a, seq, bank))):
            self.forged += 1  # forged, replayed or from another run: never a register
            return
        self._last_seq[a] = seq
        self.taken += 1
        self._out[a].reshape(1).view(np.uint8)[:] = np.frombuffer(bank, np.uint8)

    def service(self, until_ns: int) -> None:
        """Answer requests until ``until_ns``; when the step is late, take what
        is already queued, up to LATE_BATCH frames (a late plant must not build
        a backlog, nor stop stepping under a flood of frames)."""
        import can

        late = 0
        while True:
            remaining = (until_ns - time.monotonic_ns()) / 1e9
            if remaining <= 0:
                late += 1
                if late > LATE_BATCH:
                    return
            try:
                msg = self.bus.recv(timeout=max(0.0, remaining))
            except can.CanError:
                msg = None
            if msg is not None:
                self.handle(msg)
            elif remaining <= 0:
                return

    def close(self) -> None:
        self.bus.shutdown()

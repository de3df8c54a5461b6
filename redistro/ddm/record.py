"""The DDM wire record: fixed size, versioned, checksummed, authenticated.

Every record carries one robot's Robot Group Shared Data, a Command (SSC ->
ESC) or a Feedback (ESC -> SSC), as the same bytes as its Local Data block
payload (:mod:`redistro.localdata.layout`), behind a header, followed by a
tag::

    magic u4 | version u2 | kind u1 | robot u1 | source S16 | seq u8 |
    stamp_ns i8 | estop u1 | pad | crc32 u4 (over everything else) |
    payload | tag: HMAC-SHA256 (the link's key) over header and payload

The crc32 tells noise from forgery: a flipped bit fails the checksum, a
record written without the link's key (forged, or renamed to another
source) fails the tag (``auth``). The link's key is the session's
(``ddm.key`` in its runtime directory) or, for nodes started alone,
``ddm.key_file`` (:func:`load_key`). Computing or checking a tag costs
about 1 µs hot in Python (hmac, zlib), under 1 µs in the kernels
(``wire_verify``, ``wire_seal``: libcrypto's HMAC and zlib's crc32, linked).

Freshness across runs: the link's key signs only hellos. Commands and
feedback are signed with the *run key*, :func:`run_key` of the link's key
and the SSC's ddm's nonce (16 random bytes, new in every run), which an
ESC's ddm takes on only from a hello that answers its own challenge (its
own fresh nonce, :data:`HELLO` ``peer``): a record or hello of an earlier
run is refused (``auth``, or a stale hello), whoever sends it
(:mod:`redistro.ddm.handshake`).

``seq`` counts the source's records of that kind and robot; ``stamp_ns`` is
the source's CLOCK_MONOTONIC when it sent the record (comparable only with
the same source's earlier stamps: there is no global clock). :func:`decode`
refuses anything malformed with :class:`WireError` naming why; it never
raises anything else, whatever the bytes. :class:`Admission` drops
duplicate, out-of-order and stale records and counts each kind of drop.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import stat
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from redistro.ddm import wire_layout
from redistro.errors import WireError
from redistro.kernels import KERNELS
from redistro.localdata.layout import COMMAND, FEEDBACK

MAGIC = 0x52445344  # "DSDR" little-endian
VERSION = 3
TAG_BYTES = 32  # HMAC-SHA256
KEY_BYTES = 32
SESSION_KEY = "ddm.key"  # a session's link key, in its runtime directory
KIND_COMMAND = 1
KIND_FEEDBACK = 2
KIND_HELLO = 3  # the handshake's records, signed with the link's key (redistro.ddm.handshake)
NONCE_BYTES = 16
# a hello: the sender's nonce for this run, and the nonce of the peer it answers
HELLO = np.dtype(
    [("stamp_ns", "<i8"), ("nonce", "u1", (NONCE_BYTES,)), ("peer", "u1", (NONCE_BYTES,))]
)
PAYLOADS: dict[int, np.dtype[Any]] = {
    KIND_COMMAND: COMMAND,
    KIND_FEEDBACK: FEEDBACK,
    KIND_HELLO: HELLO,
}
PAYLOAD_BYTES = max(d.itemsize for d in PAYLOADS.values())

HEADER = np.dtype(
    [
        ("magic", "<u4"),
        ("version", "<u2"),
        ("kind", "u1"),
        ("robot", "u1"),
        ("source", "S16"),
        ("seq", "<u8"),
        ("stamp_ns", "<i8"),
        ("estop", "u1"),
        ("pad", "u1", (3,)),
        ("crc32", "<u4"),
    ]
)
WIRE = np.dtype([("header", HEADER), ("payload", "u1", (PAYLOAD_BYTES,))])
BODY = WIRE.itemsize  # what the tag covers
SIZE = BODY + TAG_BYTES
_CRC_AT = HEADER.fields["crc32"][1]  # type: ignore[index]


# the header as a struct (the same layout as HEADER): the ddm's hot path
HEAD = struct.Struct("<IHBB16sQqB3xI")
assert HEAD.size == HEADER.itemsize
PAYLOAD_AT = HEADER.itemsize
_STAMP = struct.Struct("<q")  # every payload starts with its producer's stamp [ns]


def _crc(buf: bytes | bytearray | memoryview) -> int:
    view = memoryview(buf)[:BODY]
    return zlib.crc32(view[_CRC_AT + 4 :], zlib.crc32(view[:_CRC_AT])) & 0xFFFFFFFF


class _Signer:
    """HMAC-SHA256 (RFC 2104) under one key, from the two padded-key states
    hashed once: a tag is two state copies and two updates. ``hmac.digest``
    gives the same bytes but looks the algorithm up in OpenSSL on every
    call, which a process woken cold (a ddm, once per record) paid with
    tens of µs."""

    BLOCK = 64  # SHA-256's block size

    def __init__(self, key: bytes) -> None:
        if len(key) > self.BLOCK:
            key = hashlib.sha256(key).digest()
        key = key.ljust(self.BLOCK, b"\0")
        self.inner = hashlib.sha256(bytes(b ^ 0x36 for b in key))
        self.outer = hashlib.sha256(bytes(b ^ 0x5C for b in key))

    def tag(self, body: bytes | bytearray | memoryview) -> bytes:
        inner = self.inner.copy()
        inner.update(body)
        outer = self.outer.copy()
        outer.update(inner.digest())
        return outer.digest()


_SIGNERS: dict[bytes, _Signer] = {}


def _tag(key: bytes, buf: bytes | bytearray | memoryview) -> bytes:
    signer = _SIGNERS.get(key)
    if signer is None:
        if len(_SIGNERS) >= 16:  # a process holds one or two keys; a test may make many
            _SIGNERS.clear()
        signer = _SIGNERS[key] = _Signer(key)
    return signer.tag(memoryview(buf)[:BODY])


_CODECS: dict[bytes, Any] = {}
_VERIFY_FAILS = {
    1: ("size", ""),
    2: ("checksum", ""),
    3: ("auth", "the tag does not match the link's key"),
}


def codec_record(key: bytes) -> np.ndarray[Any, Any]:
    """The codec of ``key`` for the kernels (CODEC, ddm/wire_layout.py): the
    key and where a record's tag and checksum lie."""
    if len(key) > wire_layout.KEY_MAX:
        raise ValueError(f"a key of {len(key)} bytes: at most {wire_layout.KEY_MAX}")
    rec = np.zeros((), wire_layout.CODEC)
    rec["key"][: len(key)] = np.frombuffer(key, np.uint8)
    rec["key_len"], rec["body"], rec["crc_at"] = len(key), BODY, _CRC_AT
    return rec


def _codec(key: bytes) -> Any:
    """The compiled codec of ``key``: a plan of the ``wire`` kernels (a
    record's crc32 and tag in one call)."""
    codec = _CODECS.get(key)
    if codec is None:
        if len(_CODECS) >= 16:
            _CODECS.clear()
        from redistro.kernels import plan

        codec = _CODECS[key] = plan("wire", codec=codec_record(key))
    return codec


def _check_tag(key: bytes, buf: bytes | bytearray | memoryview) -> None:
    if not hmac.compare_digest(_tag(key, buf), bytes(memoryview(buf)[BODY:SIZE])):
        raise WireError("auth", "the tag does not match the link's key")


def run_key(key: bytes, nonce: bytes) -> bytes:
    """The key of one run's commands and feedback: HMAC-SHA256 of the SSC's
    nonce under the link's key (RFC 2104 as a key derivation, as HKDF's
    extract step)."""
    return hmac.digest(key, b"redistro run key\0" + nonce, "sha256")


def cipher_key(run_key: bytes) -> bytes:
    """The key that encrypts one run's payloads (``ddm.encrypt``), apart from
    the run key that signs them."""
    return hmac.digest(run_key, b"redistro record cipher\0", "sha256")


_NONCE = struct.Struct("<IBBHQ")  # ChaCha20's block counter (0), then kind, robot, 0, seq


def crypt(key: bytes, kind: int, robot: int, seq: int, payload: bytes | memoryview) -> bytes:
    """A payload encrypted, or decrypted (the same operation), with ChaCha20
    (``cryptography``'s documented cipher) under ``key``. The nonce is the
    record's kind, robot and sequence number: each sender's (the SSC's
    commands, an ESC's feedback) and never repeated under one run's key.
    With the record's tag (HMAC-SHA256 with the run key, over the header
    and the encrypted payload) this is encrypt-then-MAC."""
    from cryptography.hazmat.primitives.ciphers import Cipher, algorithms

    nonce = _NONCE.pack(0, kind, robot, 0, seq)
    out: bytes = (
        Cipher(algorithms.ChaCha20(key, nonce), mode=None).encryptor().update(bytes(payload))
    )
    return out


def new_key(path: Path | str) -> bytes:
    """A fresh random key, written to ``path`` (mode 0600, created, never
    overwritten)."""
    key = os.urandom(KEY_BYTES)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    try:
        os.write(fd, key.hex().encode() + b"\n")
    finally:
        os.close(fd)
    return key


def read_private(path: Path | str, what: str, limit: int = 4096) -> str:
    """A secret's text from its file: a regular file of this user, mode 0600
    (no access for group or others), no symlink. ValueError naming what is
    wrong otherwise (``what``: "key", "users")."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the {what} file ({exc.strerror})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise ValueError(f"{path}: the {what} file is not a regular file")
        if st.st_uid != os.getuid():
            raise ValueError(
                f"{path}: the {what} file is owned by uid {st.st_uid}, not {os.getuid()}"
            )
        if st.st_mode & 0o077:
            raise ValueError(
                f"{path}: the {what} file has mode {stat.S_IMODE(st.st_mode):04o}, expected 0600"
            )
        return os.read(fd, limit).decode("utf-8", errors="replace")
    finally:
        os.close(fd)


def load_key(path: Path | str) -> bytes:
    """A link key from its file (:func:`read_private`), holding at least 16
    bytes as hex. ValueError naming what is wrong otherwise."""
    text = read_private(path, "key").strip()
    try:
        key = bytes.fromhex(text)
    except ValueError:
        raise ValueError(f"{path}: the key file does not hold a hex key") from None
    if not 16 <= len(key) <= wire_layout.KEY_MAX:
        raise ValueError(
            f"{path}: the key is {len(key)} bytes, from 16 to {wire_layout.KEY_MAX} are needed"
        )
    return key


@dataclass(frozen=True)
class Decoded:
    kind: int
    robot: int
    source: str
    seq: int
    stamp_ns: int
    estop: bool
    payload: np.ndarray[Any, Any]  # 0-d record of PAYLOADS[kind]


def encode(
    kind: int,
    robot: int,
    source: str,
    seq: int,
    stamp_ns: int,
    payload: np.ndarray[Any, Any] | np.void | bytes,
    estop: bool = False,
    key: bytes = b"",
) -> bytes:
    """One record's bytes. payload: a record (or its bytes) of PAYLOADS[kind]."""
    if kind not in PAYLOADS:
        raise ValueError(f"unknown record kind {kind}")
    raw = payload if isinstance(payload, bytes) else np.asarray(payload).tobytes()
    if len(raw) != PAYLOADS[kind].itemsize:
        raise ValueError(f"payload of kind {kind} must be {PAYLOADS[kind].itemsize} bytes")
    rec = np.zeros((), WIRE)
    h = rec["header"]
    h["magic"] = MAGIC
    h["version"] = VERSION
    h["kind"] = kind
    h["robot"] = robot
    h["source"] = source.encode()[:16]
    h["seq"] = seq
    h["stamp_ns"] = stamp_ns
    h["estop"] = 1 if estop else 0
    rec["payload"][: len(raw)] = np.frombuffer(raw, dtype=np.uint8)
    out = bytearray(rec.tobytes())
    out[_CRC_AT : _CRC_AT + 4] = _crc(out).to_bytes(4, "little")
    return bytes(out) + _tag(key, out)


def decode(buf: bytes | bytearray | memoryview, key: bytes = b"") -> Decoded:
    """The record in ``buf``, or WireError(reason) with reason one of
    size, magic, version, kind, checksum, auth."""
    if len(buf) != SIZE:
        raise WireError("size", f"{len(buf)} bytes, expected {SIZE}")
    rec = np.frombuffer(bytes(buf)[:BODY], dtype=WIRE)[0]
    h = rec["header"]
    if int(h["magic"]) != MAGIC:
        raise WireError("magic", f"{int(h['magic']):#010x}")
    if int(h["version"]) != VERSION:
        raise WireError("version", f"{int(h['version'])}, expected {VERSION}")
    kind = int(h["kind"])
    if kind not in PAYLOADS:
        raise WireError("kind", str(kind))
    if int(h["crc32"]) != _crc(buf):
        raise WireError("checksum")
    _check_tag(key, buf)
    dtype = PAYLOADS[kind]
    payload = np.frombuffer(rec["payload"][: dtype.itemsize].tobytes(), dtype=dtype)[0]
    return Decoded(
        kind=kind,
        robot=int(h["robot"]),
        source=bytes(h["source"]).decode(errors="replace"),
        seq=int(h["seq"]),
        stamp_ns=int(h["stamp_ns"]),
        estop=bool(h["estop"]),
        payload=np.asarray(payload),
    )


def check(
    buf: bytes | bytearray | memoryview, key: bytes = b""
) -> tuple[int, int, bytes, int, int, int]:
    """The header of a well-formed, authentic record: (kind, robot, source,
    seq, stamp_ns, estop), its payload at ``PAYLOAD_AT``; WireError(reason)
    as :func:`decode` (no numpy: the ddm's per-record path)."""
    if len(buf) != SIZE:
        raise WireError("size", f"{len(buf)} bytes, expected {SIZE}")
    magic, version, kind, robot, source, seq, stamp, estop, crc = HEAD.unpack_from(buf, 0)
    if magic != MAGIC:
        raise WireError("magic", f"{magic:#010x}")
    if version != VERSION:
        raise WireError("version", f"{version}, expected {VERSION}")
    if kind not in PAYLOADS:
        raise WireError("kind", str(kind))
    if KERNELS is not None:
        why = KERNELS.wire_verify(_codec(key), buf)
        if why:
            raise WireError(*_VERIFY_FAILS[why])
        return kind, robot, source, seq, stamp, estop
    if crc != _crc(buf):
        raise WireError("checksum")
    _check_tag(key, buf)
    return kind, robot, source, seq, stamp, estop


def payload_stamp(buf: bytes | bytearray | memoryview) -> int:
    """The producer's stamp [ns] in a record's payload."""
    return int(_STAMP.unpack_from(buf, PAYLOAD_AT)[0])


class Encoder:
    """Records of one kind and robot from one source, into one reused buffer."""

    def __init__(self, kind: int, robot: int, source: str, key: bytes = b"") -> None:
        if kind not in PAYLOADS:
            raise ValueError(f"unknown record kind {kind}")
        self.buf = bytearray(SIZE)
        self.view = memoryview(self.buf)
        self.size = PAYLOADS[kind].itemsize
        self.head = (MAGIC, VERSION, kind, robot, source.encode()[:16])
        self.rekey(key)

    def rekey(self, key: bytes) -> None:
        """Sign with ``key`` from now on."""
        self.key = key
        self.codec = _codec(key) if KERNELS is not None else None

    def encode(self, seq: int, stamp_ns: int, payload: Any, estop: bool = False) -> bytes:
        """The record's bytes; payload: the payload's bytes (a memoryview of a
        record is fine)."""
        v = self.view
        HEAD.pack_into(v, 0, *self.head, seq, stamp_ns, 1 if estop else 0, 0)
        v[PAYLOAD_AT : PAYLOAD_AT + self.size] = payload
        if self.codec is not None:
            KERNELS.wire_seal(self.codec, v)
        else:
            struct.pack_into("<I", v, _CRC_AT, _crc(v))
            v[BODY:SIZE] = _tag(self.key, v)
        return bytes(self.buf)


@dataclass
class Admission:
    """Which decoded records to trust: per (source, kind, robot), sequence
    numbers must grow and the source's stamps must move forward.

    duplicate: the same seq again; out_of_order: an older seq; stale: a newer
    seq whose stamp is not newer than the last accepted one (a replay).
    """

    last: dict[tuple[Any, int, int], tuple[int, int]] = field(default_factory=dict)
    accepted: int = 0
    dropped: dict[str, int] = field(
        default_factory=lambda: {"duplicate": 0, "out_of_order": 0, "stale": 0}
    )

    def admit(self, d: Decoded) -> bool:
        return not self.refuse(d.source, d.kind, d.robot, d.seq, d.stamp_ns)

    def refuse(self, source: Any, kind: int, robot: int, seq: int, stamp_ns: int) -> str:
        """Why a record is dropped ('' when admitted; the drop is counted)."""
        key = (source, kind, robot)
        prev = self.last.get(key)
        if prev is not None:
            last_seq, last_stamp = prev
            why = ""
            if seq == last_seq:
                why = "duplicate"
            elif seq < last_seq:
                why = "out_of_order"
            elif stamp_ns <= last_stamp:
                why = "stale"
            if why:
                self.dropped[why] += 1
                return why
        self.last[key] = (seq, stamp_ns)
        self.accepted += 1
        return ""

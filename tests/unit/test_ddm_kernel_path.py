"""The ddm's compiled common case against the wire format's Python reference.

The codec kernels (crc32 from zlib, HMAC-SHA256 from libcrypto) must give
the bytes Python's zlib and hmac give; the admit and emit kernels must take
exactly the common case and leave every other record untouched for the
Python path.
"""

from __future__ import annotations

import hmac
import zlib
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from redistro.ddm import record as wire
from redistro.ddm import wire_layout
from redistro.ddm.kernel_path import KernelPath
from redistro.kernels import KERNELS
from redistro.localdata import LocalData
from redistro.localdata.block import Record
from redistro.localdata.layout import COMMAND, COUNTER, FEEDBACK
from redistro.process.stats import Samples
from tests.helpers import esc_segment

pytestmark = pytest.mark.skipif(KERNELS is None, reason="the kernels are not built")

KEY = bytes(range(32))
LONG_KEY = bytes(range(100))  # longer than SHA-256's block: HMAC hashes it first

# RFC 4231, HMAC-SHA256: (key, data, tag; test case 5 is truncated to 128 bits)
RFC4231 = [
    (b"\x0b" * 20, b"Hi There",
     "b0344c61d8db38535ca8afceaf0bf12b881dc200c9833da726e9376c2e32cff7"),
    (b"Jefe", b"what do ya want for nothing?",
     "5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"),
    (b"\xaa" * 20, b"\xdd" * 50,
     "773ea91e36800e46854db8ebd09181a72959098b3ef8c122d9635514ced565fe"),
    (bytes(range(1, 26)), b"\xcd" * 50,
     "82558a389a443c0ea4cc819899f2083a85f0faa3e578f8077a2e3ff46729665b"),
    (b"\x0c" * 20, b"Test With Truncation", "a3b6167473100ee06e0c796c2955552b"),
    (b"\xaa" * 131, b"Test Using Larger Than Block-Size Key - Hash Key First",
     "60e431591ee0b67f0d8a26aacbf5b77f8e0bc6213728c5140546040f0ee37f54"),
    (b"\xaa" * 131,
     b"This is a test using a larger than block-size key and a larger than block-size data. "
     b"The key needs to be hashed before being used by the HMAC algorithm.",
     "9b09ffa71b942fcb27635fbcd5b0e944bfdc63644f0713938a7f51535c3a35e2"),
]  # fmt: skip


@pytest.mark.parametrize(("key", "data", "tag"), RFC4231)
def test_the_tag_is_hmac_sha256_by_the_rfc_4231_vectors(key: bytes, data: bytes, tag: str) -> None:
    assert KERNELS is not None
    assert KERNELS.wire_tag(wire._codec(key), data).hex()[: len(tag)] == tag


@settings(max_examples=500, deadline=None)
@given(key=st.binary(max_size=wire_layout.KEY_MAX), data=st.binary(max_size=2 * wire.SIZE))
def test_the_tag_is_pythons_hmac_for_any_key_and_data(key: bytes, data: bytes) -> None:
    assert KERNELS is not None
    assert KERNELS.wire_tag(wire._codec(key), data) == hmac.digest(key, data, "sha256")


@settings(max_examples=500, deadline=None)
@given(
    key=st.binary(min_size=16, max_size=64),
    seq=st.integers(0, 2**64 - 1),
    stamp=st.integers(0, 2**63 - 1),
    mark=st.floats(allow_nan=False),
    flip=st.integers(0, wire.SIZE * 8 - 1),
)
def test_sealing_and_verifying_agree_with_the_python_wire_format(
    key: bytes, seq: int, stamp: int, mark: float, flip: int
) -> None:
    """A record sealed by the kernel is byte for byte the one the Python
    path encodes; a flipped bit anywhere is refused with the Python path's
    reason (the checksum for a bit of the body, the tag for one of the tag)."""
    assert KERNELS is not None
    codec = wire._codec(key)
    payload = np.zeros((), COMMAND)
    payload["tau_nm"][0] = mark
    rec = wire.encode(wire.KIND_COMMAND, 1, "ssc", seq, stamp, payload, key=key)
    sealed = bytearray(rec)
    sealed[wire._CRC_AT : wire._CRC_AT + 4] = bytes(4)
    sealed[wire.BODY :] = bytes(32)
    KERNELS.wire_seal(codec, sealed)
    assert bytes(sealed) == rec
    crc = zlib.crc32(rec[wire._CRC_AT + 4 : wire.BODY], zlib.crc32(rec[: wire._CRC_AT]))
    assert int.from_bytes(rec[wire._CRC_AT : wire._CRC_AT + 4], "little") == crc
    assert KERNELS.wire_verify(codec, rec) == 0
    assert KERNELS.wire_verify(codec, rec[:-1]) == 1
    flipped = bytearray(rec)
    flipped[flip // 8] ^= 1 << (flip % 8)
    # a bit of the body or of the stored crc: the checksum; of the tag: the tag
    assert KERNELS.wire_verify(codec, flipped) == (3 if flip >= wire.BODY * 8 else 2)
    if flip >= wire.PAYLOAD_AT * 8:  # (the Python path reads the header's fields first)
        with pytest.raises(wire.WireError, match="checksum" if flip < wire.BODY * 8 else "auth"):
            wire.decode(bytes(flipped), key)
    assert KERNELS.wire_verify(wire._codec(key + b"x"), rec) == 3


def test_a_codec_refuses_a_key_or_record_that_does_not_fit() -> None:
    assert KERNELS is not None
    with pytest.raises(ValueError, match="a key of 193 bytes: at most 192"):
        wire.codec_record(bytes(193))
    bad = wire.codec_record(KEY)
    bad["crc_at"] = wire.BODY  # outside the body
    from redistro.kernels import plan

    p = plan("wire", codec=bad)
    with pytest.raises(ValueError, match="the crc at"):
        KERNELS.wire_verify(p, bytes(wire.SIZE))
    with pytest.raises(ValueError, match="a record of"):
        KERNELS.wire_seal(wire._codec(KEY), bytearray(wire.SIZE - 1))


# -- admit and emit, on a real Local Data segment --


@pytest.fixture
def ld() -> Iterator[LocalData]:
    procs = [("acquisition", "acquisition", 0), ("sender", "sender", 1), ("ddm", "ddm", -1)]
    with esc_segment(procs) as (_, seg):
        yield seg


def _esc_kernel_path(ld: LocalData, latency: Samples) -> KernelPath:
    return KernelPath(
        ld,
        [1],
        [("command", 0)],
        [("feedback", 0)],
        wire.KIND_COMMAND,
        wire.KIND_FEEDBACK,
        "esc.r2",
        KEY,
        starving=True,
        latency=latency,
    )


def _command(
    seq: int,
    stamp: int,
    *,
    robot: int = 1,
    estop: bool = False,
    key: bytes = KEY,
    source: str = "ssc",
    kind: int = wire.KIND_COMMAND,
    mark: float = 0.0,
) -> bytes:
    payload = np.zeros((), wire.PAYLOADS[kind])
    payload["stamp_ns"] = 1  # the producer's stamp: long ago
    if kind == wire.KIND_COMMAND:
        payload["seq_src"] = seq
        payload["tau_nm"][0] = mark
    return wire.encode(kind, robot, source, seq, stamp, payload, estop=estop, key=key)


def test_admit_takes_only_the_common_case(ld: LocalData) -> None:
    latency = Samples(64)
    kpath = _esc_kernel_path(ld, latency)
    admission = wire.Admission()
    command = ld.block("command", 0)
    sent = ld.writer("starving_sent", role="sender")
    counter = Record(COUNTER)
    counter["count"] = 17
    sent.publish(counter.bytes)

    first = _command(1, 100)
    assert kpath.admit(first) == -1  # no source has claimed the robot yet
    assert command.seq == 0  # ... and nothing was written
    # the Python path admits it: the source claims the row
    assert kpath.refuse(admission, 0, b"ssc".ljust(16, b"\0"), wire.KIND_COMMAND, 1, 1, 100) == ""
    assert kpath.admit(_command(2, 200)) == -1  # the exchange is not fresh yet
    kpath.ex[0]["fresh"] = 1

    for bad in (
        _command(3, 300, estop=True),  # an e-stop: the Python path raises it
        _command(3, 300, robot=0),  # not this ddm's robot
        _command(3, 300, key=LONG_KEY),  # forged
        _command(3, 300, source="other"),  # another source
        _command(3, 300, kind=wire.KIND_FEEDBACK),  # not the kind an ESC receives
        _command(1, 300),  # a duplicate seq
        _command(3, 100),  # a replay: a newer seq, an old stamp
        _command(3, 300)[:-1],  # short
    ):
        assert kpath.admit(bad) == -1
    flipped = bytearray(_command(3, 300))
    flipped[70] ^= 4
    assert kpath.admit(bytes(flipped)) == -1
    assert command.seq == 0 and int(kpath.ex[0]["updates"]) == 0

    assert kpath.admit(_command(3, 300, mark=2.5)) == 0
    got = command.read()
    assert float(got["tau_nm"][0]) == 2.5 and int(got["seq_src"]) == 3
    assert int(kpath.ex[0]["updates"]) == 1 and int(kpath.ex[0]["last_update_ns"]) > 0
    paid = ld.block("starving_delivered").read()
    assert int(paid["count"]) == 17 and int(paid["stamp_ns"]) > 0
    assert kpath.latency_count() == 1 and latency._buf[0] > 0  # in the ddm's ring
    # the Python path sees the kernel's admission state
    ssc = b"ssc".ljust(16, b"\0")
    assert kpath.refuse(admission, 0, ssc, wire.KIND_COMMAND, 1, 3, 300) == "duplicate"
    assert kpath.refuse(admission, 0, ssc, wire.KIND_COMMAND, 1, 2, 400) == "out_of_order"
    assert kpath.refuse(admission, 0, ssc, wire.KIND_COMMAND, 1, 4, 300) == "stale"
    assert kpath.refuse(admission, 0, ssc, wire.KIND_COMMAND, 1, 4, 400) == ""
    assert kpath.admit(_command(4, 400)) == -1  # ... and the kernel the Python path's
    assert kpath.admit(_command(5, 500)) == 0


def test_emit_encodes_each_new_sample_once(ld: LocalData) -> None:
    kpath = _esc_kernel_path(ld, Samples(8))
    feedback = ld.writer("feedback", 0, role="acquisition")
    assert kpath.emit() == 0  # nothing produced yet
    rec = Record(FEEDBACK)
    rec["seq_src"] = 5
    rec["stamp_ns"] = 123
    feedback.publish(rec.bytes)
    assert kpath.emit() == 1
    d = wire.decode(bytes(kpath.wire_views[0]), KEY)
    assert (d.kind, d.robot, d.source.rstrip("\0"), d.seq) == (wire.KIND_FEEDBACK, 1, "esc.r2", 1)
    assert not d.estop and d.payload.tobytes() == rec.bytes.tobytes()
    assert int(kpath.out[0]["seq_src"]) == 5  # the Python path sees what was read
    assert int(kpath.ex[0]["sent"]) == 1
    assert kpath.emit() == 0  # the same sample: nothing new
    rec["seq_src"] = 6
    feedback.publish(rec.bytes)
    assert kpath.emit() == 1
    assert wire.decode(bytes(kpath.wire_views[0]), KEY).seq == 2
    assert list(kpath.seq) == [2] and list(kpath.last_out) == [6]


# -- the socket calls: ddm_recv and ddm_send, on a real stream socket pair --


def test_recv_admits_whole_records_and_leaves_the_rest(ld: LocalData) -> None:
    import errno
    import socket

    kpath = _esc_kernel_path(ld, Samples(8))
    kpath.refuse(wire.Admission(), 0, b"ssc".ljust(16, b"\0"), wire.KIND_COMMAND, 1, 1, 100)
    kpath.ex[0]["fresh"] = 1
    rx = bytearray(64 * wire.SIZE)
    a, b = socket.socketpair()
    try:
        a.setblocking(False)
        assert kpath.recv_call(kpath.admit_plan, rx, a.fileno()) == -errno.EAGAIN
        forged = _command(3, 300, key=LONG_KEY)
        b.sendall(_command(2, 200, mark=1.5) + forged)
        assert kpath.recv_call(kpath.admit_plan, rx, a.fileno()) == 2 * wire.SIZE
        assert int(kpath.state["mask"]) == 0b01  # the first admitted, the forged one left
        assert bytes(rx[wire.SIZE : 2 * wire.SIZE]) == forged
        assert float(ld.block("command", 0).read()["tau_nm"][0]) == 1.5
        assert int(kpath.ex[0]["updates"]) == 1
        b.sendall(_command(3, 300)[:100])  # a part record: received, not admitted
        assert kpath.recv_call(kpath.admit_plan, rx, a.fileno()) == 100
        assert int(kpath.state["mask"]) == 0 and int(kpath.ex[0]["updates"]) == 1
        b.close()
        assert kpath.recv_call(kpath.admit_plan, rx, a.fileno()) == 0  # closed by the peer
    finally:
        a.close()
        b.close()


def test_send_sends_whole_records_and_returns_what_it_could_not(ld: LocalData) -> None:
    import errno
    import socket

    kpath = _esc_kernel_path(ld, Samples(8))
    feedback = ld.writer("feedback", 0, role="acquisition")
    rec = Record(FEEDBACK)
    rec["seq_src"] = 1
    feedback.publish(rec.bytes)
    assert kpath.emit() == 1
    assert kpath.send_call(kpath.send_plan, 1, 0) == 1  # no socket: the caller's
    assert int(kpath.send_status[0]) == 0
    a, b = socket.socketpair()
    try:
        kpath.send_fds[0] = a.fileno()
        assert kpath.send_call(kpath.send_plan, 1, 1) == 0
        assert int(kpath.send_status[0]) == wire.SIZE
        assert b.recv(4 * wire.SIZE) == bytes(kpath.wire_views[0])
        assert kpath.send_call(kpath.send_plan, 0, 0) == 0  # nothing to send
        b.close()
        assert kpath.send_call(kpath.send_plan, 1, 0) == 1  # the peer gone
        assert int(kpath.send_status[0]) == -errno.EPIPE
    finally:
        a.close()
        b.close()


def test_reply_receives_admits_and_sends_back_in_one_call(ld: LocalData) -> None:
    """ddm_reply: a whole command admitted and the new feedback sent back
    as the reply (DDM_REPLIED); nothing there (-EAGAIN); a record refused
    leaves everything to the general path (no reply); a part record too;
    a command with no new feedback: admitted, nothing sent."""
    import errno
    import socket

    from redistro.ddm.socket_steps import NOTHING, REPLIED

    kpath = _esc_kernel_path(ld, Samples(8))
    kpath.refuse(wire.Admission(), 0, b"ssc".ljust(16, b"\0"), wire.KIND_COMMAND, 1, 1, 100)
    kpath.ex[0]["fresh"] = 1
    feedback = ld.writer("feedback", 0, role="acquisition")
    rec = Record(FEEDBACK)
    rx = bytearray(64 * wire.SIZE)
    a, b = socket.socketpair()

    def reply() -> int:
        got: int = kpath.reply_call(
            kpath.admit_plan, kpath.emit_plan, kpath.send_plan, rx, a.fileno()
        )
        return got

    try:
        a.setblocking(False)
        b.settimeout(2.0)
        kpath.send_fds[0] = a.fileno()
        assert reply() == NOTHING == -errno.EAGAIN
        assert int(kpath.reply["emitted"]) == -2  # no emit

        rec["seq_src"] = 7
        feedback.publish(rec.bytes)
        b.sendall(_command(2, 200, mark=1.5))
        assert reply() == REPLIED
        assert float(ld.block("command", 0).read()["tau_nm"][0]) == 1.5
        back = wire.decode(b.recv(4 * wire.SIZE), KEY)
        assert back.kind == wire.KIND_FEEDBACK and int(back.payload["seq_src"]) == 7
        assert int(kpath.ex[0]["updates"]) == 1 and int(kpath.ex[0]["sent"]) == 1

        b.sendall(_command(3, 300))  # no new feedback: admitted, nothing to send
        assert reply() == REPLIED
        assert int(kpath.reply["emitted"]) == 0 and int(kpath.ex[0]["sent"]) == 1
        assert int(kpath.ex[0]["updates"]) == 2

        rec["seq_src"] = 8
        feedback.publish(rec.bytes)
        forged = _command(4, 400, key=LONG_KEY)
        b.sendall(forged)  # refused by the kernel: the general path's, no reply
        assert reply() == wire.SIZE
        assert int(kpath.state["mask"]) == 0 and int(kpath.reply["emitted"]) == -2
        assert bytes(rx[: wire.SIZE]) == forged
        b.setblocking(False)
        with pytest.raises(BlockingIOError):
            b.recv(4 * wire.SIZE)

        b.sendall(_command(4, 400)[:100])  # a part record
        assert reply() == 100 and int(kpath.reply["emitted"]) == -2
    finally:
        a.close()
        b.close()


def test_the_compiled_answer_takes_the_usual_command_and_leaves_the_rest(ld: LocalData) -> None:
    """_kernels.CompiledAnswer, an ESC's answer in the transport's thread: a sound
    command admitted and the new feedback handed to put as the reply (a
    sample's payload, or bytes); with no new feedback, admitted and nothing
    put. Everything else goes to the fallback untouched: the state closed,
    the e-stop up, records queued before it, the step's lock held, a record
    the kernel refuses, an answerer closed. A put that raises leaves the
    reply owed and wakes the ddm; every 64th answer publishes the exchange."""
    import collections
    import threading

    from redistro.localdata.layout import EXCHANGE, MANAGER

    assert KERNELS is not None
    kpath = _esc_kernel_path(ld, Samples(8))
    kpath.refuse(wire.Admission(), 0, b"ssc".ljust(16, b"\0"), wire.KIND_COMMAND, 1, 1, 100)
    kpath.ex[0]["fresh"] = 1
    feedback = ld.writer("feedback", 0, role="acquisition")
    rec = Record(FEEDBACK)
    state = np.zeros((), wire_layout.ANSWER_STATE)
    _, manager_at, _ = ld.block_offsets("manager")
    estop_at = manager_at + int(MANAGER.fields["estop"][1])  # type: ignore[index]
    lock = threading.Lock()
    put: list[bytes] = []
    inbox: collections.deque[bytes] = collections.deque()
    fallen: list[bytes] = []
    woken: list[int] = []
    before: list[int] = []

    class Payload:
        def __init__(self, raw: bytes) -> None:
            self.raw = raw

        def to_bytes(self) -> bytes:
            return self.raw

    class Sample:  # (zenoh's: the record is its payload's bytes)
        def __init__(self, raw: bytes) -> None:
            self.payload = Payload(raw)

    def failing_put(reply: bytes) -> None:
        raise RuntimeError("the session is closing")

    def answerer(put_call: object) -> Any:
        return KERNELS.CompiledAnswer(
            kpath.admit_plan,
            kpath.emit_plan,
            kpath.publish_plan,
            state,
            estop_at,
            lock,
            put_call,
            inbox,
            fallen.append,
            lambda: woken.append(1),
            lambda: before.append(1),
        )

    answer = answerer(put.append)
    first = _command(2, 200, mark=1.5)
    answer(Sample(first))  # the state closed (not yet commanded): the Python path's
    assert fallen == [first] and not put and int(kpath.ex[0]["updates"]) == 0
    assert before == [1]

    state["answering"] = 1
    rec["seq_src"] = 7
    feedback.publish(rec.bytes)
    answer(Sample(_command(3, 300, mark=2.5)))
    assert float(ld.block("command", 0).read()["tau_nm"][0]) == 2.5
    assert len(put) == 1 and int(wire.decode(put[0], KEY).payload["seq_src"]) == 7
    assert int(state["answered"]) == 1 and int(kpath.ex[0]["updates"]) == 1
    answer(_command(4, 400))  # bytes; no new feedback: admitted, nothing put
    assert len(put) == 1 and int(state["answered"]) == 2

    refused = [_command(5, 500, key=LONG_KEY), _command(4, 450)]  # forged; a duplicate
    for raw in refused:
        answer(raw)
    assert fallen[1:] == refused and int(state["answered"]) == 2
    left = [_command(5, 500), _command(6, 600), _command(7, 700)]
    inbox.append(b"queued first")
    answer(left[0])
    inbox.clear()
    with lock:  # the ddm stepping
        answer(left[1])
    ld.raw[estop_at] = 1
    answer(left[2])
    ld.raw[estop_at] = 0
    assert fallen[3:] == left and int(state["answered"]) == 2

    rec["seq_src"] = 8
    feedback.publish(rec.bytes)
    answerer(failing_put)(_command(8, 800))  # admitted, the reply owed to the ddm
    assert int(state["reply_owed"]) == 1 and woken == [1] and int(state["answered"]) == 3
    assert not lock.locked()

    exchange = ld.block("exchange", 0)
    for k in range(9, 9 + 61):  # the 64th answer publishes the exchange
        answer(_command(k, 100 * k))
    assert int(state["answered"]) == 64
    assert int(np.frombuffer(exchange.read().tobytes(), EXCHANGE)[0]["updates"]) == 64

    with pytest.raises(ValueError, match="not initialized"):
        KERNELS.CompiledAnswer.__new__(KERNELS.CompiledAnswer)(_command(70, 7000))

    answer.close()
    answer(_command(70, 7000))
    assert fallen[-1] == _command(70, 7000) and int(state["answered"]) == 64
    assert len(before) == 1 + 1 + 1 + 2 + 3 + 1 + 61 + 1  # run first on every record


def test_the_sscs_compiled_answer_admits_feedback_and_publishes_the_exchange() -> None:
    """The SSC's side of _kernels.CompiledAnswer (put None): each sound feedback
    admitted into its robot's block and the exchange published at once (the
    manager watches every robot's updates); nothing is put."""
    import collections
    import threading

    from redistro.localdata.layout import EXCHANGE, MANAGER

    assert KERNELS is not None
    from redistro.ipc.names import new_session_id

    seg = LocalData.create(
        new_session_id(),
        "ssc",
        node_kind="ssc",
        proc_names=["worker", "ddm"],
        proc_roles=["worker", "ddm"],
        proc_stages=[0, -1],
        robot_names=["r1", "r2"],
        rate_hz=200.0,
        period_ns=5_000_000,
        heartbeat_limit_cycles=5,
        manifest=None,
        memory=True,
    )
    try:
        kpath = KernelPath(
            seg,
            [0, 1],
            [("feedback", 0), ("feedback", 1)],
            [("command", 0), ("command", 1)],
            wire.KIND_FEEDBACK,
            wire.KIND_COMMAND,
            "ssc",
            KEY,
            starving=False,
            latency=Samples(8),
        )
        for i, name in enumerate(("esc.r1", "esc.r2")):
            source = name.encode().ljust(16, b"\0")
            kpath.refuse(wire.Admission(), i, source, wire.KIND_FEEDBACK, i, 1, 100)
            kpath.ex[i]["fresh"] = 1
        state = np.zeros((), wire_layout.ANSWER_STATE)
        state["answering"] = 1
        _, manager_at, _ = seg.block_offsets("manager")
        fallen: list[bytes] = []
        answer = KERNELS.CompiledAnswer(
            kpath.admit_plan,
            kpath.emit_plan,
            kpath.publish_plan,
            state,
            manager_at + int(MANAGER.fields["estop"][1]),  # type: ignore[index]
            threading.Lock(),
            None,
            collections.deque(),
            fallen.append,
            lambda: None,
            None,
        )
        payload = np.zeros((), FEEDBACK)
        payload["seq_src"] = 5
        answer(wire.encode(wire.KIND_FEEDBACK, 1, "esc.r2", 2, 200, payload, key=KEY))
        assert int(seg.block("feedback", 1).read()["seq_src"]) == 5
        published = np.frombuffer(seg.block("exchange", 1).read().tobytes(), EXCHANGE)[0]
        assert int(published["updates"]) == 1 and int(state["answered"]) == 1
        other = wire.encode(wire.KIND_FEEDBACK, 0, "esc.r2", 3, 300, payload, key=KEY)
        answer(other)  # robot r1's feedback from r2's ESC: the Python path refuses it
        assert fallen == [other] and int(state["answered"]) == 1
    finally:
        seg.close()
        seg.unlink()

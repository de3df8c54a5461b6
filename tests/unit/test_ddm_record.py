"""The DDM wire record: round trip, refusal of anything malformed, admission."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from redistro.ddm.record import (
    KIND_COMMAND,
    KIND_FEEDBACK,
    SIZE,
    Admission,
    decode,
    encode,
)
from redistro.errors import WireError
from redistro.localdata.layout import COMMAND, FEEDBACK


def _feedback(q0: float = 0.5) -> np.ndarray:
    fb = np.zeros((), FEEDBACK)
    fb["q_rad"] = np.arange(7) * 0.1 + q0
    fb["wrench"] = [1, 2, 3, 0.1, 0.2, 0.3]
    return fb


def test_round_trip_keeps_every_field() -> None:
    fb = _feedback()
    buf = encode(KIND_FEEDBACK, 1, "esc.r2", 42, 123456789, fb, estop=True)
    assert len(buf) == SIZE
    d = decode(buf)
    assert (d.kind, d.robot, d.source, d.seq, d.stamp_ns, d.estop) == (
        KIND_FEEDBACK,
        1,
        "esc.r2",
        42,
        123456789,
        True,
    )
    assert d.payload.tobytes() == fb.tobytes()
    cmd = np.zeros((), COMMAND)
    cmd["tau_nm"] = 3.5
    assert decode(encode(KIND_COMMAND, 0, "ssc", 1, 5, cmd)).payload["tau_nm"][6] == 3.5


@pytest.mark.parametrize(
    ("mutate", "reason"),
    [
        (lambda b: b[:-1], "size"),
        (lambda b: b + b"\0", "size"),
        (lambda b: b"\0\0\0\0" + b[4:], "magic"),
        (lambda b: b[:4] + b"\x09\x00" + b[6:], "version"),
        (lambda b: b[:6] + b"\x07" + b[7:], "kind"),
        (lambda b: b[:40] + bytes([b[40] ^ 1]) + b[41:], "checksum"),
        (lambda b: b[:-33] + bytes([b[-33] ^ 0x80]) + b[-32:], "checksum"),
        (lambda b: b[:-1] + bytes([b[-1] ^ 0x80]), "auth"),
    ],
)
def test_malformed_records_are_refused_with_the_reason(mutate, reason: str) -> None:  # type: ignore[no-untyped-def]
    buf = encode(KIND_FEEDBACK, 0, "esc.r1", 1, 10, _feedback())
    with pytest.raises(WireError) as exc:
        decode(mutate(buf))
    assert exc.value.reason == reason


@settings(max_examples=400, deadline=None)
@given(st.binary(min_size=0, max_size=2 * SIZE))
def test_random_bytes_never_crash_the_decoder(data: bytes) -> None:
    with contextlib.suppress(WireError):  # anything else fails the test
        decode(data)


@settings(max_examples=200, deadline=None)
@given(st.integers(min_value=0, max_value=SIZE - 1), st.integers(min_value=1, max_value=255))
def test_any_flipped_byte_is_caught(at: int, flip: int) -> None:
    buf = bytearray(encode(KIND_FEEDBACK, 0, "esc.r1", 7, 99, _feedback()))
    buf[at] ^= flip
    with pytest.raises(WireError):
        decode(bytes(buf))


def test_admission_drops_duplicates_old_and_replayed_records() -> None:
    adm = Admission()

    def rec(seq: int, stamp: int, source: str = "esc.r1", robot: int = 0):  # type: ignore[no-untyped-def]
        return decode(encode(KIND_FEEDBACK, robot, source, seq, stamp, _feedback()))

    assert adm.admit(rec(1, 100))
    assert adm.admit(rec(2, 200))
    assert not adm.admit(rec(2, 200))  # duplicate
    assert not adm.admit(rec(1, 100))  # out of order
    assert not adm.admit(rec(3, 150))  # newer seq, older stamp: a replay
    assert adm.admit(rec(3, 300))
    assert adm.admit(rec(1, 50, source="esc.r2"))  # another source has its own count
    assert adm.admit(rec(1, 50, robot=1))
    assert adm.dropped == {"duplicate": 1, "out_of_order": 1, "stale": 1}
    assert adm.accepted == 5


def test_the_ddm_fast_path_agrees_with_encode_and_decode() -> None:
    """Encoder and check() (the ddm's per-record path, no numpy) write and
    read exactly the records encode() and decode() do; check() refuses what
    decode() refuses, for the same reason."""
    from redistro.ddm.record import PAYLOAD_AT, Encoder, check, payload_stamp

    enc = Encoder(KIND_FEEDBACK, 1, "esc.r2")
    for seq in range(1, 50):
        fb = _feedback(seq * 0.01)
        fb["stamp_ns"] = 1000 + seq
        fast = enc.encode(seq, 7 * seq, memoryview(fb.reshape(1).view(np.uint8)), seq % 3 == 0)
        assert fast == encode(KIND_FEEDBACK, 1, "esc.r2", seq, 7 * seq, fb, estop=seq % 3 == 0)
        kind, robot, source, s, stamp, estop = check(fast)
        d = decode(fast)
        assert (kind, robot, source.rstrip(b"\0").decode(), s, stamp, bool(estop)) == (
            d.kind,
            d.robot,
            d.source.rstrip("\0"),
            d.seq,
            d.stamp_ns,
            d.estop,
        )
        assert fast[PAYLOAD_AT : PAYLOAD_AT + FEEDBACK.itemsize] == fb.tobytes()
        assert payload_stamp(fast) == 1000 + seq
    rng = np.random.default_rng(5)
    for _ in range(500):
        bad = bytearray(fast)
        bad[int(rng.integers(SIZE))] ^= 1 << int(rng.integers(8))
        reasons = []
        for fn in (check, decode):
            try:
                fn(bytes(bad))
                reasons.append("")
            except WireError as exc:
                reasons.append(exc.args[0])
        assert reasons[0] == reasons[1] != ""


def _resealed(buf: bytes) -> bytes:
    """A record changed by someone without the key: its checksum recomputed
    (the tag cannot be)."""
    from redistro.ddm.record import _crc

    b = bytearray(buf)
    b[_CRC_AT_TEST : _CRC_AT_TEST + 4] = _crc(b).to_bytes(4, "little")
    return bytes(b)


_CRC_AT_TEST = 44  # the header's crc32 field


def test_a_record_without_the_links_key_is_refused_as_forged() -> None:
    from redistro.ddm.record import BODY, check

    key, other = b"k" * 32, b"o" * 32
    good = encode(KIND_COMMAND, 0, "ssc", 1, 10, np.zeros((), COMMAND), key=key)
    assert check(good, key)[0] == KIND_COMMAND
    forged = encode(KIND_COMMAND, 0, "ssc", 1, 10, np.zeros((), COMMAND), key=other)
    with pytest.raises(WireError) as exc:
        check(forged, key)
    assert exc.value.reason == "auth"
    # the same record under another source name, its checksum made right
    renamed = bytearray(good)
    renamed[8:24] = b"intruder".ljust(16, b"\0")
    with pytest.raises(WireError) as exc:
        check(_resealed(bytes(renamed)), key)
    assert exc.value.reason == "auth"
    # a 150 N m command written into a genuine record
    cmd = np.zeros((), COMMAND)
    cmd["tau_nm"][0] = 150.0
    tampered = bytearray(good)
    raw = cmd.tobytes()
    tampered[48 : 48 + len(raw)] = raw
    with pytest.raises(WireError) as exc:
        check(_resealed(bytes(tampered)), key)
    assert exc.value.reason == "auth"
    assert len(good) == BODY + 32


@settings(max_examples=60, deadline=None)
@given(key=st.binary(min_size=16, max_size=200), body=st.binary(min_size=0, max_size=400))
def test_the_records_tag_is_hmac_sha256(key: bytes, body: bytes) -> None:
    """The tag from the two padded-key states is RFC 2104's HMAC-SHA256
    (keys longer than the block included), the standard library's bytes."""
    import hmac

    from redistro.ddm.record import BODY, _tag

    buf = body.ljust(BODY, b"\x5a")
    assert _tag(key, buf) == hmac.digest(key, buf[:BODY], "sha256")


def test_a_key_file_must_be_private(tmp_path: Path) -> None:
    from redistro.ddm.record import load_key, new_key

    path = tmp_path / "link.key"
    key = new_key(path)
    assert load_key(path) == key and len(key) == 32
    os.chmod(path, 0o644)
    with pytest.raises(ValueError, match="mode 0644, expected 0600"):
        load_key(path)
    os.chmod(path, 0o600)
    path.write_text("not hex")
    with pytest.raises(ValueError, match="does not hold a hex key"):
        load_key(path)
    with pytest.raises(FileExistsError):
        new_key(path)  # never overwritten

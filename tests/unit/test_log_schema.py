"""The session log's messages are ROS 2 messages: every logged block's and
the timing's definition, encoded as the writer does, decoded by a reader
no one here wrote (mcap-ros2-support) and by our own, field for field."""

from __future__ import annotations

import io
import struct
from typing import Any

import numpy as np
import pytest

from redistro.localdata.layout import BLOCKS
from redistro.log import schema
from redistro.log.writer import cdr_message


def _random(dt: np.dtype[Any], n: int, rng: np.random.Generator) -> np.ndarray[Any, Any]:
    raw = rng.integers(0, 256, size=n * dt.itemsize, dtype=np.uint8).tobytes()
    arr = np.frombuffer(raw, dt).copy()
    for name in dt.names or ():
        if arr[name].dtype.kind == "f":  # (no NaN: compared by value below)
            arr[name] = rng.normal(size=arr[name].shape)
    return arr


def _mcap(name: str, definition: str, messages: list[bytes]) -> bytes:
    from mcap.writer import Writer

    out = io.BytesIO()
    w = Writer(out)
    w.start(profile="ros2", library="test")
    sid = w.register_schema(name, "ros2msg", definition.encode())
    cid = w.register_channel("/t", "cdr", sid)
    for k, data in enumerate(messages):
        w.add_message(cid, k, data, k, k)
    w.finish()  # type: ignore[no-untyped-call]
    return out.getvalue()


def _decoded(blob: bytes) -> list[Any]:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    reader = make_reader(io.BytesIO(blob), decoder_factories=[DecoderFactory()])
    return [m for _s, _c, _m, m in reader.iter_decoded_messages()]


CASES = [(name, schema.with_cycle(BLOCKS[name][0])) for name in BLOCKS] + [
    ("timing5", schema.timing_dtype(5))
]


@pytest.mark.parametrize(("name", "dt"), CASES, ids=[c[0] for c in CASES])
def test_a_logged_message_decodes_the_same_in_a_ros2_reader(name: str, dt: np.dtype[Any]) -> None:
    rng = np.random.default_rng(7)
    arr = _random(dt, 5, rng)
    runs = [(a, a + n, bytes(p)) for a, n, p in schema.cdr_runs(dt)]
    messages = [cdr_message(r.tobytes(), runs) for r in arr]
    wire = schema.cdr_dtype(dt)
    assert all(len(m) == wire.itemsize for m in messages)
    definition = schema.msg_definition(dt)
    back = schema.dtype_from_msg(definition)  # (a text field: a uint8 array)
    assert back.names == dt.names and back.itemsize == dt.itemsize
    # the timing's writer packs with struct: the same bytes as the runs give
    if name.startswith("timing"):
        fmt = struct.Struct(schema.cdr_struct(dt))
        values = [x for f in dt.names or () for x in np.atleast_1d(arr[0][f]).tolist()]
        assert schema.CDR_HEADER + fmt.pack(*values) == messages[0]
    decoded = _decoded(_mcap(schema.type_name(name), definition, messages))
    assert len(decoded) == len(arr)
    ours = np.frombuffer(b"".join(messages), wire)
    for got, theirs, want in zip(ours, decoded, arr, strict=True):
        for field in dt.names or ():
            v, their = want[field], getattr(theirs, field)
            if isinstance(their, bytes | bytearray):  # a uint8 array, as that reader gives it
                assert their == v.tobytes(), field
            else:
                np.testing.assert_array_equal(np.asarray(their), v, err_msg=field)
            assert got[field].tobytes() == v.tobytes(), field


def test_type_names_are_ros2_names() -> None:
    assert schema.type_name("feedback") == "redistro/msg/Feedback"
    assert schema.type_name("starving_sent") == "redistro/msg/StarvingSent"
    assert schema.type_name("timing12") == "redistro/msg/Timing12"


def test_feedback_becomes_a_joint_state_and_a_wrench_in_a_ros2_reader() -> None:
    """A robot's feedback as sensor_msgs/JointState and
    geometry_msgs/WrenchStamped, as the writer makes them, decoded by
    mcap-ros2-support: names, stamp, frame and values."""
    from redistro.log import ros2
    from redistro.robotmodel import JOINT_NAMES

    dt = schema.with_cycle(BLOCKS["feedback"][0])
    arr = _random(dt, 3, np.random.default_rng(3))
    fields = dt.fields
    assert fields is not None
    want = ("q_rad", "qd_rad_s", "tau_nm", "wrench")
    spec = {k: int(fields[k][1]) for k in want}
    fb = ros2.Feedback("r2", list(JOINT_NAMES), spec)
    stamps = [1_764_000_000_123_456_789 + k * 1_000_000 for k in range(len(arr))]
    js = [fb.joint_state(r.tobytes(), t) for r, t in zip(arr, stamps, strict=True)]
    ws = [fb.wrench(r.tobytes(), t) for r, t in zip(arr, stamps, strict=True)]
    got_js = _decoded(_mcap(ros2.JOINT_STATE, ros2.JOINT_STATE_DEF, js))
    got_ws = _decoded(_mcap(ros2.WRENCH_STAMPED, ros2.WRENCH_STAMPED_DEF, ws))
    for r, t, j, w in zip(arr, stamps, got_js, got_ws, strict=True):
        for m in (j, w):
            assert (m.header.stamp.sec, m.header.stamp.nanosec) == divmod(t, 1_000_000_000)
        assert j.header.frame_id == "" and w.header.frame_id == "r2_tool"
        assert j.name == [f"r2_{n}" for n in JOINT_NAMES]
        np.testing.assert_array_equal(j.position, r["q_rad"])
        np.testing.assert_array_equal(j.velocity, r["qd_rad_s"])
        np.testing.assert_array_equal(j.effort, r["tau_nm"])
        f, tq = w.wrench.force, w.wrench.torque
        np.testing.assert_array_equal([f.x, f.y, f.z, tq.x, tq.y, tq.z], r["wrench"])


def test_an_event_is_a_ros2_string_of_its_json_document() -> None:
    import json

    from redistro.log import ros2

    docs = [{"cycle": 3, "event": "segment", "name": "insért"}, {"text": ""}]
    messages = [ros2.event(json.dumps(d)) for d in docs]
    got = _decoded(_mcap(ros2.EVENT, ros2.EVENT_DEF, messages))
    assert [json.loads(m.json) for m in got] == docs
    assert [json.loads(ros2.event_json(m)) for m in messages] == docs
    for bad in (b"", messages[0][:-1], b"\x00\x01\x00\x00" + bytes(4), messages[0] + b"x"):
        with pytest.raises(ValueError):
            ros2.event_json(bad)


def test_a_message_box_line_is_a_message_of_its_own() -> None:
    """redistro/msg/Message: decoded by mcap-ros2-support and by our reader
    to the recorder's event, level as rcl_interfaces' (Python's) number."""
    from redistro.log import ros2

    docs: list[dict[str, Any]] = [
        {"cycle": 7, "level": "ERROR", "process": "worker", "text": "stuck é", "stamp_ns": 5},
        {"cycle": 2**40, "level": "INFO", "process": "", "text": "", "stamp_ns": 18 * 10**17 + 9},
        {"cycle": 0, "level": "WARNING", "process": "ddm", "text": "x" * 301, "stamp_ns": 1},
    ]
    messages = [ros2.message(d) for d in docs]
    got = _decoded(_mcap(ros2.MESSAGE, ros2.MESSAGE_DEF, messages))
    assert [(m.level, m.process, m.text, m.cycle) for m in got] == [
        (ros2.LEVELS[d["level"]], d["process"], d["text"], d["cycle"]) for d in docs
    ]
    assert [m.stamp.sec * 10**9 + m.stamp.nanosec for m in got] == [d["stamp_ns"] for d in docs]
    assert [ros2.message_doc(m) for m in messages] == docs
    for bad in (b"", messages[0][:-1], messages[0][:25], b"\x00\x01\x00\x00" + bytes(30)):
        with pytest.raises(ValueError):
            ros2.message_doc(bad)


def test_the_package_message_files_are_the_ones_the_log_writes() -> None:
    """redistro/msg/*.msg: every message the log's channels define, no other
    (after a layout change: ``schema.write_package_messages()``)."""
    from tests.helpers import ROOT

    folder = ROOT / schema.MSG_FOLDER
    files = {p.name: p.read_text() for p in folder.glob("*.msg")}
    assert files == schema.package_messages(), "run schema.write_package_messages()"

"""The ROS 2 bridge's wire conventions against a ROS 2 client no one here
wrote (zenoh-ros2-sdk), and its zenoh session's access rules for real."""

from __future__ import annotations

import socket
import threading
import time
from typing import Any

import pytest

from redistro import ros2bridge
from redistro.log import ros2


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_keys_tokens_and_attachment_are_the_ones_rmw_zenoh_clients_read() -> None:
    """The data key, the publisher's liveliness token and the attachment,
    each as zenoh-ros2-sdk builds or parses them (its own code)."""
    from zenoh_ros2_sdk.attachment import Attachment
    from zenoh_ros2_sdk.entity import EndpointEntity, EntityKind, NodeEntity
    from zenoh_ros2_sdk.keyexpr import endpoint_liveliness_keyexpr, topic_keyexpr
    from zenoh_ros2_sdk.utils import ros2_to_dds_type

    t = ros2bridge.Topic("/r2/joint_states", ros2.JOINT_STATE, entity=3, domain=7)
    h = ros2bridge.type_hash(ros2.JOINT_STATE)
    assert h.startswith("RIHS01_") and len(h) == 7 + 64
    assert ros2bridge.dds_type(ros2.JOINT_STATE) == ros2_to_dds_type(ros2.JOINT_STATE)
    assert t.key == topic_keyexpr(7, "/r2/joint_states", ros2_to_dds_type(ros2.JOINT_STATE), h)
    node = NodeEntity(domain_id=7, session_id="abc", node_id=0, node_name="redistro_bridge")
    ep = EndpointEntity(
        node=node,
        entity_id=3,
        kind=EntityKind.PUBLISHER,
        name="/r2/joint_states",
        dds_type_name=ros2_to_dds_type(ros2.JOINT_STATE),
        type_hash=h,
        qos=ros2bridge.QOS,
    )
    assert t.token("abc") == endpoint_liveliness_keyexpr(ep)
    sent: list[tuple[bytes, bytes]] = []

    class Pub:
        def put(self, payload: bytes, attachment: bytes) -> None:
            sent.append((payload, attachment))

    t.pub = Pub()
    t.put(b"x", 123_456_789)
    t.put(b"y", 123_456_790)
    got = [Attachment.from_bytes(a) for _, a in sent]
    assert [(a.sequence_id, a.timestamp_ns) for a in got] == [(1, 123_456_789), (2, 123_456_790)]
    assert all(a.gid == t.gid and len(a.gid) == 16 for a in got)


def test_the_type_hashes_are_the_ones_the_sdk_computes_from_the_definitions() -> None:
    """RIHS01 of each published type: ours (rosbags' type store) and the SDK's
    own computation from the .msg text must agree, or no subscriber matches."""
    from zenoh_ros2_sdk.utils import get_type_hash

    time_def = "int32 sec\nuint32 nanosec\n"
    header = "builtin_interfaces/Time stamp\nstring frame_id\n"
    deps = {"builtin_interfaces/msg/Time": time_def, "std_msgs/msg/Header": header}
    js = "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\n"
    js += "float64[] effort\n"
    assert ros2bridge.type_hash(ros2.JOINT_STATE) == get_type_hash(ros2.JOINT_STATE, js, deps)
    assert ros2bridge.type_hash("std_msgs/msg/String") == get_type_hash(
        "std_msgs/msg/String", "string data\n", {}
    )


def _open(settings: dict[str, Any]) -> Any:
    from redistro.ddm.zenoh_transport import open_session

    return open_session(settings)


def _client(port: int) -> Any:
    return _open(
        {
            "mode": "client",
            "connect/endpoints": [f"tcp/127.0.0.1:{port}"],
            "scouting/multicast/enabled": False,
            "transport/shared_memory/enabled": False,
        }
    )


def _wait(cond: Any, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.02)  # polling a condition, with a deadline
    return False


def test_the_bridges_session_lets_its_topics_out_and_nothing_in() -> None:
    """A client on the bridge's endpoint receives what the bridge puts under
    its domain, and nothing it puts elsewhere; what the client puts never
    reaches a subscriber on the bridge's side."""
    import zenoh

    port = _port()
    bridge = _open(ros2bridge.session_settings([f"tcp/127.0.0.1:{port}"], 0))
    outside = _client(port)
    try:
        seen_out: list[str] = []
        seen_in: list[str] = []
        lock = threading.Lock()

        def out(sample: Any) -> None:
            with lock:
                seen_out.append(str(sample.key_expr))

        def inn(sample: Any) -> None:
            with lock:
                seen_in.append(str(sample.key_expr))

        remote = zenoh.Locality.REMOTE  # (a session's own puts reach its own subscribers)
        subs = [
            outside.declare_subscriber(k, out, allowed_origin=remote)
            for k in ("0/**", "redistro/**")
        ]
        sub_in = bridge.declare_subscriber("**", inn, allowed_origin=remote)
        pub = bridge.declare_publisher("0/r1/joint_states/T/H")
        other = bridge.declare_publisher("redistro/g/r1/command")

        def arrived() -> bool:
            pub.put(b"ok")
            other.put(b"no")
            with lock:
                return "0/r1/joint_states/T/H" in seen_out

        assert _wait(arrived), seen_out
        for _ in range(20):
            outside.put("0/r1/command/T/H", b"from ros 2")
            outside.put("redistro/g/r1/command", b"from ros 2")
        # a round trip after them: anything allowed in would be there by now
        assert _wait(arrived)
        with lock:
            assert "redistro/g/r1/command" not in seen_out, seen_out
            assert seen_in == [], seen_in
        for sub in [*subs, sub_in]:
            sub.undeclare()
    finally:
        outside.close()
        bridge.close()


@pytest.mark.parametrize("endpoint", ["tcp/127.0.0.1:0", "tcp/nohost", "http://x:1"])
def test_a_bad_listen_endpoint_is_refused_before_anything_starts(endpoint: str) -> None:
    from redistro.errors import ConfigError

    with pytest.raises(ConfigError, match="--listen"):
        ros2bridge.run_bridge("no-such-session", [endpoint])

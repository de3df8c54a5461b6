"""A ROS 2 client over Zenoh that no one here wrote (zenoh-ros2-sdk), run as its own process.

``python tests/ros2_listener.py PORT TOPIC COUNT TIMEOUT MSGDIR`` connects to
the zenoh endpoint tcp/127.0.0.1:PORT, lists the ROS 2 graph's topics (the
liveliness tokens, as ``ros2 topic list`` would), takes COUNT JointState
messages from TOPIC and prints JSON. The standard message definitions are
given to the SDK as .msg files in MSGDIR (it would fetch them from git):
the SDK computes the type hash from them itself.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path

DEFINITIONS = {
    "builtin_interfaces/msg/Time.msg": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header.msg": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "sensor_msgs/msg/JointState.msg": (
        "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\n"
        "float64[] effort\n"
    ),
}


def main() -> int:
    port, topic, count, timeout, msgdir = sys.argv[1:6]
    for name, text in DEFINITIONS.items():
        path = Path(msgdir) / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    from zenoh_ros2_sdk import ROS2Subscriber, message_registry
    from zenoh_ros2_sdk.discovery import get_topic_names_and_types

    message_registry.get_registry(msgdir)
    got: list[dict[str, object]] = []
    done = threading.Event()

    def take(m: object) -> None:
        h = m.header  # type: ignore[attr-defined]
        got.append(
            {
                "name": list(m.name),  # type: ignore[attr-defined]
                "position": [float(v) for v in m.position],  # type: ignore[attr-defined]
                "velocity": [float(v) for v in m.velocity],  # type: ignore[attr-defined]
                "effort": [float(v) for v in m.effort],  # type: ignore[attr-defined]
                "stamp_ns": h.stamp.sec * 10**9 + h.stamp.nanosec,
                "received_ns": time.time_ns(),
            }
        )
        if len(got) >= int(count):
            done.set()

    sub = ROS2Subscriber(
        topic=topic,
        msg_type="sensor_msgs/msg/JointState",
        callback=take,
        router_port=int(port),
    )
    done.wait(float(timeout))
    topics = get_topic_names_and_types(router_port=int(port), timeout=2.0)
    sub.close()
    print(json.dumps({"key": sub.keyexpr, "topics": topics, "messages": got[: int(count)]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

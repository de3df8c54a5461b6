"""The view's parts that need no browser: the pose algebra, the address
check, the panel's text."""

from __future__ import annotations

import socket

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from redistro.errors import ConfigError
from redistro.view import _mul, check_address


def _matrix(p: tuple[float, ...]) -> np.ndarray:
    x, y, z, w = p[3:]
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, p[:3]
    return m


unit = st.floats(-1, 1, allow_nan=False)


def _pose(v: list[float]) -> tuple[float, ...]:
    q = np.array(v[3:]) + np.array([0, 0, 0, 1e-3])
    q = q / np.linalg.norm(q)
    return (*v[:3], *q)


@settings(max_examples=300, deadline=None)
@given(st.lists(unit, min_size=7, max_size=7), st.lists(unit, min_size=7, max_size=7))
def test_a_pose_then_another_is_the_product_of_their_matrices(
    a: list[float], b: list[float]
) -> None:
    pa, pb = _pose(a), _pose(b)
    got = _matrix(_mul(pa, pb))  # type: ignore[arg-type]
    assert np.allclose(got, _matrix(pa) @ _matrix(pb), atol=1e-12)


def test_a_port_taken_or_out_of_range_or_an_address_not_ours_is_refused() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(ConfigError, match=f"--port {port}: "):
            check_address("127.0.0.1", port)
    with pytest.raises(ConfigError, match="expected 1-65535"):
        check_address("127.0.0.1", 70000)
    with pytest.raises(ConfigError, match=r"192\.0\.2\.1 --port 8080: Cannot assign"):
        check_address("192.0.2.1", 8080)  # (TEST-NET-1: no host's address)
    with pytest.raises(ConfigError, match="expected an IP address of this host"):
        check_address("robot-lab.example", 8080)


def test_a_live_poll_held_off_inside_a_read_keeps_the_frame_as_it_was() -> None:
    """A loaded host can hold the live view off inside a seqlocked read
    past its budget (TornReadTimeout): the frame stays as it was until the
    next poll, and the thread that sees the session end goes on."""
    import threading

    from redistro.errors import TornReadTimeout
    from redistro.view import Live

    class Torn:
        def read(self, name: str, index: int) -> None:
            raise TornReadTimeout(f"block {name}: no consistent snapshot in 0.005 s")

    class Views:
        def get(self, node: str) -> Torn:
            return Torn()

    live = Live.__new__(Live)
    live.robots, live.views, live.lock = ["r1"], Views(), threading.Lock()  # type: ignore[assignment]
    live.q = {"r1": np.full((1, 7), 0.25)}
    live.poll()  # (no exception)
    assert np.all(live.q["r1"] == 0.25)
    assert not live.lock.locked()

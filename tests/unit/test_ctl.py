"""The operator's commands on the wire (``ssc/ctl.py``): what the SSC
manager's desk takes, what it refuses, and what it answers."""

from __future__ import annotations

import math
import os
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from redistro.localdata.block import Record
from redistro.localdata.layout import OPERATOR, PLAN
from redistro.ssc import ctl
from redistro.ssc.ctl import Checker, Client, Command, Desk, Order, Receiver, Refused, Status

KEY = bytes(range(32))
SID = "20261128T000000-abcdef"


def _signed(
    order: Order, key: bytes = KEY, sid: str = SID, nonce: int = 1, age_ns: int = 0
) -> bytes:
    return ctl.sign(key, sid, order, nonce, time.monotonic_ns() - age_ns)


def test_a_signed_command_is_taken_once() -> None:
    checker = Checker(KEY, SID)
    order = Order(Command.JOG, 1, (0.0, 0.0, 0.005, 0.0, 0.0, 0.01))
    data = _signed(order, nonce=7)
    assert checker.check(data, time.monotonic_ns()) == order
    with pytest.raises(Refused, match="seen before"):
        checker.check(data, time.monotonic_ns())  # (the same datagram again: a replay)


@pytest.mark.parametrize(
    ("data", "why"),
    [
        (lambda: _signed(Order(Command.PAUSE), key=os.urandom(32)), "not signed with the session"),
        (lambda: _signed(Order(Command.PAUSE), sid="20261128T000000-ffffff"), "another session"),
        (lambda: _signed(Order(Command.PAUSE), age_ns=ctl.MAX_AGE_NS + 10**9), "stale"),
        (lambda: _signed(Order(Command.PAUSE))[:-1], "bytes, not"),
        (lambda: _signed(Order(Command.NONE)), "no command"),
        (lambda: _signed(Order(Command.JOG, 0, (math.nan, 0, 0, 0, 0, 0))), "out of range"),
        (lambda: _signed(Order(Command.JOG, 0, (2.0, 0, 0, 0, 0, 0))), "out of range"),
    ],
    ids=["other key", "other session", "stale", "short", "none", "nan step", "huge step"],
)
def test_anything_else_is_refused_with_its_reason(data: Any, why: str) -> None:
    with pytest.raises(Refused, match=why):
        Checker(KEY, SID).check(data(), time.monotonic_ns())


def test_a_tampered_byte_breaks_the_tag() -> None:
    data = bytearray(_signed(Order(Command.PAUSE)))
    data[6] ^= 0x01  # the command byte: a pause made a resume
    with pytest.raises(Refused, match="not signed"):
        Checker(KEY, SID).check(bytes(data), time.monotonic_ns())


class _Block:
    """A stand-in for the operator block's write handle: what was published."""

    def __init__(self) -> None:
        self.rec = Record(OPERATOR)

    def publish(self, data: Any) -> None:
        self.rec.bytes[:] = data


def _desk(tmp_path: Path) -> tuple[Desk, _Block, list[str]]:
    said: list[str] = []
    block = _Block()
    rx = Receiver(tmp_path, KEY, SID)
    desk = Desk(rx, block, ["r1", "r2"], lambda text, warning=False: said.append(text), True)
    return desk, block, said


def _exchange(desk: Desk, client: Client, order: Order, answer: Any = None) -> dict[str, Any]:
    """The client's command, taken by the desk's Idle poll (and answered by
    ``answer`` as the worker would), from another thread."""
    got: dict[str, Any] = {}
    t = threading.Thread(target=lambda: got.update(client.send(order, 5.0)))
    t.start()
    deadline = time.monotonic() + 5.0
    while t.is_alive() and time.monotonic() < deadline:
        desk.idle(cycle=10)
        if desk.owed is not None and answer is not None:
            desk.answer(answer)
        time.sleep(0.001)  # (the desk's cycles, while the client waits for its answer)
    t.join(5.0)
    return got


def test_the_desk_publishes_a_command_and_answers_with_the_workers_effect(tmp_path: Path) -> None:
    desk, block, said = _desk(tmp_path)
    try:
        assert os.stat(tmp_path / ctl.SOCKET).st_mode & 0o077 == 0  # (its socket: 0600)
        plan = Record(PLAN)
        plan["op_seq"], plan["op_command"], plan["op_status"] = 1, 3, int(Status.DONE)
        order = Order(Command.JOG, 1, (0.0, 0.0, 0.005, 0.0, 0.0, 0.0))
        got = _exchange(desk, Client(SID, tmp_path, KEY), order, plan)
        assert got["ok"] is True and got["text"] == "jog: done", got
        assert int(block.rec["seq"]) == 1 and int(block.rec["command"]) == Command.JOG
        assert int(block.rec["robot"]) == 1 and block.rec.array["step"][2] == 0.005
        assert said == ["operator command 1: jog r2 by (0.00, 0.00, 5.00) mm, (0.00, 0.00, 0.00)°"]
        stop = _exchange(desk, Client(SID, tmp_path, KEY), Order(Command.ESTOP))
        assert stop["ok"] is True and desk.act == Command.ESTOP, stop
    finally:
        desk.close()
    assert not (tmp_path / ctl.SOCKET).exists()


def test_the_desk_refuses_counts_and_changes_nothing(tmp_path: Path) -> None:
    desk, block, said = _desk(tmp_path)
    try:
        forged = _exchange(desk, Client(SID, tmp_path, os.urandom(32)), Order(Command.STOP))
        assert forged["ok"] is False and "not signed" in forged["text"], forged
        too_far = Order(Command.JOG, 0, (0.006, 0.0, 0.0, 0.0, 0.0, 0.0))  # (signed, but 6 mm)
        far = _exchange(desk, Client(SID, tmp_path, KEY), too_far)
        assert far["ok"] is False and "at most 5 mm" in far["text"], far
        assert desk.refused == 2 and int(block.rec["refused"]) == 2 and desk.accepted == 0
        assert int(block.rec["seq"]) == 0 and desk.act == Command.NONE
        assert all("refused" in line for line in said), said
    finally:
        desk.close()


@pytest.mark.parametrize(
    ("args", "why"),
    [
        (("pause", "r1", [0, 0, 0], [0, 0, 0]), "takes no robot"),
        (("jog", None, [0, 0, 1], [0, 0, 0]), "name the robot"),
        (("jog", "r1", [0, 0, 0], [0, 0, 0]), "give a step"),
        (("jog", "r1", [3, 4, 0.1], [0, 0, 0]), "at most 5"),
        (("jog", "r1", [0, 0, 0], [2.1, 0, 0]), "at most 2"),
        (("jog", "r1", [math.inf, 0, 0], [0, 0, 0]), "finite"),
    ],
)
def test_the_command_line_is_checked_before_anything_is_sent(args: Any, why: str) -> None:
    from redistro.ctl import order_of
    from redistro.errors import ConfigError

    with pytest.raises(ConfigError, match=why):
        order_of(*args)
    jog = order_of("jog", "r1", [0.0, 0.0, 5.0], [0.0, 0.0, 2.0])
    assert jog.step[2] == 0.005 and abs(jog.step[5] - math.radians(2.0)) < 1e-12

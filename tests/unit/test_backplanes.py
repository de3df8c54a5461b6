"""One contract, every backplane: the shared-memory register bank and CAN
frames (python-can's in-process ``virtual`` bus here; the integration tests
run ``udp_multicast`` between processes)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from redistro.drivers.io.backplane import Backplane, BoardPort
from redistro.drivers.io.registers import BANKS, BoardType
from redistro.errors import IOFault

BOARDS = {16: BoardType.ENCODER, 32: BoardType.DAC, 64: BoardType.FORCE}
TIMEOUT_S = 0.05


@dataclass
class Pair:
    backplane: Backplane
    port: BoardPort
    step: Any  # () -> None: the boards take one sample (and serve requests)
    stop: Any  # () -> None: the boards fall silent
    serve: Any  # () -> None: the boards published again, their step unchanged


@pytest.fixture(params=["shm", "can-virtual"])
def pair(request: pytest.FixtureRequest) -> Iterator[Pair]:
    if request.param == "shm":
        from redistro.drivers.io.bank import RegisterBank
        from redistro.drivers.io.shm import ShmBackplane, ShmPort
        from redistro.ipc.session import Session

        with Session.create() as session:
            bank = RegisterBank.create(session.id, BOARDS, ["r1"], 1000.0, session.manifest)
            port = ShmPort(bank)
            bp = ShmBackplane(session.id, TIMEOUT_S)
            silent = threading.Event()
            steps = [0]

            def step(advance: int = 1) -> None:
                if not silent.is_set():
                    steps[0] += advance
                    for a, t in BOARDS.items():
                        rec = np.zeros((), BANKS[t][0])
                        rec["step"] = steps[0]
                        rec["board_type"] = int(t)
                        port.publish(a, rec)

            step()
            try:
                yield Pair(bp, port, step, silent.set, lambda: step(0))
            finally:
                bp.close()
                bank.close()
                bank.unlink()
    else:
        import can

        from redistro.drivers.io.can import CanBackplane, CanPort

        channel = f"contract-{time.monotonic_ns()}"
        port = CanPort(BOARDS, can.Bus(interface="virtual", channel=channel), key=CAN_KEY)
        bp = CanBackplane(
            "s", TIMEOUT_S, bus=can.Bus(interface="virtual", channel=channel), key=CAN_KEY
        )
        silent = threading.Event()
        done = threading.Event()

        def serve() -> None:
            while not done.is_set():
                if silent.is_set():
                    time.sleep(0.001)
                    continue
                port.service(time.monotonic_ns() + 1_000_000)

        thread = threading.Thread(target=serve, daemon=True)
        thread.start()
        try:
            yield Pair(bp, port, lambda: None, silent.set, lambda: None)
        finally:
            done.set()
            thread.join()
            port.close()
            bp.bus.shutdown()


CAN_KEY = b"the plant's CAN key, 32 bytes..."


def test_inventory(pair: Pair) -> None:
    assert pair.backplane.inventory() == BOARDS


def test_published_inputs_are_read_back(pair: Pair) -> None:
    rec = np.zeros((), BANKS[BoardType.ENCODER][0])
    rec["counter"] = [1, 2, 3, 0xFFFFFF]
    rec["step"] = 99
    pair.port.publish(16, rec)
    got = pair.backplane.read([16, 32])
    assert list(got[16]["counter"]) == [1, 2, 3, 0xFFFFFF]
    assert got[32].dtype == BANKS[BoardType.DAC][0]


def test_written_outputs_reach_the_board(pair: Pair) -> None:
    out = np.zeros((), BANKS[BoardType.DAC][1])
    out["code"][:3] = [100, -200, 2047]
    pair.backplane.write(32, out)
    deadline = time.monotonic() + 2
    while list(pair.port.outputs(32)["code"][:3]) != [100, -200, 2047]:
        assert time.monotonic() < deadline, "the board never saw the write"
        time.sleep(0.001)


def test_unknown_board_is_an_io_fault(pair: Pair) -> None:
    with pytest.raises(IOFault, match="no board at address 5"):
        pair.backplane.read([5])


def test_silent_boards_are_an_io_fault_within_the_timeout(pair: Pair) -> None:
    pair.backplane.read([16])
    pair.stop()
    t0 = time.monotonic()
    with pytest.raises(IOFault):
        while time.monotonic() - t0 < 2:
            pair.backplane.read([16])
    assert time.monotonic() - t0 < TIMEOUT_S * 4 + 0.5


def test_boards_served_without_a_step_are_no_fault(pair: Pair) -> None:
    """In lockstep the plant serves the boards (presets, brakes) without a
    physics step until the group's first tick: their step stays where it
    is for longer than the I/O timeout, and that is no fault."""
    first = int(pair.backplane.read([16])[16]["step"])
    t0 = time.monotonic()
    while time.monotonic() - t0 < TIMEOUT_S * 6:
        pair.serve()
        assert int(pair.backplane.read([16])[16]["step"]) == first
        time.sleep(TIMEOUT_S / 5)  # (the boards' pace: served every 10 ms)


def test_corrupt_frames_are_counted_and_dropped() -> None:
    from redistro.drivers.io.can import FRAME, HEAD, Reassembly, frames_for

    payload = bytes(range(150))
    frames = frames_for(7, payload)
    assert all(len(f) == FRAME for f in frames) and len(frames) == 3
    rx = Reassembly(len(payload))
    bad = bytearray(frames[1])
    bad[HEAD.size + 3] ^= 0xFF  # one flipped byte
    assert rx.add(frames[0]) is None
    assert rx.add(bytes(bad)) is None
    assert rx.bad == 1
    assert rx.add(b"\x01\x02") is None and rx.bad == 2  # too short
    assert rx.add(frames[1]) is None
    assert rx.add(frames[2]) == payload
    # a stale reply (another sequence) is not taken as the answer
    assert rx.add(frames_for(6, payload)[0], want_seq=8) is None


def test_a_can_write_without_the_plants_key_never_reaches_a_register() -> None:
    import can

    from redistro.drivers.io.can import CanBackplane, CanPort

    channel = f"forged-{time.monotonic_ns()}"
    port = CanPort(BOARDS, can.Bus(interface="virtual", channel=channel), key=CAN_KEY)
    good = CanBackplane(
        "s", TIMEOUT_S, bus=can.Bus(interface="virtual", channel=channel), key=CAN_KEY
    )
    bad = CanBackplane(
        "s", TIMEOUT_S, bus=can.Bus(interface="virtual", channel=channel), key=b"x" * 32
    )
    sniffer = can.Bus(interface="virtual", channel=channel)
    try:
        out = np.zeros((), BANKS[BoardType.DAC][1])
        out["code"][:3] = [100, -200, 2047]
        good.write(32, out)
        frames = []  # what a listener on the bus captured: the genuine write
        while (msg := sniffer.recv(timeout=0.2)) is not None:
            frames.append(msg)
        port.service(time.monotonic_ns() + 50_000_000)
        assert list(port.outputs(32)["code"][:3]) == [100, -200, 2047]
        forged = np.zeros((), BANKS[BoardType.DAC][1])
        forged["code"][:3] = [2047, 2047, 2047]
        bad.write(32, forged)  # DAC codes from someone without the key
        port.service(time.monotonic_ns() + 50_000_000)
        assert list(port.outputs(32)["code"][:3]) == [100, -200, 2047]
        assert port.forged == 1
        out["code"][:3] = [0, 0, 0]
        good.write(32, out)
        port.service(time.monotonic_ns() + 50_000_000)
        assert list(port.outputs(32)["code"][:3]) == [0, 0, 0]
        for msg in frames:  # the captured genuine write, replayed: an old sequence
            sniffer.send(msg)
        port.service(time.monotonic_ns() + 50_000_000)
        assert list(port.outputs(32)["code"][:3]) == [0, 0, 0]
        assert port.forged == 2
    finally:
        for bus in (port.bus, good.bus, bad.bus, sniffer):
            bus.shutdown()


def test_a_captured_can_write_is_refused_after_the_sequence_wrapped() -> None:
    """A brake-release write captured early, replayed after the driver's
    16-bit sequence would have wrapped: refused and counted; the genuine
    writer is never locked out."""
    import can

    from redistro.drivers.io.can import CanBackplane, CanPort

    channel = f"wrap-{time.monotonic_ns()}"
    port = CanPort(BOARDS, can.Bus(interface="virtual", channel=channel), key=CAN_KEY)
    good = CanBackplane(
        "s", TIMEOUT_S, bus=can.Bus(interface="virtual", channel=channel), key=CAN_KEY
    )
    sniffer = can.Bus(interface="virtual", channel=channel)

    def write(codes: list[int]) -> None:
        out = np.zeros((), BANKS[BoardType.DAC][1])
        out["code"][:3] = codes
        good.write(32, out)
        port.service(time.monotonic_ns() + 50_000_000)

    try:
        write([2047, 2047, 2047])  # the write an attacker captures
        captured = []
        while (msg := sniffer.recv(timeout=0.2)) is not None:
            captured.append(msg)
        write([0, 0, 0])
        # 70 000 writes later (more than the old 16-bit window): the driver's
        # sequence as it would stand then
        good._seq += 70_000
        write([1, 2, 3])
        for _ in range(3):
            for msg in captured:
                sniffer.send(msg)
            port.service(time.monotonic_ns() + 50_000_000)
            assert list(port.outputs(32)["code"][:3]) == [1, 2, 3]
        assert port.forged == 3
        write([4, 5, 6])  # the genuine writer goes on
        assert list(port.outputs(32)["code"][:3]) == [4, 5, 6]
        assert port.forged == 3
        # a write from an earlier driver beside the same plant: refused too
        old = CanBackplane(
            "s", TIMEOUT_S, bus=can.Bus(interface="virtual", channel=channel), key=CAN_KEY
        )
        try:
            out = np.zeros((), BANKS[BoardType.DAC][1])
            out["code"][:3] = [7, 7, 7]
            old.next_seq = lambda: 5  # type: ignore[method-assign]  # an earlier run's number
            old.write(32, out)
            port.service(time.monotonic_ns() + 50_000_000)
            assert list(port.outputs(32)["code"][:3]) == [4, 5, 6] and port.forged == 4
        finally:
            old.bus.shutdown()
    finally:
        for bus in (port.bus, good.bus, sniffer):
            bus.shutdown()


def test_a_forged_or_replayed_can_reply_is_not_taken() -> None:
    """An old reply sent again as the answer to a new request (its header
    renumbered to match): the driver refuses it and takes the board's own."""
    import can

    from redistro.drivers.io.can import HEAD, READ, REPLY, CanBackplane, CanPort, frames_for

    channel = f"reply-{time.monotonic_ns()}"
    port = CanPort(BOARDS, can.Bus(interface="virtual", channel=channel), key=CAN_KEY)
    drv = CanBackplane(
        "s", TIMEOUT_S * 10, bus=can.Bus(interface="virtual", channel=channel), key=CAN_KEY
    )
    sniffer = can.Bus(interface="virtual", channel=channel)
    rec = np.zeros((), BANKS[BoardType.ENCODER][0])
    try:
        drv._types = dict(BOARDS)  # (the inventory, asked before)
        rec["counter"] = [111, 0, 0, 0]
        port.publish(16, rec)
        got: dict[str, Any] = {}
        t = threading.Thread(target=lambda: got.update(first=drv.read([16])[16]["counter"][0]))
        t.start()
        old_reply = []
        deadline = time.monotonic() + 2
        while t.is_alive() and time.monotonic() < deadline:
            port.service(time.monotonic_ns() + 5_000_000)
            while (msg := sniffer.recv(timeout=0)) is not None:
                if msg.arbitration_id == REPLY | 16:
                    old_reply.append(bytes(msg.data))
        t.join()
        assert got["first"] == 111 and old_reply
        rec["counter"] = [222, 0, 0, 0]
        port.publish(16, rec)
        t = threading.Thread(target=lambda: got.update(second=drv.read([16])[16]["counter"][0]))
        t.start()
        request = None
        while request is None:
            msg = sniffer.recv(timeout=1.0)
            assert msg is not None, "no request seen"
            if msg.arbitration_id == READ | 16:
                request = bytes(msg.data)
        seq16 = HEAD.unpack_from(request)[0]
        whole = b"".join(frame[HEAD.size :] for frame in old_reply)
        replay = frames_for(seq16, whole[: drv._rx[16].size])
        for frame in replay:  # the old reply, renumbered, before the board answers
            sniffer.send(can.Message(arbitration_id=REPLY | 16, data=frame, is_fd=True))
        deadline = time.monotonic() + 2
        while t.is_alive() and time.monotonic() < deadline:
            port.service(time.monotonic_ns() + 5_000_000)
        t.join()
        assert got["second"] == 222
        assert drv.bad_frames == 1
    finally:
        for bus in (port.bus, drv.bus, sniffer):
            bus.shutdown()


def test_a_node_started_beside_the_plant_sees_it_come_up_or_end() -> None:
    """PlantWatch: no bank yet or STARTING is not up; RUNNING is; a plant that
    ended (STOPPED or FAILED) before that ends the waiting node."""
    from redistro.drivers.io.bank import PlantState, PlantWatch, RegisterBank
    from redistro.errors import NodeFault
    from redistro.ipc.session import Session

    with Session.create() as session:
        watch = PlantWatch(session.id)
        assert not watch.running()  # (no bank yet)
        bank = RegisterBank.create(session.id, BOARDS, ["r1"], 1000.0, session.manifest)
        try:
            assert not watch.running()  # STARTING
            for state, up in ((PlantState.RUNNING, True), (PlantState.FAILED, None)):
                with bank.status.write() as d:
                    d["state"] = state
                if up:
                    assert watch.running()
                else:
                    with pytest.raises(NodeFault, match="the plant ended before"):
                        watch.running()
        finally:
            watch.close()
            bank.close()
            bank.unlink()


def test_a_bank_being_made_is_not_attached() -> None:
    """An attacher that comes while the plant still writes the board table
    (its layout hash, written last, still 0) gets a LayoutError (it tries
    again), not a board of type NONE."""
    from redistro.drivers.io.bank import RegisterBank
    from redistro.errors import LayoutError
    from redistro.ipc.session import Session

    with Session.create() as session:
        bank = RegisterBank.create(session.id, BOARDS, ["r1"], 1000.0, session.manifest)
        try:
            made = int(bank.view["header"]["layout_hash"])
            bank.view["header"]["layout_hash"] = 0
            bank.view["table"]["type"][0] = 0  # (half written)
            with pytest.raises(LayoutError, match="not made yet"):
                RegisterBank.attach(session.id)
            bank.view["table"]["type"][0] = int(bank.types[0])
            bank.view["header"]["layout_hash"] = made
            RegisterBank.attach(session.id).close()
        finally:
            bank.close()
            bank.unlink()


def test_the_chassis_bus_takes_a_larger_buffer() -> None:
    """Every socket on the udp_multicast bus takes every frame, its own
    included: the chassis' asks for ``PLANT_RCVBUF`` (a burst past the
    default buffer was lost, a brake's write among it); a driver's keeps
    the default."""
    import socket

    from redistro.drivers.io.can import PLANT_RCVBUF, open_bus
    from redistro.ipc.names import new_session_id

    sid = new_session_id()
    plant = open_bus("udp_multicast", "", 0, sid, True, PLANT_RCVBUF)
    driver = open_bus("udp_multicast", "", 0, sid, True)
    try:

        def size(bus: Any) -> int:
            return int(bus._multicast._socket.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))

        with open("/proc/sys/net/core/rmem_max") as f:  # (the kernel's cap, doubled)
            cap = 2 * int(f.read())
        assert size(plant) == min(2 * PLANT_RCVBUF, cap) > size(driver)
    finally:
        plant.shutdown()
        driver.shutdown()

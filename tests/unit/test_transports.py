"""Contract tests over every DDM transport (real sockets, real SysV memory
cards) and the in-process fake beside them (``ddm.loopback``)."""

from __future__ import annotations

import contextlib
import os
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from redistro.ddm.record import KIND_COMMAND, KIND_FEEDBACK, decode, encode
from redistro.ddm.transport import Transport, transport_class
from redistro.errors import TransportError
from redistro.ipc.names import new_session_id
from redistro.localdata.layout import COMMAND, FEEDBACK
from tests.helpers import wait_for

Pair = tuple[Transport, Transport]  # (SSC side, ESC side)

# both ends in this process: zenoh's threads hand the records and the
# peers' liveliness over, and beside the other workers' lockstep sessions
# the token's loss once came before the two records sent ahead of it
pytestmark = pytest.mark.usefixtures("above_the_other_workers")


def _socket_pair() -> Pair:
    cls = transport_class("socket")
    esc = cls(listen=("127.0.0.1", 0))
    ssc = cls(peers={0: esc.address})
    deadline = time.monotonic() + 5
    while not (ssc.connected() and esc.connected()):  # type: ignore[attr-defined]
        assert time.monotonic() < deadline, "no connection within 5 s"
        time.sleep(0.001)  # polling a non-blocking connect, to a deadline
    return ssc, esc


def _reflective_pair() -> Pair:
    cls = transport_class("reflective")
    sid = new_session_id()
    return cls(sid, "ssc"), cls(sid, "esc.r1")


def _loopback_pair() -> Pair:
    from redistro.ddm.loopback import Loopback

    return Loopback.pair()


def _free_port() -> int:
    probe = socket.socket()
    probe.bind(("127.0.0.1", 0))
    port = int(probe.getsockname()[1])
    probe.close()
    return port


def _tls_sets(folder: Path, who: str, ca: str = "ca") -> list[str]:
    """--set lines for TLS: the group's CA, ``who``'s certificate and key
    (made by a test CA in ``folder``/``ca``)."""
    from tests.helpers import make_test_ca

    made = folder / ca
    if not (made / "ca.pem").exists():
        make_test_ca(made)
    return [
        f"ddm.zenoh.tls.ca_file={made / 'ca.pem'}",
        f"ddm.zenoh.tls.cert_file={made / (who + '.pem')}",
        f"ddm.zenoh.tls.key_file={made / (who + '.key')}",
    ]


def _zenoh_pair(
    robots: tuple[str, ...] = ("r1",),
    answer: Callable[[bytes], int] | None = None,
    tls: bool = False,
) -> Pair:
    """The SSC's session and r1's ESC's, authenticated, under access rules
    (``tls``: over mutual TLS, each node with a certificate of a test CA)."""
    import shutil
    import tempfile

    from redistro.config import load_config
    from redistro.ddm import zenoh_transport as zt

    folder = tempfile.mkdtemp()
    users = f"{folder}/users"
    group = new_session_id()
    zt.new_users_file(users, group, ["ssc", *(f"esc.{r}" for r in robots)])
    port = _free_port()
    gids = {r: i for i, r in enumerate(robots)}

    def side(node: str, kind: str, mine: list[str]) -> zt.ZenohTransport:
        sets = [f"ddm.zenoh.port={port}"]
        if tls:
            sets += _tls_sets(Path(folder), "ssc" if kind == "ssc" else "esc")
        settings = zt.session_config(load_config(None, sets), group, node, kind, mine, users)
        return zt.ZenohTransport(
            settings, group=group, node=node, kind=kind, robots=mine, gids=gids
        )

    ssc = side("ssc", "ssc", list(robots))
    esc = side(f"esc.{robots[0]}", "esc", [robots[0]])
    if answer is not None:
        assert esc.accelerator.answer_with(answer)
    try:
        # the sessions open at their first look (as a ddm's at its first
        # receive) and read the users file then: it stays until they met
        deadline = time.monotonic() + 10
        while not all([ssc.connected(), esc.connected()]):  # both look, every turn
            if time.monotonic() > deadline:
                why = ssc.why_not or esc.why_not
                ssc.close()
                esc.close()
                raise AssertionError(f"the zenoh sessions did not meet within 10 s: {why}")
            time.sleep(0.01)  # polling the liveliness callbacks, to a deadline
    finally:
        shutil.rmtree(folder)
    return ssc, esc


PAIRS: dict[str, Callable[[], Pair]] = {
    "socket": _socket_pair,
    "reflective": _reflective_pair,
    "loopback": _loopback_pair,
    "zenoh": _zenoh_pair,
    "zenoh-tls": lambda: _zenoh_pair(tls=True),
}


@pytest.fixture(params=list(PAIRS))
def pair(request: pytest.FixtureRequest) -> Iterator[Pair]:
    make = PAIRS[request.param]
    a, b = make()
    try:
        yield a, b
    finally:
        a.close()
        b.close()


def _command(seq: int) -> bytes:
    c = np.zeros((), COMMAND)
    c["tau_nm"] = seq
    return encode(KIND_COMMAND, 0, "ssc", seq, 1000 + seq, c)


def _feedback(seq: int) -> bytes:
    f = np.zeros((), FEEDBACK)
    f["q_rad"] = seq / 10
    return encode(KIND_FEEDBACK, 0, "esc.r1", seq, 1000 + seq, f)


def _collect(t: Transport, want: int, timeout_s: float = 2.0) -> list[bytes]:
    got: list[bytes] = []
    deadline = time.monotonic() + timeout_s
    while len(got) < want and time.monotonic() < deadline:
        got += t.receive()
        time.sleep(0.001)  # polling a non-blocking receive, to a deadline
    return got


def test_send_receive_reply(pair: Pair) -> None:
    """A step's sends go out by its flush at the latest (a transport may
    hold them until then: reflective memory sends them together)."""
    ssc, esc = pair
    ssc.send(_command(1), 0)
    ssc.links.flush()
    got = _collect(esc, 1)
    assert [decode(r).payload["tau_nm"][0] for r in got] == [1.0]
    esc.send(_feedback(1), 0)
    esc.links.flush()
    got = _collect(ssc, 1)
    assert [decode(r).source for r in got] == ["esc.r1"]


def test_nothing_sent_nothing_received(pair: Pair) -> None:
    ssc, esc = pair
    assert ssc.receive() == [] and esc.receive() == []


def test_a_stream_of_records_arrives_in_order(pair: Pair) -> None:
    """100 records, ten a step (each step flushed and taken before the
    next, as a ddm does), arrive in order, none twice; a stream takes every
    one. Zenoh's publishers drop rather than block when the link is
    congested (a loaded host lost 3-4 of 100, 96 of a burst of 100): what
    it delivers is in order, and most of it arrives."""
    ssc, esc = pair
    got: list[int] = []
    for seq in range(1, 101):
        ssc.send(_command(seq), 0)
        if seq % 10 == 0:
            ssc.links.flush()
            if not esc.latest_only:
                got += _until(esc, seq)
    if esc.latest_only:  # a memory: each receive hands over a slot's latest record
        deadline = time.monotonic() + 2.0
        while (not got or got[-1] != 100) and time.monotonic() < deadline:
            got += [decode(r).seq for r in esc.receive()]
            time.sleep(0.001)  # polling a non-blocking receive, to a deadline
        assert got == sorted(set(got)) and got[-1] == 100, got[-5:]
        return
    if esc.drops_when_congested:
        assert got == sorted(set(got)) and len(got) >= 50, got
        return
    assert got == list(range(1, 101)), got


def _until(t: Transport, last: int, timeout_s: float = 2.0) -> list[int]:
    """The sequence numbers received until ``last`` is among them (or the deadline)."""
    got: list[int] = []
    deadline = time.monotonic() + timeout_s
    while last not in got and time.monotonic() < deadline:
        got += [decode(r).seq for r in t.receive()]
        time.sleep(0.001)  # polling a non-blocking receive, to a deadline
    return got


def test_reflective_cards_hold_the_latest_record() -> None:
    ssc, esc = _reflective_pair()
    try:
        assert esc.read_card(KIND_COMMAND, 0) is None  # type: ignore[attr-defined]
        for seq in (1, 2, 3):
            ssc.send(_command(seq), 0)
        assert ssc.read_card(KIND_COMMAND, 0) == _command(3)  # type: ignore[attr-defined]
        ssc.links.flush()  # (the three in one datagram: one receive takes them)
        assert _collect(esc, 1) == [_command(3)]  # the latest only ...
        assert esc.read_card(KIND_COMMAND, 0) == _command(3)  # type: ignore[attr-defined]
        assert esc.superseded == 2  # type: ignore[attr-defined]  # ... the others counted
    finally:
        ssc.close()
        esc.close()


def test_reflective_supersession_is_counted_per_slot() -> None:
    """Another robot's commands overwritten on the card are not this robot's
    (an ESC's card holds every robot's commands)."""
    ssc, esc = _reflective_pair()
    try:
        for seq in (1, 2):
            ssc.send(_command(seq), 0)
        other = np.zeros((), COMMAND)
        for seq in (1, 2, 3):
            ssc.send(encode(KIND_COMMAND, 1, "ssc", seq, 1000 + seq, other), 1)
        ssc.links.flush()  # two datagrams, both queued on loopback before a receive
        got = sorted((r[7], decode(r).seq) for r in _collect(esc, 2))
        assert got == [(0, 2), (1, 3)], got
        assert esc.superseded_of(KIND_COMMAND, 0) == 1  # type: ignore[attr-defined]
        assert esc.superseded_of(KIND_COMMAND, 1) == 2  # type: ignore[attr-defined]
        assert esc.superseded == 3  # type: ignore[attr-defined]
    finally:
        ssc.close()
        esc.close()


def test_a_reflective_step_goes_out_as_one_datagram_and_never_comes_back() -> None:
    """The records a node writes in one step leave together (one datagram,
    one wake-up of each other node, up to BATCH records); its own writes do
    not come back to wake it; a datagram of no whole records is handed on
    (the ddm counts it malformed)."""
    import select

    from redistro.ddm.record import SIZE
    from redistro.ddm.reflective import BATCH

    ssc, esc = _reflective_pair()
    try:
        ep = select.epoll()
        ep.register(esc.fds()[0], select.EPOLLIN)
        ssc.send(_command(1), 0)
        ssc.send(_command(2), 1)
        assert not ep.poll(0.05)  # held until the step's flush
        ssc.links.flush()
        assert ep.poll(2.0)
        datagram = os.read(esc.fds()[0], 8 * SIZE)  # (what receive would take)
        assert len(datagram) == 2 * SIZE  # both robots' commands, one datagram
        assert ssc.receive() == []  # its own writes: not back
        for seq in range(3, 3 + BATCH + 1):
            ssc.send(_command(seq), 0)
        ssc.links.flush()
        assert ep.poll(2.0)
        datagram = os.read(esc.fds()[0], 8 * SIZE)
        assert len(datagram) == BATCH * SIZE  # at most BATCH records a datagram
        got = _collect(esc, 1)  # the rest; the card hands over the latest
        assert [decode(r).seq for r in got] == [3 + BATCH]
        probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        probe.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
        probe.sendto(b"not a record", esc.group)  # type: ignore[attr-defined]
        probe.close()
        assert _collect(esc, 1) == [b"not a record"]
    finally:
        ssc.close()
        esc.close()


@pytest.mark.parametrize("lockstep", [True, False])
def test_in_lockstep_a_reflective_write_the_host_lost_goes_out_again(lockstep: bool) -> None:
    """The host's UDP may lose a datagram (a full socket buffer). In real
    time the next cycle's write takes its place; in lockstep the tick waits
    for it, so a node that wrote nothing for ``RESEND_S`` writes its slots'
    latest records again (and its other writes are not held back)."""
    import select

    from redistro.ddm.record import SIZE
    from redistro.ddm.reflective import RESEND_S

    cls = transport_class("reflective")
    sid = new_session_id()
    ssc = cls(sid, "ssc", resend_after_s=RESEND_S if lockstep else 0.0)  # type: ignore[call-arg]
    esc = cls(sid, "esc.r1")
    try:
        ep = select.epoll()
        ep.register(esc.fds()[0], select.EPOLLIN)
        ssc.send(_command(1), 0)
        ssc.links.flush()
        assert ep.poll(2.0)
        assert len(os.read(esc.fds()[0], 8 * SIZE)) == SIZE  # lost: taken unread
        start = time.monotonic()
        got: list[bytes] = []
        while not got and time.monotonic() < start + 0.5:
            assert ssc.receive() == []  # (its step: nothing came, it writes again)
            got = esc.receive()
            time.sleep(0.005)  # a ddm's steps, a period apart
        if not lockstep:
            assert got == [] and ssc.resent == 0  # type: ignore[attr-defined]
            return
        assert [decode(r).seq for r in got] == [1], got
        assert time.monotonic() - start >= RESEND_S
        assert ssc.resent == 1  # type: ignore[attr-defined]
        # the ESC has it now: the next resend is no news to its card
        deadline = time.monotonic() + 2.0
        while ssc.resent < 2 and time.monotonic() < deadline:  # type: ignore[attr-defined]
            ssc.receive()
            time.sleep(0.005)
        assert ep.poll(2.0)  # (the resend came in)
        assert esc.receive() == []
        ssc.send(_command(2), 0)  # a new write goes out at once, as ever
        ssc.links.flush()
        assert [decode(r).seq for r in _collect(esc, 1)] == [2]
    finally:
        ssc.close()
        esc.close()


@pytest.mark.parametrize("kind", ["socket", "loopback", "zenoh"])
def test_a_closed_end_is_a_lost_link_once_its_records_are_in(kind: str) -> None:
    """Over the transports with links: what the peer sent before it closed
    arrives, then the loss (a reflective network has no links to lose). The
    records are this run's (the ddm says so: ``authenticated``); a link lost
    before any came would be made again."""
    ssc, esc = PAIRS[kind]()
    try:
        esc.send(_feedback(1), 0)
        esc.send(_feedback(2), 0)
        esc.close()
        got: list[bytes] = []
        with pytest.raises(TransportError, match="closed by the peer"):
            deadline = time.monotonic() + 2
            while time.monotonic() < deadline:
                got += ssc.receive()
                if got:
                    ssc.links.authenticated(0)
                time.sleep(0.001)  # polling a non-blocking receive, to a deadline
        assert [decode(r).seq for r in got] == [1, 2]
    finally:
        ssc.close()
        esc.close()


def test_a_zenoh_token_loss_that_overtakes_records_waits_for_them(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The records and the token's loss come in two of zenoh-python's
    threads: a loss taken first (delivered here before the records are
    sent) leaves the link up for its grace, the records are taken, and then
    the link is lost."""
    import types

    import zenoh

    from redistro.ddm import zenoh_transport as zt

    monkeypatch.setattr(zt, "LOSS_GRACE_S", 30.0)
    ssc, esc = _zenoh_pair()
    assert isinstance(ssc, zt.ZenohTransport)
    try:
        key = zt.alive_key(ssc.group, "esc.r1")
        ssc._liveliness(types.SimpleNamespace(key_expr=key, kind=zenoh.SampleKind.DELETE))
        assert ssc.receive() == []  # within its grace: no loss yet
        esc.send(_feedback(1), 0)
        esc.send(_feedback(2), 0)
        assert [decode(r).seq for r in _collect(ssc, 2)] == [1, 2]
        monkeypatch.setattr(zt, "LOSS_GRACE_S", 0.0)  # (its grace over)
        with pytest.raises(TransportError, match="closed by the peer"):
            ssc.receive()
    finally:
        ssc.close()
        esc.close()


def test_the_loopback_fds_wake_a_waiting_ddm() -> None:
    import select

    from redistro.ddm.loopback import Loopback

    ssc, escs = Loopback.group([0, 1])
    try:
        (fd,) = escs[1].fds()
        assert select.select([fd], [], [], 0)[0] == []
        ssc.send(_command(1), 1)
        assert select.select([fd], [], [], 0)[0] == [fd]
        assert [decode(r).seq for r in escs[1].receive()] == [1]
        assert escs[0].receive() == [] and escs[1].replies and not ssc.replies
        escs[0].close()  # one robot's link lost: the other's goes on
        ssc.send(_command(2), 0)  # dropped
        assert ssc.links.lost_links() == {0: "closed by the peer"} and ssc.receive() == []
        ssc.send(_command(3), 1)
        assert [decode(r).seq for r in escs[1].receive()] == [3]
    finally:
        ssc.close()
        for e in escs.values():
            e.close()


def test_socket_link_loss_is_reported() -> None:
    ssc, esc = _socket_pair()
    try:
        ssc.send(_command(1), 0)
        _collect(esc, 1)
        ssc.close()
        with pytest.raises(TransportError, match="lost"):
            deadline = time.monotonic() + 2
            while time.monotonic() < deadline:
                esc.receive()
                time.sleep(0.001)
    finally:
        esc.close()


def test_one_lost_esc_link_leaves_the_other_robot_exchanging() -> None:
    cls = transport_class("socket")
    esc1, esc2 = cls(listen=("127.0.0.1", 0)), cls(listen=("127.0.0.1", 0))
    ssc = cls(peers={0: esc1.address, 1: esc2.address})
    try:
        deadline = time.monotonic() + 5
        while not (ssc.connected() and esc1.connected() and esc2.connected()):  # type: ignore[attr-defined]
            assert time.monotonic() < deadline
            time.sleep(0.001)  # polling a non-blocking connect, to a deadline
        ssc.links.authenticated(0)  # (both links brought records of this run)
        ssc.links.authenticated(1)
        esc1.close()  # r1's node ends
        deadline = time.monotonic() + 2
        while 0 not in ssc.links.lost_links():
            assert time.monotonic() < deadline, "the lost link was not noticed"
            ssc.receive()  # no exception: r2's link is alive
            time.sleep(0.001)  # polling a non-blocking receive, to a deadline
        assert "closed by the peer" in ssc.links.lost_links()[0]
        ssc.send(_command(7), 1)  # the group's e-stop still reaches r2
        ssc.send(_command(8), 0)  # dropped: r1's link is gone
        assert [decode(r).seq for r in _collect(esc2, 1)] == [7]
        esc2.close()
        with pytest.raises(TransportError, match="lost: closed by the peer"):
            deadline = time.monotonic() + 2
            while time.monotonic() < deadline:
                ssc.receive()
                time.sleep(0.001)  # polling a non-blocking receive, to a deadline
    finally:
        ssc.close()
        esc2.close()


def test_socket_connect_to_nobody_fails_clearly() -> None:
    cls = transport_class("socket")
    t = cls(peers={0: ("127.0.0.1", 9)}, connect_timeout_s=0.2)
    try:
        t.send(_command(1), 0)  # not connected: dropped and counted, no error
        assert t.dropped_unconnected == 1  # type: ignore[attr-defined]
        with pytest.raises(TransportError, match=r"cannot connect to 127\.0\.0\.1:9: .*refused"):
            deadline = time.monotonic() + 2
            while time.monotonic() < deadline:
                t.receive()
                time.sleep(0.001)  # polling a non-blocking connect, to a deadline
    finally:
        t.close()


def test_socket_connects_to_a_peer_that_starts_later() -> None:
    cls = transport_class("socket")
    probe = socket.socket()
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()  # a free port, nobody listening yet
    ssc = cls(peers={0: ("127.0.0.1", port)}, connect_timeout_s=5)
    esc = None
    try:
        assert not ssc.connected()  # type: ignore[attr-defined]
        esc = cls(listen=("127.0.0.1", port))
        deadline = time.monotonic() + 5
        while not ssc.connected():  # type: ignore[attr-defined]
            assert time.monotonic() < deadline
            time.sleep(0.001)  # polling a non-blocking connect, to a deadline
        ssc.send(_command(1), 0)
        assert len(_collect(esc, 1)) == 1
    finally:
        ssc.close()
        if esc is not None:
            esc.close()


KEY = b"k" * 32


def _hello(seq: int = 1) -> bytes:
    from redistro.ddm.record import HELLO, KIND_HELLO

    return encode(KIND_HELLO, 0, "ssc", seq, 1000 + seq, np.zeros((), HELLO), key=KEY)


def _admit(esc: Transport, records: list[bytes]) -> int:
    """What the ESC's ddm does with records: check the key, pin the peer on a
    good one, drop the connection on a forged one. Returns the good ones."""
    from redistro.ddm.record import check
    from redistro.errors import WireError

    good = 0
    for r in records:
        try:
            check(r, KEY)
        except WireError:
            esc.links.drop_unauthenticated()
            continue
        esc.links.authenticated()
        good += 1
    return good


def _listening_with_peer() -> tuple[Transport, Transport]:
    cls = transport_class("socket")
    esc = cls(listen=("127.0.0.1", 0), authenticate=True)
    ssc = cls(peers={0: esc.address}, hello=_hello())
    deadline = time.monotonic() + 5
    got: list[bytes] = []
    while not got:
        assert time.monotonic() < deadline, "no hello within 5 s"
        ssc.connected()  # type: ignore[attr-defined]
        got = esc.receive()
        time.sleep(0.001)  # polling non-blocking sockets, to a deadline
    assert _admit(esc, got) == 1
    return ssc, esc


def test_a_new_connection_never_displaces_the_authenticated_peer() -> None:
    ssc, esc = _listening_with_peer()
    intruder = socket.create_connection(esc.address)  # type: ignore[attr-defined]
    try:
        intruder.settimeout(2.0)
        for _ in range(64):  # a pinned link looks for newcomers every 64 receives
            esc.receive()
        assert intruder.recv(16) == b""  # refused: closed
        assert esc.links.refused() == 1
        ssc.send(encode(KIND_COMMAND, 0, "ssc", 2, 1002, np.zeros((), COMMAND), key=KEY), 0)
        assert _admit(esc, _collect(esc, 1)) == 1  # the SSC's link goes on
    finally:
        intruder.close()
        ssc.close()
        esc.close()


def test_an_unauthenticated_connection_gives_way_and_forged_records_drop_it() -> None:
    cls = transport_class("socket")
    esc = cls(listen=("127.0.0.1", 0), authenticate=True)
    squatter = socket.create_connection(esc.address)
    ssc = None
    try:
        squatter.settimeout(2.0)
        deadline = time.monotonic() + 5
        while esc.peer is None:  # type: ignore[attr-defined]
            assert time.monotonic() < deadline
            esc.receive()
            time.sleep(0.001)  # polling a non-blocking accept, to a deadline
        # a forged record on the squatter's connection: it is dropped
        forged = encode(KIND_COMMAND, 0, "ssc", 1, 1001, np.zeros((), COMMAND), key=b"x" * 32)
        squatter.sendall(forged)
        assert _admit(esc, _collect(esc, 1)) == 0
        assert squatter.recv(16) == b""
        # the real SSC then connects, proves the key and is pinned
        ssc = cls(peers={0: esc.address}, hello=_hello())
        got: list[bytes] = []
        while not got:
            assert time.monotonic() < deadline, "no hello"
            ssc.connected()  # type: ignore[attr-defined]
            got = esc.receive()
            time.sleep(0.001)  # polling non-blocking sockets, to a deadline
        assert _admit(esc, got) == 1
    finally:
        squatter.close()
        if ssc is not None:
            ssc.close()
        esc.close()


def test_a_flooding_peer_does_not_hold_a_receive() -> None:
    from redistro.ddm.sockets import MAX_RECORDS

    ssc, esc = _listening_with_peer()
    try:
        rec = encode(KIND_COMMAND, 0, "ssc", 5, 1005, np.zeros((), COMMAND), key=KEY)
        for _ in range(4 * MAX_RECORDS):
            ssc.send(rec, 0)
        deadline = time.monotonic() + 5
        sizes = []
        while sum(sizes) < 4 * MAX_RECORDS:
            assert time.monotonic() < deadline, sizes
            t0 = time.monotonic()
            n = len(esc.receive())
            assert time.monotonic() - t0 < 0.5
            if n:
                sizes.append(n)
            time.sleep(0.001)  # polling a non-blocking receive, to a deadline
        assert max(sizes) <= MAX_RECORDS and len(sizes) >= 4, sizes
    finally:
        ssc.close()
        esc.close()


def test_a_zenoh_node_with_a_wrong_password_is_refused_and_says_so() -> None:
    """An ESC's session whose password is not the group's never gets in: its
    ddm's transport reports it cannot reach the group's door, and the SSC's
    side never sees its liveliness token."""
    import shutil
    import tempfile

    from redistro.config import load_config
    from redistro.ddm import zenoh_transport as zt

    folder = tempfile.mkdtemp()
    try:
        users = f"{folder}/users"
        group = new_session_id()
        zt.new_users_file(users, group, ["ssc", "esc.r1"])
        wrong = f"{folder}/wrong"
        text = Path(users).read_text().replace(f"esc.r1@{group}:", f"esc.r1@{group}:x")
        fd = os.open(wrong, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        os.write(fd, text.encode())
        os.close(fd)
        cfg = load_config(None, [f"ddm.zenoh.port={_free_port()}"])
        ssc_settings = zt.session_config(cfg, group, "ssc", "ssc", ["r1"], users)
        esc_settings = zt.session_config(cfg, group, "esc.r1", "esc", ["r1"], wrong)
        gids = {"r1": 0}
        ssc = zt.ZenohTransport(
            ssc_settings, group=group, node="ssc", kind="ssc", robots=["r1"], gids=gids
        )
        esc = zt.ZenohTransport(
            esc_settings,
            group=group,
            node="esc.r1",
            kind="esc",
            robots=["r1"],
            gids=gids,
            connect_timeout_s=1.5,
        )
        try:
            with pytest.raises(
                TransportError, match=r"cannot reach the group's door within 1\.5 s"
            ):
                deadline = time.monotonic() + 5
                while time.monotonic() < deadline:
                    esc.receive()
                    time.sleep(0.01)  # polling a non-blocking receive, to a deadline
            assert not ssc.connected() and ssc.receive() == []
        finally:
            ssc.close()
            esc.close()
    finally:
        shutil.rmtree(folder)


@pytest.mark.parametrize("wrong", ["another CA's certificate", "no certificate"])
def test_a_zenoh_node_with_a_wrong_certificate_is_refused(wrong: str) -> None:
    """Over mutual TLS, an ESC whose certificate the group's CA did not sign
    (or that has none) never gets in: the SSC's side refuses the
    connection, the ESC's ddm reports it cannot reach the group's door."""
    import shutil
    import tempfile

    from redistro.config import load_config
    from redistro.ddm import zenoh_transport as zt

    folder = Path(tempfile.mkdtemp())
    try:
        users = str(folder / "users")
        group = new_session_id()
        zt.new_users_file(users, group, ["ssc", "esc.r1"])
        port = f"ddm.zenoh.port={_free_port()}"
        ssc_cfg = load_config(None, [port, *_tls_sets(folder, "ssc")])
        esc_sets = [port, *_tls_sets(folder, "esc", ca="other")]
        esc_sets[1] = f"ddm.zenoh.tls.ca_file={folder / 'ca' / 'ca.pem'}"  # it trusts the SSC
        esc_cfg = load_config(None, esc_sets)
        gids = {"r1": 0}
        ssc = zt.ZenohTransport(
            zt.session_config(ssc_cfg, group, "ssc", "ssc", ["r1"], users),
            group=group, node="ssc", kind="ssc", robots=["r1"], gids=gids,
        )  # fmt: skip
        settings = zt.session_config(esc_cfg, group, "esc.r1", "esc", ["r1"], users)
        assert settings["connect/endpoints"][0].startswith("tls/localhost:")
        if wrong == "no certificate":  # the client shows none
            settings = {k: v for k, v in settings.items() if "/connect_" not in k}
        esc = zt.ZenohTransport(
            settings, group=group, node="esc.r1", kind="esc", robots=["r1"], gids=gids,
            connect_timeout_s=1.5,
        )  # fmt: skip
        try:
            with pytest.raises(TransportError, match=r"cannot reach the group's door"):
                deadline = time.monotonic() + 5
                while time.monotonic() < deadline:
                    esc.receive()
                    ssc.receive()
                    time.sleep(0.01)  # polling a non-blocking receive, to a deadline
            assert not ssc.connected()
        finally:
            ssc.close()
            esc.close()
    finally:
        shutil.rmtree(folder)


def test_a_zenoh_esc_answers_in_zenohs_thread_and_queues_what_it_leaves() -> None:
    """An ESC side that answers (``Transport.answer_with``) is handed each
    command in zenoh's thread as it arrives. What the answer takes never
    reaches ``receive``; what it leaves goes to the inbox and wakes the
    ddm's fd, and the records after it queue behind it, in order, unoffered,
    until the ddm has taken the inbox: then the answer gets them again."""
    import select
    import threading

    from redistro.ddm.transport import ANSWERED, NOT_TAKEN

    cmds = [_command(s) for s in range(1, 6)]
    seen: list[tuple[int, bytes]] = []

    def answer(raw: bytes) -> int:
        seen.append((threading.get_ident(), raw))
        return NOT_TAKEN if raw == cmds[1] else ANSWERED

    ssc, esc = _zenoh_pair(answer=answer)
    try:

        def arrived(c: bytes) -> bool:
            return c in esc.inbox or c in [raw for _, raw in seen]

        for c in cmds[:4]:  # one at a time (a burst may be dropped: express, DROP)
            ssc.send(c, 0)
            wait_for(lambda c=c: arrived(c), 5, "zenoh's thread to deliver a command")
        assert select.select(esc.fds(), [], [], 0)[0] == esc.fds()  # woken
        assert esc.receive() == cmds[1:4]  # the left one, then those behind it
        assert [raw for _, raw in seen] == cmds[:2]
        assert threading.get_ident() not in {t for t, _ in seen}
        ssc.send(cmds[4], 0)  # the inbox is empty again: offered, and answered
        wait_for(lambda: len(seen) >= 3, 5, "zenoh's thread to answer the last command")
        assert [raw for _, raw in seen] == cmds[:2] + cmds[4:]
        assert esc.receive() == []
    finally:
        ssc.close()
        esc.close()


def test_a_connecting_side_given_up_before_the_handshake_connects_again() -> None:
    """The ESC gives up an SSC's connection for a newcomer before the
    handshake (a squatter came in between): the SSC connects again, within
    its connect deadline; once its link brought this run's records, a loss
    is a loss."""
    cls = transport_class("socket")
    esc = cls(listen=("127.0.0.1", 0), authenticate=True)
    ssc = cls(peers={0: esc.address}, connect_timeout_s=10.0)
    squatter = None
    try:
        deadline = time.monotonic() + 5
        while esc.peer is None or not ssc.connected():  # type: ignore[attr-defined]
            assert time.monotonic() < deadline
            esc.receive()
            time.sleep(0.001)  # polling non-blocking sockets, to a deadline
        first = esc.peer  # type: ignore[attr-defined]
        squatter = socket.create_connection(esc.address)  # type: ignore[attr-defined]
        while esc.peer is first:  # type: ignore[attr-defined]
            assert time.monotonic() < deadline
            esc.receive()
            time.sleep(0.001)
        # the SSC sees its link closed, and connects again
        while not (ssc.conns and esc.peer is not None and esc.peer.name != first.name):  # type: ignore[attr-defined]
            assert time.monotonic() < deadline, "the SSC did not connect again"
            ssc.receive()
            esc.receive()
            time.sleep(0.001)
        assert ssc.links.lost_links() == {}
        ssc.links.authenticated(0)  # records of this run came over it: a loss is now a loss
        esc.close()
        while not ssc.links.lost_links():
            assert time.monotonic() < deadline
            with contextlib.suppress(TransportError):
                ssc.receive()
            time.sleep(0.001)
    finally:
        if squatter is not None:
            squatter.close()
        ssc.close()
        esc.close()


def test_a_tcp_self_connect_is_recognized() -> None:
    """On loopback a socket connecting to a port no one listens on can come
    out connected to itself (its ephemeral port the peer's): the connecting
    side tries again instead of holding the port its peer would listen on."""
    import socket

    from redistro.ddm.sockets import self_connected

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        s.connect(s.getsockname())  # a simultaneous open with itself
        assert self_connected(s)
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as srv:
        srv.bind(("127.0.0.1", 0))
        srv.listen(1)
        with socket.create_connection(srv.getsockname()) as c:
            assert not self_connected(c)


def test_the_derived_ports_keep_out_of_the_ephemeral_range_and_of_each_other() -> None:
    """Every derived TCP listening port (an ESC's socket ddm, the SSC's zenoh
    session) lies below Linux's ephemeral ports, where no connection of the
    host takes it; the two kinds never meet."""
    from redistro.config import load_config
    from redistro.ddm.sockets import esc_port
    from redistro.ddm.zenoh_transport import ssc_port

    cfg = load_config(None)
    groups = [f"20261129T{k:06d}-{k * 7919 % 16**6:06x}" for k in range(2000)]
    escs = {esc_port(cfg, g, r) for g in groups for r in ("r1", "r2")}
    sscs = {ssc_port(cfg, g) for g in groups}
    low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    assert max(escs | sscs) < min(low, 32768) and min(escs | sscs) >= 1024
    assert max(sscs) < min(escs), (max(sscs), min(escs))

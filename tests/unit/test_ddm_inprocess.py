"""Real ddms in one process: the SSC's and both ESCs' (``ddm.worker.Ddm``,
their compiled common case included) over the in-process transport
(``ddm.loopback``), each on its node's Local Data in memory. A command the
SSC's worker publishes reaches each ESC's Local Data and pays back its
starving index; the feedback each ESC's acquisition publishes comes back
as the reply; a forged record is dropped and counted."""

from __future__ import annotations

import dataclasses
import socket
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from redistro.config import load_config
from redistro.config.hardware import load_hardware
from redistro.config.task import load_task
from redistro.ddm import record as wire
from redistro.ddm.loopback import Loopback
from redistro.ddm.worker import Ddm
from redistro.esc.plan import esc_spec
from redistro.ipc.names import new_session_id
from redistro.localdata import LocalData
from redistro.localdata.block import Record
from redistro.localdata.layout import COMMAND, COUNTER, FEEDBACK
from redistro.process.spec import NodeSpec
from redistro.process.watch import node_local_data
from redistro.ssc.plan import ssc_spec
from tests.helpers import ROOT, wait_for

ROBOTS = ["r1", "r2"]


@dataclass
class Node:
    spec: NodeSpec
    ld: LocalData
    ddm: Ddm


def _node(spec: NodeSpec, end: Loopback) -> Node:
    ld = node_local_data(spec, 5_000_000, None, memory=True)
    j = next(j for j, w in enumerate(spec.workers) if w.role == "ddm")
    ddm = Ddm(spec, j, ld, transport=end)
    ddm.initialize()
    return Node(spec, ld, ddm)


@dataclass
class Setup:
    key: Path
    cfg: Any
    task: Any
    hw: Any
    sid: str
    gids: list[int]


def _setup(tmp_path: Path, sets: tuple[str, ...] = ()) -> Setup:
    """A group's link key, config, task, hardware, session id and robot ids."""
    key = tmp_path / "link.key"
    wire.new_key(key)
    cfg = load_config(ROOT / "config/redistro.yaml", [f"ddm.key_file={key}", *sets])
    task = load_task(ROOT / "tasks/peg_insertion_short.yaml", cfg)
    gids = [list(cfg.robots).index(r) for r in ROBOTS]
    return Setup(key, cfg, task, load_hardware(cfg), new_session_id(), gids)


def _shake_hands(ssc: Node, escs: dict[str, Node]) -> None:
    """The run's handshake over in-process ends: the SSC's hellos, the ESCs'
    challenges, the SSC's proofs, the ESCs take the run key."""
    for cycle in range(2):
        ssc.ddm.step(cycle)
        for esc in escs.values():
            esc.ddm.step(cycle)
    assert all(esc.ddm.handshake.done for esc in escs.values())
    assert all(esc.ddm.key == ssc.ddm.key for esc in escs.values())


@pytest.fixture
def group(tmp_path: Path) -> Iterator[tuple[Node, dict[str, Node]]]:
    g = _setup(tmp_path)
    cfg, task, hw, sid, gids = g.cfg, g.task, g.hw, g.sid, g.gids
    ssc_end, esc_ends = Loopback.group(gids)
    ssc = _node(ssc_spec(cfg, task, sid, run_dir=""), ssc_end)
    escs = {
        r: _node(esc_spec(cfg, task, r, hw[r], sid, positions_file="p.json"), esc_ends[g])
        for r, g in zip(ROBOTS, gids, strict=True)
    }
    _shake_hands(ssc, escs)
    yield ssc, escs
    for n in [ssc, *escs.values()]:
        n.ddm.cleanup()
        n.ld.close()
        n.ld.unlink()


def test_commands_go_down_and_feedback_comes_back_as_the_reply(
    group: tuple[Node, dict[str, Node]],
) -> None:
    ssc, escs = group
    # the ESCs' acquisitions have a sample; their senders sent 3 commands
    for k, esc in enumerate(escs.values()):
        fb = Record(FEEDBACK)
        fb["seq_src"] = 1
        fb.array["q_rad"] = np.arange(7) + 10 * k
        esc.ld.writer("feedback", 0, role="acquisition").publish(fb.bytes)
        sent = Record(COUNTER)
        sent["count"] = 3
        esc.ld.writer("starving_sent", role="sender").publish(sent.bytes)
        esc.ddm.step(1)  # the start-up datum: its feedback goes out on its own
    ssc.ddm.step(1)
    for i, r in enumerate(ROBOTS):
        got = ssc.ld.block("feedback", i).read()
        assert list(got["q_rad"]) == list(np.arange(7) + 10 * i), r
    # the SSC's worker publishes a command per robot, the ddm sends them
    for i in range(len(ROBOTS)):
        cmd = Record(COMMAND)
        cmd["seq_src"] = 1
        cmd.array["tau_nm"] = i + 0.5
        ssc.ld.writer("command", i, role="worker").publish(cmd.bytes)
    ssc.ddm.step(2)
    for i, (r, esc) in enumerate(escs.items()):
        esc.ddm.step(2)
        got = esc.ld.block("command", 0).read()
        assert float(got["tau_nm"][0]) == i + 0.5, r
        assert int(esc.ld.block("starving_delivered").read()["count"]) == 3, r
        ex = esc.ddm.ex[0]
        assert ex["updates"] == 1 and ex["fresh"] == 1 and ex["dropped"] == 0, r
    # a new sample on each ESC goes out as the reply to the next command
    sent_before = [n.ddm.ex[0]["sent"] for n in escs.values()]
    for k, esc in enumerate(escs.values()):
        fb = Record(FEEDBACK)
        fb["seq_src"] = 2
        fb.array["q_rad"] = -(np.arange(7) + 10 * k)
        esc.ld.writer("feedback", 0, role="acquisition").publish(fb.bytes)
        esc.ddm.step(3)  # no command came: a replying ddm says nothing
    assert [n.ddm.ex[0]["sent"] for n in escs.values()] == sent_before
    for i in range(len(ROBOTS)):
        cmd = Record(COMMAND)
        cmd["seq_src"] = 2
        ssc.ld.writer("command", i, role="worker").publish(cmd.bytes)
    ssc.ddm.step(4)
    for esc in escs.values():
        esc.ddm.step(4)
    ssc.ddm.step(5)
    for i in range(len(ROBOTS)):
        assert list(ssc.ld.block("feedback", i).read()["q_rad"]) == list(-(np.arange(7) + 10 * i))
    assert ssc.ddm.ex[0]["updates"] == ssc.ddm.ex[1]["updates"] == 2
    from redistro.kernels import KERNELS

    assert (ssc.ddm.kernel_path is not None) == (KERNELS is not None)  # the compiled path ran


def test_a_forged_command_is_dropped_and_counted(group: tuple[Node, dict[str, Node]]) -> None:
    ssc, escs = group
    esc = escs["r2"]
    cmd = np.zeros((), COMMAND)
    cmd["seq_src"] = 1
    cmd["tau_nm"] = 300.0
    gid = esc.ddm.gid["r2"]
    forged = wire.encode(wire.KIND_COMMAND, gid, "ssc", 1, 1, cmd, key=bytes(32))
    ssc.ddm.transport.send(forged, gid)
    esc.ddm.step(1)
    assert esc.ddm.ex[0]["forged"] == 1 and esc.ddm.ex[0]["dropped"] == 1
    assert float(esc.ld.block("command", 0).read()["tau_nm"][0]) == 0.0


def test_a_command_read_torn_beside_another_robots_is_sent_once_its_write_is_over(
    group: tuple[Node, dict[str, Node]],
) -> None:
    """The SSC's worker writes each robot's command in turn; its ddm may
    read them while the worker is inside the second write. The compiled
    emit then hands the step to the Python path, which reads again: the
    first robot's command must still go out (a lockstep tick waited for
    it for ever)."""
    ssc, escs = group
    kpath = ssc.ddm.kernel_path
    if kpath is None:
        pytest.skip("the kernels are not built")
    for i in range(len(ROBOTS)):
        cmd = Record(COMMAND)
        cmd["seq_src"] = 1
        cmd.array["tau_nm"] = i + 0.5
        ssc.ld.writer("command", i, role="worker").publish(cmd.bytes)
    seq_off = ssc.ld.block_offsets("command", 1)[0]
    seq = ssc.ld.raw[seq_off : seq_off + 8].view(np.uint64)
    seq[0] += 1  # the worker inside its write of robot 1's command
    assert kpath.emit() == -1  # a torn read: the Python path's
    seq[0] += 1  # ... and the write over
    ssc.ddm.step(2)
    for i, (r, esc) in enumerate(escs.items()):
        esc.ddm.step(2)
        got = esc.ld.block("command", 0).read()
        assert int(got["seq_src"]) == 1 and float(got["tau_nm"][0]) == i + 0.5, r
        assert int(ssc.ddm.ex[i]["sent"]) == 1 and int(esc.ddm.ex[0]["updates"]) == 1, r


def test_in_lockstep_each_ddm_rings_the_plants_bell_when_it_admits(tmp_path: Path) -> None:
    """In lockstep the plant sleeps on its bell (``ipc.bell``): the SSC's
    ddm rings it once it admitted the samples, an ESC's once it admitted
    its command; a step that admitted nothing rings nothing."""
    from redistro.ipc import bell
    from redistro.ipc.sem import Semaphore

    g = _setup(tmp_path, ("session.clock=lockstep",))
    ssc_end, esc_ends = Loopback.group(g.gids)
    ssc = _node(ssc_spec(g.cfg, g.task, g.sid, run_dir=""), ssc_end)
    escs = {
        r: _node(esc_spec(g.cfg, g.task, r, g.hw[r], g.sid, positions_file="p"), esc_ends[gid])
        for r, gid in zip(ROBOTS, g.gids, strict=True)
    }
    plant = Semaphore.create(bell.bell_name(g.sid), None)
    try:
        assert ssc.spec.clock == "lockstep" and ssc.ddm.ring is not None
        _shake_hands(ssc, escs)
        while plant.try_acquire():
            pass  # (the handshake's)
        for esc in escs.values():
            fb = Record(FEEDBACK)
            fb["seq_src"] = 1
            esc.ld.writer("feedback", 0, role="acquisition").publish(fb.bytes)
            esc.ddm.step(1)  # its sample out: nothing admitted, no ring
        assert plant.value == 0
        ssc.ddm.step(1)  # both samples in
        assert plant.value == 1
        for i in range(len(ROBOTS)):
            cmd = Record(COMMAND)
            cmd["seq_src"] = 1
            ssc.ld.writer("command", i, role="worker").publish(cmd.bytes)
        ssc.ddm.step(2)  # the commands out: nothing admitted
        assert plant.value == 1
        for esc in escs.values():
            esc.ddm.step(2)
        assert plant.value == 3  # each ESC's command in
    finally:
        for n in [ssc, *escs.values()]:
            n.ddm.cleanup()
            n.ld.close()
            n.ld.unlink()
        plant.close()
        plant.unlink()


def test_the_ssc_worker_plans_and_commands_in_one_process(
    group: tuple[Node, dict[str, Node]],
) -> None:
    """A Worker on its own (the SSC's planner): once every robot's feedback
    has come through the ddm it starts the task and publishes a plan and a
    command per robot every cycle; the ddm then carries them down."""
    from redistro.ssc.worker import SscWorker

    ssc, escs = group
    j = next(j for j, w in enumerate(ssc.spec.workers) if w.role == "worker")
    worker = SscWorker(ssc.spec, j, ssc.ld)
    worker.initialize()
    try:
        worker.step(1)  # no feedback yet: the datum is missing, nothing is produced
        assert int(ssc.ld.block("command", 0).read()["seq_src"]) == 0
        for esc in escs.values():
            fb = Record(FEEDBACK)
            fb["seq_src"] = 1
            fb["step"] = 1000
            fb.array["q_rad"] = [0.0, 0.5, 0.0, -1.2, 0.0, 1.0, 0.0]
            esc.ld.writer("feedback", 0, role="acquisition").publish(fb.bytes)
            esc.ddm.step(1)
        ssc.ddm.step(1)
        for cycle in range(2, 12):
            worker.step(cycle)
        plan = ssc.ld.block("plan", 1).read()  # r2 moves in the first segment
        assert int(plan["segment"]) == 1 and int(plan["moving"]) == 1
        cmds = [ssc.ld.block("command", i).read() for i in range(2)]
        assert [int(c["seq_src"]) for c in cmds] == [10, 10]
        assert all(np.isfinite(c["tau_nm"]).all() for c in cmds)
        assert abs(cmds[1]["tau_nm"]).max() > 0  # gravity, at least
        ssc.ddm.step(12)
        escs["r2"].ddm.step(12)
        assert int(escs["r2"].ld.block("command", 0).read()["seq_src"]) == 10
    finally:
        worker.cleanup()


# -- the same ddms over real TCP sockets on loopback: the compiled socket path --


@pytest.fixture
def socket_group(tmp_path: Path) -> Iterator[tuple[Node, dict[str, Node]]]:
    """The group of :func:`group`, each ddm on its own real SocketTransport
    (the ESCs listening on free ports, the SSC connecting to them)."""
    from redistro.ddm.sockets import SocketTransport

    g = _setup(tmp_path)
    cfg, task, hw, sid, gids = g.cfg, g.task, g.hw, g.sid, g.gids
    ends = {g: SocketTransport(listen=("127.0.0.1", 0), authenticate=True) for g in gids}
    ssc_end = SocketTransport(peers={g: ends[g].address for g in gids})
    nodes: list[Node] = []
    try:
        for r, g in zip(ROBOTS, gids, strict=True):
            spec = esc_spec(cfg, task, r, hw[r], sid, positions_file="p.json")
            nodes.append(_node(spec, ends[g]))
        nodes.insert(0, _node(ssc_spec(cfg, task, sid, run_dir=""), ssc_end))
        yield nodes[0], dict(zip(ROBOTS, nodes[1:], strict=True))
    finally:
        for n in nodes:
            n.ddm.cleanup()
            n.ld.close()
            n.ld.unlink()
        for end in [ssc_end, *ends.values()]:
            end.close()


def _step_until(nodes: list[Node], done: Callable[[], bool], what: str) -> None:
    """Step every ddm (the SSC's first) until ``done`` (the records cross
    the loopback between two steps), with a deadline."""
    cycle = 0

    def turn() -> bool:
        nonlocal cycle
        cycle += 1
        for n in nodes:
            n.ddm.ready_fds = None  # (look at every socket)
            n.ddm.step(cycle)
        return done()

    wait_for(turn, 5.0, what)


def test_over_sockets_the_kernels_receive_admit_and_send(
    socket_group: tuple[Node, dict[str, Node]],
) -> None:
    """Real sockets: the records go out through ddm_send and come in
    through ddm_recv, admitted without the Python path; a forged and a
    replayed record on the same connection are refused and counted by it."""
    from redistro.kernels import KERNELS

    if KERNELS is None:
        pytest.skip("the compiled kernels are not built")
    ssc, escs = socket_group
    nodes = [ssc, *escs.values()]
    for k, esc in enumerate(escs.values()):
        fb = Record(FEEDBACK)
        fb["seq_src"] = 1
        fb.array["q_rad"] = np.arange(7) + 10 * k
        esc.ld.writer("feedback", 0, role="acquisition").publish(fb.bytes)
    _step_until(
        nodes,
        lambda: all(int(ssc.ld.block("feedback", i).read()["seq_src"]) == 1 for i in range(2)),
        "every ESC's start-up datum at the SSC",
    )
    assert all(n.ddm.socket_kernels for n in nodes)
    for seq in range(1, 11):
        for i in range(len(ROBOTS)):
            cmd = Record(COMMAND)
            cmd["seq_src"] = seq
            cmd.array["tau_nm"] = i + seq / 10
            ssc.ld.writer("command", i, role="worker").publish(cmd.bytes)
        for k, esc in enumerate(escs.values()):
            fb = Record(FEEDBACK)
            fb["seq_src"] = seq + 1
            fb.array["q_rad"] = -(np.arange(7) + seq + 10 * k)
            esc.ld.writer("feedback", 0, role="acquisition").publish(fb.bytes)
        _step_until(
            nodes,
            lambda s=seq: (
                all(int(e.ld.block("command", 0).read()["seq_src"]) == s for e in escs.values())
                and all(
                    int(ssc.ld.block("feedback", i).read()["seq_src"]) == s + 1 for i in range(2)
                )
            ),
            f"command {seq} down and its reply up",
        )
    for i, esc in enumerate(escs.values()):
        got = esc.ld.block("command", 0).read()
        assert float(got["tau_nm"][0]) == pytest.approx(i + 1.0)
        assert list(ssc.ld.block("feedback", i).read()["q_rad"]) == list(
            -(np.arange(7) + 10 + 10 * i)
        )
        ex = esc.ddm.ex[0]
        assert ex["updates"] == 10 and ex["dropped"] == 0
        fast = esc.ddm.kernel_path
        assert fast is not None and int(fast.state["taken"]) >= 9  # admitted by the kernel
        assert int(fast.send_fds[0]) >= 0  # sent by ddm_send, on the peer's socket
    assert ssc.ddm.kernel_path is not None and int(ssc.ddm.kernel_path.state["taken"]) >= 18
    # a forged record, then a replay of a sound one, on the pinned connection
    esc = escs["r2"]
    gid = esc.ddm.gid["r2"]
    cmd = np.zeros((), COMMAND)
    cmd["seq_src"] = 99
    cmd["tau_nm"] = 300.0
    ssc.ddm.transport.send(
        wire.encode(wire.KIND_COMMAND, gid, "ssc", 99, 1, cmd, key=bytes(32)), gid
    )
    replay = bytes(ssc.ddm.kernel_path.wire_views[1])  # the last command sent to r2
    ssc.ddm.transport.send(replay, gid)
    wait_for(
        lambda: esc.ddm.step(99) or esc.ddm.ex[0]["dropped"] == 2,
        5.0,
        "the forged and the replayed record refused",
    )
    assert esc.ddm.ex[0]["forged"] == 1 and esc.ddm.ex[0]["duplicate"] == 1
    assert float(esc.ld.block("command", 0).read()["tau_nm"][0]) == pytest.approx(2.0)
    assert esc.ddm.ex[0]["updates"] == 10


def test_an_answering_esc_ddm_sleeps_out_of_the_commands_burst(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A ddm that answers its commands in its transport's thread (zenoh's)
    has nothing to step for on a deadline but its heartbeat: it sleeps a
    quarter of its heartbeat limit and wakes half a period away from the
    commands' arrival. Any other ddm (or one not yet answering) sleeps a
    period."""
    from redistro.ddm import worker as ddm_worker
    from redistro.ddm.answer import ThreadAnswer
    from redistro.localdata.layout import EXCHANGE

    period = 5_000_000
    d = Ddm.__new__(Ddm)  # (only what wait_s reads)
    d.period_ns, d.heartbeat_cycles = period, 25
    d.kind, d.commanded = "esc", True
    d.answers = ThreadAnswer(d)
    d.answers.on = True
    d.ex = [Record(EXCHANGE)]
    assert d.wait_s() == pytest.approx(0.005)  # nothing answered yet
    d.answers.taken_here = 1
    now = 10_000 * period + 1_300_000
    monkeypatch.setattr(ddm_worker.time, "monotonic_ns", lambda: now)
    for last in (now - 1_000_000, now - 4_900_000, now - 3 * period - 200_000):
        d.ex[0]["last_update_ns"] = last
        wait_ns = round(d.wait_s() * 1e9)
        assert wait_ns % 1_000_000 == 0  # whole milliseconds, as epoll waits
        wake = now + wait_ns
        # about half a period after a command (1 ms early at most)
        assert period // 2 - 1_000_000 < (wake - last) % period <= period // 2
        assert 5 * period < wake - now <= 7 * period  # 25 // 4 periods, about
    d.kind = "ssc"  # (answering in zenoh's thread too, but woken by its worker)
    assert d.wait_s() == pytest.approx(0.005)
    d.kind, d.answers.on = "esc", False  # (a socket ESC)
    assert d.wait_s() == pytest.approx(0.005)


def test_an_earlier_runs_hello_and_records_are_refused_and_pin_nothing(tmp_path: Path) -> None:
    """Nodes started alone share a key file. Run 1's hello and commands,
    recorded, are sent to run 2's ESC over a connection of their own before
    run 2's SSC comes: the ESC challenges the hello, refuses every command
    (not signed with run 2's key), never pins that connection, and takes
    run 2's SSC when it comes."""
    from redistro.ddm.sockets import SocketTransport

    g = _setup(tmp_path)
    cfg, task, hw, gids = g.cfg, g.task, g.hw, g.gids
    gid = gids[1]  # r2

    def esc_of(sid: str) -> tuple[Node, SocketTransport]:
        end = SocketTransport(listen=("127.0.0.1", 0), authenticate=True)
        spec = esc_spec(cfg, task, "r2", hw["r2"], sid, positions_file="p.json")
        return _node(spec, end), end

    def ssc_of(sid: str, address: tuple[str, int]) -> tuple[Node, SocketTransport]:
        ssc_end = SocketTransport(peers={gid: address})
        spec = dataclasses.replace(ssc_spec(cfg, task, sid, run_dir=""), robots=["r2"])
        return _node(spec, ssc_end), ssc_end

    # run 1: a handshake, then commands; everything the SSC sent is recorded
    sid = new_session_id()
    esc, end = esc_of(sid)
    ssc, ssc_end = ssc_of(sid, end.address)
    sent: list[bytes] = []
    real_send = ssc_end.send
    ssc_end.send = lambda record, robot: (sent.append(bytes(record)), real_send(record, robot))[1]  # type: ignore[method-assign]
    try:
        _step_until([ssc, esc], lambda: esc.ddm.handshake.done, "run 1's handshake")
        for seq in range(1, 6):
            cmd = Record(COMMAND)
            cmd["seq_src"] = seq
            cmd.array["tau_nm"] = 5.0
            ssc.ld.writer("command", 0, role="worker").publish(cmd.bytes)
            _step_until(
                [ssc, esc],
                lambda s=seq: int(esc.ld.block("command", 0).read()["seq_src"]) == s,
                f"run 1's command {seq}",
            )
            if ssc.ddm.kernel_path is not None:  # (sent by the send kernel, not through send())
                sent.append(bytes(ssc.ddm.kernel_path.wire_views[0]))
    finally:
        for n in (ssc, esc):
            n.ddm.cleanup()
            n.ld.close()
            n.ld.unlink()
    hellos = [r for r in sent if r[6] == wire.KIND_HELLO]
    commands = [r for r in sent if r[6] == wire.KIND_COMMAND]
    assert hellos and len(commands) >= 5

    # run 2: the ESC alone, and someone replaying run 1 before its SSC comes
    sid2 = new_session_id()
    esc2, end2 = esc_of(sid2)
    nodes = [esc2]
    ssc_end2 = None
    try:
        replayer = socket.create_connection(end2.address)
        replayer.settimeout(2.0)
        for record in [*hellos, *commands]:
            replayer.sendall(record)
        wait_for(
            lambda: esc2.ddm.step(1) or esc2.ddm.ex[0]["forged"] >= 1,
            5.0,
            "the replayed commands refused",
        )
        assert not esc2.ddm.handshake.done and not end2.pinned
        assert int(esc2.ld.block("command", 0).read()["seq_src"]) == 0
        # each replayed hello was only challenged (run 1's SSC says hello
        # every HELLO_EVERY_S until it hears back: one or more), and the
        # connection dropped at the first forgery (the end of the stream)
        got = b""
        while chunk := replayer.recv(4096):
            got += chunk
        challenges = [got[i : i + wire.SIZE] for i in range(0, len(got), wire.SIZE)]
        assert 1 <= len(challenges) <= len(hellos) and len(got) % wire.SIZE == 0, got
        assert all(c[6] == wire.KIND_HELLO for c in challenges), challenges
        # run 2's SSC: shakes hands, is pinned, its commands are taken
        ssc2, ssc_end2 = ssc_of(sid2, end2.address)
        nodes.insert(0, ssc2)
        cmd = Record(COMMAND)
        cmd["seq_src"] = 1
        cmd.array["tau_nm"] = 1.25
        ssc2.ld.writer("command", 0, role="worker").publish(cmd.bytes)
        _step_until(
            [ssc2, esc2],
            lambda: int(esc2.ld.block("command", 0).read()["seq_src"]) == 1,
            "run 2's first command",
        )
        assert esc2.ddm.handshake.done and end2.pinned
        assert float(esc2.ld.block("command", 0).read()["tau_nm"][0]) == 1.25
        assert esc2.ddm.ex[0]["updates"] == 1
        replayer.close()
    finally:
        for n in nodes:
            n.ddm.cleanup()
            n.ld.close()
            n.ld.unlink()
        for e in (ssc_end, end, ssc_end2, end2):
            if e is not None:
                e.close()


def test_encrypted_payloads_cross_unreadable_and_arrive_whole(tmp_path: Path) -> None:
    """ddm.encrypt: what goes on the wire holds no byte of a command's
    payload as the worker wrote it; the ESC's Local Data gets it whole; a
    flipped bit of the ciphertext fails the tag (forged), as any change."""
    g = _setup(tmp_path, ("ddm.encrypt=true",))
    ssc_end, esc_ends = Loopback.group(g.gids)
    wire_seen: list[bytes] = []
    real = ssc_end.send

    def seen(record: bytes, robot: int) -> None:
        wire_seen.append(bytes(record))
        real(record, robot)

    ssc_end.send = seen  # type: ignore[method-assign]
    ssc = _node(ssc_spec(g.cfg, g.task, g.sid, run_dir=""), ssc_end)
    escs = {
        r: _node(esc_spec(g.cfg, g.task, r, g.hw[r], g.sid, positions_file="p.json"), esc_ends[gid])
        for r, gid in zip(ROBOTS, g.gids, strict=True)
    }
    try:
        _shake_hands(ssc, escs)
        assert (
            ssc.ddm.kernel_path is None
            and ssc.ddm.cipher
            and escs["r2"].ddm.cipher == ssc.ddm.cipher
        )
        cmd = Record(COMMAND)
        cmd["seq_src"] = 1
        cmd.array["tau_nm"] = [1.25, -2.5, 3.75, 0, 0, 0, 0.5]
        ssc.ld.writer("command", 1, role="worker").publish(cmd.bytes)
        ssc.ddm.step(5)
        escs["r2"].ddm.step(5)
        got = escs["r2"].ld.block("command", 0).read()
        assert list(got["tau_nm"]) == [1.25, -2.5, 3.75, 0, 0, 0, 0.5]
        sent = [r for r in wire_seen if r[6] == wire.KIND_COMMAND]
        assert sent
        plain = cmd.array["tau_nm"].tobytes()
        assert all(plain not in r for r in sent)
        assert escs["r2"].ddm.ex[0]["updates"] == 1
        # a flipped bit of the ciphertext: the tag fails
        bad = bytearray(sent[-1])
        bad[wire.PAYLOAD_AT + 20] ^= 1
        real(bytes(bad), g.gids[1])
        escs["r2"].ddm.step(6)
        assert escs["r2"].ddm.ex[0]["dropped"] >= 1
    finally:
        for n in [ssc, *escs.values()]:
            n.ddm.cleanup()
            n.ld.close()
            n.ld.unlink()

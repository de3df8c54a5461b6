"""The ddm's compiled paths against its Python path, on random traffic.

Twin ESC ddms (``ddm.worker.Ddm``, each on its own Local Data, over the
in-process transport) get the same records: one plans the kernels
(``ddm_admit``, ``ddm_emit``, the ``CompiledAnswer``), the other runs the Python
path alone. After every step both must have written the same command into
Local Data, counted the same in their exchange records, and sent the same
feedback records back, byte for byte (their time stamps aside: the reply's
stamp is the clock's, so it is set to 0 and the record sealed again before
the comparison). The stream sockets' kernels (``ddm_recv``, ``ddm_send``,
``ddm_reply``) are held to ``ddm_admit`` and ``ddm_emit`` on socket pairs.
"""

from __future__ import annotations

import socket
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from redistro.ddm import record as wire
from redistro.ddm import worker as ddm_worker
from redistro.ddm.loopback import Loopback
from redistro.ddm.socket_steps import REPLIED
from redistro.kernels import KERNELS
from redistro.localdata.block import Record
from redistro.localdata.layout import FEEDBACK
from tests.unit.test_ddm_inprocess import Node, _node, _setup

pytestmark = pytest.mark.skipif(KERNELS is None, reason="the kernels are not built")
EXAMPLES = settings(
    max_examples=500, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
RUN_KEY = bytes(range(100, 132))
STAMP_AT = wire.HEADER.fields["stamp_ns"][1]  # type: ignore[index]
KINDS = ("next", "next", "next", "gap", "duplicate", "older", "stale", "forged", "other robot",
         "other source", "feedback kind", "malformed", "short")  # fmt: skip


@dataclass
class Twin:
    esc: Node
    ssc_end: Loopback
    esc_end: Loopback
    feedback: Any  # the acquisition's writer of the feedback block
    others: list[Node]


@dataclass
class Traffic:
    """What the SSC has sent so far (both twins get the same)."""

    seq: int = 0
    stamp: int = 1_000
    produced: int = 0  # the ESC's acquisition's last sample
    replied: int = 0  # steps ddm_reply made whole


def _twin(tmp_path: Path, compiled: bool, monkeypatch: pytest.MonkeyPatch) -> Twin:
    from redistro.esc.plan import esc_spec
    from redistro.ssc.plan import ssc_spec

    where = tmp_path / ("k" if compiled else "p")
    where.mkdir(parents=True, exist_ok=True)
    g = _setup(where)
    gid = g.gids[0]
    ssc_end, esc_ends = Loopback.group([gid])
    with monkeypatch.context() as m:
        if not compiled:
            m.setattr(ddm_worker, "KERNELS", None)
        ssc = _node(ssc_spec(g.cfg, g.task, g.sid, run_dir=""), ssc_end)
        esc = _node(
            esc_spec(g.cfg, g.task, "r1", g.hw["r1"], g.sid, positions_file="p"), esc_ends[gid]
        )
    assert (esc.ddm.kernel_path is not None) == compiled
    for cycle in range(2):  # the run's handshake, then one key for both twins
        ssc.ddm.step(cycle)
        esc.ddm.step(cycle)
    assert esc.ddm.handshake.done
    esc.ddm.greeting.take_run_key(RUN_KEY)
    ssc_end.inbox.clear()
    feedback = esc.ld.writer("feedback", 0, role="acquisition")
    return Twin(esc, ssc_end, esc_ends[gid], feedback, [ssc])


def _close(pair: tuple[Twin, Twin]) -> None:
    """Every node of both twins: its ddm cleaned up, its Local Data removed."""
    for t in pair:
        for n in [t.esc, *t.others]:
            n.ddm.cleanup()
            n.ld.close()
            n.ld.unlink()


@pytest.fixture(scope="module")
def twins(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Twin, Twin, Traffic]]:
    mp = pytest.MonkeyPatch()
    tmp = tmp_path_factory.mktemp("twins")
    pair = (_twin(tmp, True, mp), _twin(tmp, False, mp))
    yield pair[0], pair[1], Traffic()
    mp.undo()
    _close(pair)


def _record(kind: str, traffic: Traffic, mark: float, gid: int) -> bytes:
    """One record the SSC's side might send (``kind`` of KINDS)."""
    seq, stamp = traffic.seq, traffic.stamp
    robot, source, key, rkind = gid, "ssc", RUN_KEY, wire.KIND_COMMAND
    if kind in ("next", "gap"):
        seq = traffic.seq = traffic.seq + (1 if kind == "next" else 5)
        stamp = traffic.stamp = traffic.stamp + 1000
    elif kind == "older":
        seq, stamp = max(0, seq - 2), stamp + 1
    elif kind == "stale":  # a newer seq, an older stamp
        seq = traffic.seq = traffic.seq + 1
        stamp = stamp - 500
    elif kind == "forged":
        seq, key = seq + 1, bytes(32)
    elif kind == "other robot":
        seq, robot = seq + 1, gid + 1
    elif kind == "other source":
        seq, source = seq + 1, "intruder"
    elif kind == "feedback kind":
        seq, rkind = seq + 1, wire.KIND_FEEDBACK
    payload = np.zeros((), wire.PAYLOADS[rkind])
    payload["seq_src"] = seq
    payload["stamp_ns"] = 1
    if rkind == wire.KIND_COMMAND:
        payload["tau_nm"][0] = mark
        payload["joint_on"][:] = 1
    raw = wire.encode(rkind, robot, source, seq, stamp, payload, key=key)
    if kind == "malformed":
        b = bytearray(raw)
        b[wire.PAYLOAD_AT + 3] ^= 0x40
        return bytes(b)
    return raw[:-7] if kind == "short" else raw


def _restamped(raw: bytes) -> bytes:
    """A reply with its (clock) stamp set to 0, sealed again."""
    b = bytearray(raw)
    struct.pack_into("<q", b, STAMP_AT, 0)
    struct.pack_into("<I", b, wire._CRC_AT, wire._crc(b))
    b[wire.BODY :] = wire._tag(RUN_KEY, b)
    return bytes(b)


def _state(t: Twin) -> tuple[bytes, dict[str, int], list[bytes]]:
    esc = t.esc
    command = esc.ld.block("command", 0).read().tobytes()
    ex = esc.ddm.ex[0].array
    assert ex.dtype.names is not None
    counts = {
        n: int(ex[n].sum())
        for n in ex.dtype.names
        if not n.endswith("_ns") and ex[n].dtype.kind in "iub"
    }
    counts["delivered"] = int(esc.ld.block("starving_delivered").read()["count"])
    replies = [_restamped(r) for r in t.ssc_end.inbox]
    t.ssc_end.inbox.clear()
    return command, counts, replies


@EXAMPLES
@given(
    events=st.lists(
        st.tuples(st.sampled_from(KINDS), st.floats(-50, 50), st.booleans(), st.integers(1, 3)),
        min_size=1,
        max_size=8,
    )
)
def test_the_compiled_step_writes_what_the_python_step_writes(
    twins: tuple[Twin, Twin, Traffic], events: list[tuple[str, float, bool, int]]
) -> None:
    compiled, python, traffic = twins
    gid = compiled.esc.ddm.gid["r1"]
    for kind, mark, new_feedback, burst in events:
        if new_feedback:  # the acquisition's next sample
            traffic.produced += 1
            fb = Record(FEEDBACK)
            fb["seq_src"] = traffic.produced
            fb.array["q_rad"][0] = mark
            for t in (compiled, python):
                t.feedback.publish(fb.bytes)
        records = [_record(kind, traffic, mark + k, gid) for k in range(burst)]
        for t in (compiled, python):
            t.esc_end.inbox.extend(records)
            t.esc.ddm.step(0)
        a, b = _state(compiled), _state(python)
        assert a[0] == b[0], f"{kind}: the command in Local Data differs"
        assert a[1] == b[1], f"{kind}: the exchange counts differ"
        assert a[2] == b[2], f"{kind}: the replies differ"


def test_the_kernel_took_its_share_of_that_traffic(twins: tuple[Twin, Twin, Traffic]) -> None:
    if twins[2].seq == 0:
        pytest.skip("the traffic test above was not run")
    kpath = twins[0].esc.ddm.kernel_path
    assert kpath is not None and int(kpath.taken) > 100
    assert twins[1].esc.ddm.kernel_path is None  # (and the other twin had none)


# -- the CompiledAnswer against the ddm's Python answer --


@pytest.fixture(scope="module")
def answering(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """Two compiled twins: one answers with the CompiledAnswer, one with _answer."""
    mp = pytest.MonkeyPatch()
    tmp = tmp_path_factory.mktemp("answer")
    pair = (_twin(tmp / "a", True, mp), _twin(tmp / "b", True, mp))
    for t in pair:
        t.esc.ddm.answers.on = True
        t.esc.ddm.answers.open_state()
    puts: list[list[bytes]] = [[], []]
    fallen: list[list[bytes]] = [[], []]
    ddm_a = pair[0].esc.ddm
    answer = ddm_a.answers.compiled(puts[0].append, [], fallen[0].append, lambda: None)
    yield pair, answer, puts, fallen, Traffic()
    mp.undo()
    _close(pair)


@EXAMPLES
@given(
    events=st.lists(
        st.tuples(st.sampled_from(KINDS), st.floats(-50, 50), st.booleans()), min_size=1, max_size=8
    )
)
def test_the_compiled_answer_answers_as_the_python_answer(
    answering: Any, events: list[tuple[str, float, bool]]
) -> None:
    from redistro.ddm.transport import NOT_TAKEN

    (compiled, python), answer, puts, fallen, traffic = answering
    gid = compiled.esc.ddm.gid["r1"]
    for t in (compiled, python):  # an ESC answers once commanded
        t.esc.ddm.commanded = True
        t.esc.ddm.answers.open_state()
    for kind, mark, new_feedback in events:
        if new_feedback:
            traffic.produced += 1
            fb = Record(FEEDBACK)
            fb["seq_src"] = traffic.produced
            for t in (compiled, python):
                t.feedback.publish(fb.bytes)
        raw = _record(kind, traffic, mark, gid)
        answer(raw)
        ddm = python.esc.ddm
        if ddm.answers.answer(raw) == NOT_TAKEN:
            fallen[1].append(raw)
        a_cmd = compiled.esc.ld.block("command", 0).read().tobytes()
        b_cmd = python.esc.ld.block("command", 0).read().tobytes()
        assert a_cmd == b_cmd, kind
        assert fallen[0] == fallen[1], kind
        sent_b = [_restamped(r) for r in python.ssc_end.inbox]
        python.ssc_end.inbox.clear()
        assert [_restamped(bytes(r)) for r in puts[0]] == sent_b, kind
        puts[0].clear()
        # what neither took goes through each ddm's own step alike
        for t, left in ((compiled, fallen[0]), (python, fallen[1])):
            t.esc_end.inbox.extend(left)
            left.clear()
            t.esc.ddm.step(0)
        a, b = _state(compiled), _state(python)
        assert a[0] == b[0] and a[2] == b[2], kind
        ex_a, ex_b = compiled.esc.ddm.ex[0], python.esc.ddm.ex[0]
        for name in ("updates", "dropped", "sent", "duplicate", "out_of_order", "stale", "forged"):
            assert int(ex_a[name]) == int(ex_b[name]), f"{kind}: {name}"


def test_the_answerer_took_its_share_of_that_traffic(answering: Any) -> None:
    (compiled, python), *_, traffic = answering
    if traffic.seq == 0:
        pytest.skip("the answer test above was not run")
    assert int(compiled.esc.ddm.answers.state["answered"]) > 100
    assert python.esc.ddm.answers.taken_here == int(compiled.esc.ddm.answers.state["answered"])


# -- the stream sockets' kernels against admit and emit --


def _socket_fast(ld: Any) -> Any:
    from redistro.ddm.kernel_path import KernelPath
    from redistro.process.stats import Samples

    kpath = KernelPath(
        ld, [1], [("command", 0)], [("feedback", 0)], wire.KIND_COMMAND, wire.KIND_FEEDBACK,
        "esc.r2", RUN_KEY, starving=True, latency=Samples(16),
    )  # fmt: skip
    kpath.refuse(wire.Admission(), 0, b"ssc".ljust(16, b"\0"), wire.KIND_COMMAND, 1, 1, 100)
    kpath.ex[0]["fresh"] = 1
    return kpath


@pytest.fixture(scope="module")
def socket_twins() -> Iterator[Any]:
    from tests.helpers import esc_segment

    procs = [("acquisition", "acquisition", 0), ("sender", "sender", 1), ("ddm", "ddm", -1)]
    with esc_segment(procs) as (_, a), esc_segment(procs) as (_, b):
        yield (a, _socket_fast(a)), (b, _socket_fast(b)), Traffic(seq=1, stamp=100)


@EXAMPLES
@given(
    kinds=st.one_of(  # (half the time the usual step: commands in order)
        st.lists(st.just("next"), min_size=1, max_size=3),
        st.lists(st.sampled_from(KINDS), min_size=1, max_size=5),
    ),
    new_feedback=st.booleans(),
    cut=st.sampled_from([0, 0, 0, 1, 3]),  # (a part record now and then)
)
def test_recv_and_reply_do_what_recv_admit_emit_and_send_do(
    socket_twins: Any, kinds: list[str], new_feedback: bool, cut: int
) -> None:
    """ddm_reply (one recv, its records admitted, the new feedback emitted
    and sent) on one side; recv(2), ddm_admit per record, ddm_emit and
    send(2) on the other: the same Local Data, the same bytes sent."""
    (lda, fa), (ldb, fb_), traffic = socket_twins
    records = b"".join(_record(k, traffic, 1.0, 1) for k in kinds)
    if cut:
        records = records[: -cut * 50]  # a part record at the end
    if new_feedback:
        traffic.produced += 1
        fb = Record(FEEDBACK)
        fb["seq_src"] = traffic.produced
        for ld in (lda, ldb):
            ld.writer("feedback", 0, role="acquisition").publish(fb.bytes)
    outs = []
    for ld, kpath, use_reply in ((lda, fa, True), (ldb, fb_, False)):
        a, b = socket.socketpair()
        try:
            a.setblocking(False)
            kpath.send_fds[0] = a.fileno()
            if records:
                b.sendall(records)
            rx = bytearray(64 * wire.SIZE)
            if use_reply:
                got = kpath.reply_call(
                    kpath.admit_plan, kpath.emit_plan, kpath.send_plan, rx, a.fileno()
                )
                replied = got == REPLIED
                traffic.replied += replied
                if not cut and set(kinds) == {"next"}:  # the usual step: done whole
                    assert replied, got
                left = b"" if replied else bytes(rx[: max(got, 0)])
                taken = [k for k in range(len(records) // wire.SIZE) if int(kpath.mask) >> k & 1]
                if not replied and got > 0 and got % wire.SIZE == 0:
                    left = b"".join(
                        left[k * wire.SIZE : (k + 1) * wire.SIZE]
                        for k in range(got // wire.SIZE)
                        if k not in taken
                    )
            else:
                data = a.recv(len(rx)) if records else b""
                whole = len(data) % wire.SIZE == 0 and data
                kept, all_taken = [], bool(whole)
                for k in range(len(data) // wire.SIZE if whole else 0):
                    rec = data[k * wire.SIZE : (k + 1) * wire.SIZE]
                    if kpath.admit_call(kpath.admit_plan, rec) < 0:
                        kept.append(rec)
                        all_taken = False
                left = b"".join(kept) if whole else data
                if all_taken:
                    mask = kpath.emit_call(kpath.emit_plan)
                    if mask > 0:
                        a.send(bytes(kpath.wire_views[0]))
            b.setblocking(False)
            try:
                sent = b.recv(8 * wire.SIZE)
            except BlockingIOError:
                sent = b""
            outs.append(
                (
                    ld.block("command", 0).read().tobytes(),
                    int(kpath.ex[0]["updates"]),
                    int(kpath.ex[0]["sent"]),
                    [_restamped(sent[k : k + wire.SIZE]) for k in range(0, len(sent), wire.SIZE)],
                    left,
                )
            )
        finally:
            a.close()
            b.close()
    assert outs[0] == outs[1]


def test_reply_made_its_share_of_those_steps_whole(socket_twins: Any) -> None:
    if socket_twins[2].seq == 1:
        pytest.skip("the reply test above was not run")
    assert socket_twins[2].replied > 20

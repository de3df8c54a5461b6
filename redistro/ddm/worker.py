"""The Distributed Data Manager: one per node, moving data when there is data.

It is the only door between nodes. It sleeps until records arrive (its
transport's sockets), its node produces something to send (the SSC worker
wakes it after each command, an ESC's acquisition after each feedback,
through the node's wake event), its manager raises the e-stop, or a node
period passes (so a silent peer is still seen, and its heartbeat signed).
Then it drains what the transport received, decodes and admits every record
(a malformed, duplicate, out-of-order or stale record is counted in the
exchange block and dropped), writes the fresh ones into Local Data, and
sends what this node produced since:

- in an ESC: commands in (``command[0]``; the starving index is paid back),
  feedback out: over a transport that replies (the socket DDM: the paper's
  send/receive/reply), as the answer to each command that brings a new
  sample, and on its own only until the first command (the start-up datum)
  and with an e-stop; otherwise each new sample of the acquisition;
- in the SSC: feedback in (``feedback[i]`` per robot), commands out (each
  new command the worker wrote, one record per robot).

Over a transport that delivers records on a thread of its own (zenoh),
the usual record is taken there, as it arrives, without waking the ddm
(admitted by the kernel; an ESC's reply emitted and sent): in one compiled
call (``_compiled_answer``, the C ``_kernels.Answerer``), else by
``_answer``, its Python reference. The step's state is shared under
``step_lock``, and whatever the answer does not take whole goes to the
ddm's own step.

Every record carries the node's e-stop: a manager that ended on a fault has
its ddm say so in every record from then on, and once more at Cleanup. A
record that comes in with the e-stop set makes the ddm ask its own manager
for an e-stop (one robot's fault stops the group).

Before any command or feedback, the ddms of a link shake hands
(:mod:`redistro.ddm.handshake`): the SSC's ddm signs with this run's key
from the start and sends a robot its records only once that robot's ESC
answered its hello; an ESC's ddm takes the run key from the SSC's proof,
and sends nothing before it.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import threading
import time
from typing import Any

import numpy as np

from redistro.config import Config
from redistro.ddm import record as wire
from redistro.ddm import wire_layout
from redistro.ddm.fast import FastPath
from redistro.ddm.handshake import Handshake
from redistro.ddm.transport import (
    ANSWERED,
    NO_ACCELERATOR,
    NOT_TAKEN,
    OWED,
    Accelerator,
    Transport,
    transport_class,
)
from redistro.errors import TransportError, WireError
from redistro.ipc.session import Manifest
from redistro.kernels import KERNELS
from redistro.localdata.block import Record
from redistro.localdata.layout import COMMAND, COUNTER, EXCHANGE, FEEDBACK, MANAGER, SessionStatus
from redistro.process import hooks
from redistro.process.spec import NodeSpec
from redistro.process.stats import Samples
from redistro.process.worker import Worker

REPLIED = 1 << 40  # ddm_reply: the usual step done whole
NOTHING = -errno.EAGAIN  # ... nothing had come


def _stamp_of(payload: memoryview) -> int:
    """The producer's stamp [ns] that starts a (decrypted) payload."""
    return int.from_bytes(payload[:8], "little", signed=True)


def link_id(spec: NodeSpec) -> str:
    """What the nodes of one robot group meet on (derived ports): the session
    id in a session; the ``link`` param of nodes started alone."""
    return spec.link


def link_key(cfg: Config, session_id: str) -> bytes:
    """The key that signs and checks this node's records: ``ddm.key_file``,
    else the session's own (made by the session owner in its runtime folder)."""
    path = cfg.ddm.key_file or str(Manifest.for_session(session_id).directory / wire.SESSION_KEY)
    return wire.load_key(path)


def open_transport(
    cfg: Config,
    session_id: str,
    link: str,
    node: str,
    kind: str,
    robots: list[str],
    key: bytes = b"",
) -> Transport:
    """The transport ``ddm.transport`` names, set up for this node's side
    (each transport reads its own part of the config)."""
    cls = transport_class(cfg.ddm.transport)
    return cls.for_node(cfg, session_id, link, node, kind, robots, key)


class Ddm(Worker):
    def __init__(
        self, spec: NodeSpec, index: int, ld: Any, transport: Transport | None = None
    ) -> None:
        """transport: this ddm's end, made elsewhere (unit tests hand in an
        in-process one, ``ddm.loopback``); None: ``ddm.transport`` from the
        config, opened in :meth:`initialize`."""
        super().__init__(spec, index, ld)
        self._given = transport
        # an ESC whose transport delivers on a thread of its own may answer
        # there (_answer): the step's state is then shared under this lock
        self.step_lock = threading.Lock()
        self.answering = False
        self.owed = False  # an answer's feedback the ddm's own step is to send
        self.answered_here = 0  # records the Python answer took whole
        # the compiled answer (``_compiled_answer``): its gate and counts
        # (GATE, ddm/wire_layout.py), and what runs before each record (a bench's
        # stand-in for the acquisition; None in a node)
        self.gate: Any = None
        self.before_answer: Any = None

    def initialize(self) -> None:
        self.cfg = self.spec.cfg()
        self.kind = self.spec.kind
        self.robots = list(self.spec.robots)
        self.gid = {r: list(self.cfg.robots).index(r) for r in self.robots}  # group-wide ids
        self.local = {g: i for i, g in enumerate(self.gid[r] for r in self.robots)}
        self.source = self.spec.node
        ld = self.ld
        self.manager_block = ld.block("manager")
        self.mgr = Record(MANAGER)
        self.estop_flag = self.manager_block.word("estop")
        n = len(self.robots)
        self.exchange_blocks = [ld.writer("exchange", i, role="ddm") for i in range(n)]
        self.ex = [Record(EXCHANGE) for _ in range(n)]
        self.fast: FastPath | None = None
        self.socket_kernels = False  # (see _plan_fast)
        self.replies_in_kernel = False
        self.publish_call: Any = None
        if self.kind == "esc":
            self.in_kind, self.out_kind = wire.KIND_COMMAND, wire.KIND_FEEDBACK
            self.in_blocks = [ld.writer("command", 0, role="ddm")]
            self.out_blocks = [ld.block("feedback", 0)]
            self.out_recs = [Record(FEEDBACK)]
            self.sent_block = ld.block("starving_sent")
            self.delivered_block = ld.writer("starving_delivered", role="ddm")
            self.sent_rec = Record(COUNTER)
            self.delivered_rec = Record(COUNTER)
        else:
            self.in_kind, self.out_kind = wire.KIND_FEEDBACK, wire.KIND_COMMAND
            self.in_blocks = [ld.writer("feedback", i, role="ddm") for i in range(n)]
            self.out_blocks = [ld.block("command", i) for i in range(n)]
            self.out_recs = [Record(COMMAND) for _ in range(n)]
        self.last_out: Any = [0] * n  # seq_src of the last record sent, per robot
        self.in_size = wire.PAYLOADS[self.in_kind].itemsize
        self.link_key = link_key(self.cfg, self.spec.session_id)
        self.handshake = Handshake(
            self.kind == "esc", self.link_key, self.spec.node, [self.gid[r] for r in self.robots]
        )
        # the key of this run's records: the SSC's from the start; an ESC's
        # comes with the SSC's proof (until then nothing verifies)
        self.key = self.handshake.run_key or os.urandom(wire.KEY_BYTES)
        self.encoders = [
            wire.Encoder(self.out_kind, self.gid[r], self.spec.node, self.key) for r in self.robots
        ]
        self.seq: Any = [0] * n  # the last wire seq sent, per robot
        self.admission = wire.Admission()
        self.latency = Samples()
        self.estop_sent = False
        self.commanded = False  # an ESC: the first command has come
        self.lost = False
        self.dirty = True  # exchange records not yet published
        self.urgent = True  # ... with a change of state (e-stop, link lost, the first record)
        self.steps = 0
        self.status_at = 0  # steps when the last status went out
        # the manager's limit on this ddm's silence (wait_s)
        self.heartbeat_cycles = self.me.heartbeat_limit_cycles or self.spec.heartbeat_limit_cycles
        self.transport: Transport = self._given or open_transport(
            self.cfg,
            self.spec.session_id,
            link_id(self.spec),
            self.spec.node,
            self.kind,
            self.robots,
            self.link_key,
        )
        self.refused_seen = 0
        self.stale_seen = 0
        self.greeted = self.kind == "esc"  # the SSC's hellos are not all answered yet
        self.shaken = False  # every local robot's handshake done (the usual step's test)
        # what acts on this ddm from outside (the fault harness; none normally)
        make = hooks.factory("ddm_hooks")
        self.hooks = make(self.spec.node, self.kind) if make else None
        if self.hooks is not None:
            names = {g: r for r, g in self.gid.items()}
            self.transport = self.hooks.transport(self.transport, names)
        self.links = self.transport.links  # (what the links do beside carrying records)
        self.accel: Accelerator = self.transport.accelerator or NO_ACCELERATOR
        self.links.verify_with(self._authentic)
        self.replying = self.kind == "esc" and self.transport.replies
        self.answer_gid = self.gid[self.robots[0]]
        # encrypted payloads take the Python path (the kernels copy payloads
        # into Local Data as they come)
        self.encrypt = self.cfg.ddm.encrypt
        self.cipher = wire.cipher_key(self.key) if self.encrypt and self.kind != "esc" else b""
        # (a fault harness's hooks keep it: their transport wrappers hand the
        # records over one by one, and a command fault corrupts what the
        # kernel admitted, _corrupt_command)
        self.corrupting = self.hooks is not None and self.hooks.corrupts_commands
        if KERNELS is not None and not self.encrypt:
            self._plan_fast(ld)
        for ex in self.ex:  # the acquisition wakes this ddm for every sample, until ...
            ex["feedback_wanted"] = 1

    def _plan_fast(self, ld: Any) -> None:
        """The compiled common case (:mod:`redistro.ddm.fast`), over records
        and counters the Python path shares."""
        n = len(self.robots)
        esc = self.kind == "esc"
        fast = FastPath(
            ld,
            [self.gid[r] for r in self.robots],
            [("command", 0)] if esc else [("feedback", i) for i in range(n)],
            [("feedback", 0)] if esc else [("command", i) for i in range(n)],
            self.in_kind,
            self.out_kind,
            self.spec.node,
            self.key,
            starving=esc,
            latency=self.latency,
        )
        self.fast = fast
        self.ex = fast.ex
        self.out_recs = fast.out
        self.seq = fast.seq
        self.last_out = fast.last_out
        # the robots in turn: the first send of a step wakes its ESC ddm on
        # the other CPU, the next robot's waits behind it (30-40 µs on two
        # vCPUs); a fixed order would make one robot the late one every cycle
        order = list(enumerate(self.gid[r] for r in self.robots))
        self.send_orders = (order, order[::-1])
        self.sends = 0
        # a transport on stream sockets: the records received and admitted,
        # and sent, by the kernels, without the interpreter between the
        # system calls and the records (ddm_recv, ddm_send)
        self.socket_kernels = self.accel.admit_with(fast.recv_call, fast.admit_plan, fast.state)
        self.send_generation = -1
        # an ESC that replies on a stream socket: its usual step is one
        # kernel call (ddm_reply: the command received and admitted, the
        # feedback emitted and sent back)
        self.replies_in_kernel = self.socket_kernels and self.replying
        self.publish_call = fast.publish_call
        self.publish_plan = fast.publish_plan
        if not self.socket_kernels:
            compiled = None
            if hasattr(KERNELS, "Answerer"):
                self.gate = np.zeros((), wire_layout.GATE)
                _, manager_at, _ = ld.block_offsets("manager")
                self.estop_at = manager_at + int(MANAGER.fields["estop"][1])  # type: ignore[index]
                compiled = self._compiled_answer
            self.answering = self.accel.answer_with(self._answer, compiled)
            self._open_gate()

    @property
    def answered(self) -> int:
        """Records taken whole in the transport's thread (by either answer)."""
        return self.answered_here + (0 if self.gate is None else int(self.gate["answered"]))

    def _open_gate(self) -> None:
        """The compiled answer's gate: open while this ddm answers, was
        commanded and has its link (the e-stop it reads itself)."""
        if self.gate is not None:
            commanded = self.commanded or self.kind != "esc"
            self.gate["open"] = int(self.answering and commanded and not self.lost)

    def _compiled_answer(self, put: Any, inbox: Any, fallback: Any, wake: Any) -> Any:
        """The answer in one compiled call (``_kernels.Answerer``), for the
        transport to hand each record to in its thread: what :meth:`_answer`
        does, over the same kernels, state and step lock, without the
        interpreter between them. ``put`` sends an ESC's reply (None: the
        SSC's side, which replies with nothing); a record it does not take
        goes to ``fallback(raw)`` (the transport's Python path); ``wake()``
        when the ddm's own step owes the reply."""
        fast = self.fast
        assert fast is not None and KERNELS is not None
        return KERNELS.Answerer(
            fast.admit_plan,
            fast.emit_plan,
            fast.publish_plan,
            self.gate,
            self.estop_at,
            self.step_lock,
            put,
            inbox,
            fallback,
            wake,
            self.before_answer,
        )

    # -- one tick --

    def fds(self) -> list[int]:
        return [] if self.lost else self.transport.fds()

    def wait_s(self) -> float:
        """The longest the ddm sleeps without a record, a wake or an e-stop:
        a node period, except in an ESC that answers in its transport's
        thread. There nothing is left for its own step to do on a deadline
        but sign its heartbeat (a lost link, an e-stop, a record it could
        not take each wake it at once), so it sleeps a quarter of its
        heartbeat limit (the rest is the margin for a stalled host), and
        wakes half a period away from the commands' arrival: out of the
        group's burst, where its step (150-200 µs of a vCPU, woken cold)
        held back the answers of every ESC on the host."""
        period = self.period_ns
        if not (self.kind == "esc" and self.answering and self.commanded and self.answered):
            return period / 1e9
        quiet = max(1, self.heartbeat_cycles // 4)
        phase = (time.monotonic_ns() - int(self.ex[0]["last_update_ns"])) % period
        # in whole milliseconds, as epoll waits (it rounds up: the wake's
        # lateness would read that rounding)
        return max(1, (quiet * period + period // 2 - phase) // 1_000_000) / 1e3

    def step(self, cycle: int) -> None:
        if self.answering:
            with self.step_lock:  # (zenoh's thread may be answering)
                self._step(cycle)
        else:
            self._step(cycle)

    def _step(self, cycle: int) -> None:
        if self.lost:
            return  # the managers see the data go stale (starving)
        estop = bool(self.estop_flag[0])  # the manager's e-stop, read alone
        try:
            if self.kind == "esc":
                if self.replies_in_kernel and self.commanded and not estop and self._reply():
                    self.steps += 1
                    if not self.steps & 63:
                        self._publish()
                    return
                fresh = self._receive()
                new_estop = estop and not self.estop_sent
                owed, self.owed = self.owed, False
                if self.gate is not None and self.gate["owed"]:
                    owed, self.gate["owed"] = True, 0
                if owed or not (self.replying and self.commanded and not fresh and not new_estop):
                    self._send(estop)  # (replying, feedback goes out with a command only)
            else:
                # the SSC sends first: the worker woke it for a fresh command,
                # which must not wait behind the feedback's admission
                self._send(estop)
                if not self.greeted:
                    self._greet()
                self._receive()
                self._check_links()  # the connecting side loses one robot's link at a time
        except TransportError as exc:
            # no retry: a lost link is a fault; the data stop and the
            # managers' starving checks end the session within their limits
            self.lost = True
            self._open_gate()
            for ex in self.ex:
                ex["link_lost"] = 1
                ex["fresh"] = 0
            if all(self._finished(i) for i in range(len(self.robots))):
                self.post(f"session finished, links closed: {exc}", logging.INFO)
            else:
                self.post(f"{exc}; no more exchange", logging.ERROR)
            self.dirty = True
            self.urgent = True
        self.steps += 1
        # the SSC's manager watches every robot's updates; an ESC's exchange
        # block is read at the end (and for its flags): its counters go out
        # every 64 steps, a change of state at once
        if self.dirty and (self.kind != "esc" or self.urgent or not self.steps & 63):
            self._publish()
        every = self.links.status_every
        steps = self.steps
        if self.gate is not None and self.kind == "esc":
            steps += int(self.gate["answered"])
        if every and steps - self.status_at >= every:
            # (by count: an ESC's answers in the transport's thread step the
            # count too, as the Python answer's do; the SSC's do not)
            self.status_at = steps
            self._status(estop)

    def _greet(self) -> None:
        """The SSC's side: a hello to each robot whose feedback has not come
        yet (every ``HELLO_EVERY_S``), until every robot's has."""
        now = time.monotonic_ns()
        waiting = False
        for i, g in enumerate(self.gid[r] for r in self.robots):
            if self.ex[i]["updates"]:
                self.links.authenticated(g)  # (its link brought this run's records)
                continue
            waiting = True
            if self.handshake.due(i, now) and self.links.can_send(g):
                self.transport.send(self.handshake.hello(g), g)
        self.links.flush()
        self.greeted = not waiting

    def _hello(self, raw: bytes, robot: int) -> None:
        """A hello of the handshake, signed with the link's key (checked)."""
        reply = self.handshake.take(robot, memoryview(raw)[wire.PAYLOAD_AT :])
        if reply is None:
            stale = self.handshake.stale
            if stale != self.stale_seen:
                for ex in self.ex:
                    ex["stale"] += stale - self.stale_seen
                    ex["dropped"] += stale - self.stale_seen
                self.stale_seen = stale
                self.dirty = True
                if self.kind == "esc":
                    self.links.drop_unauthenticated()  # not our SSC of this run
            return
        if reply.send:
            self.transport.send(reply.send, reply.gid)
            self.links.flush()
        if reply.run_key:
            self._take_run_key(reply.run_key)
        self.shaken = self.handshake.done

    def _authentic(self, raw: bytes) -> bool:
        """Whether a record is sound and signed (a hello with the link's key,
        the rest with this run's)."""
        hello = len(raw) == wire.SIZE and raw[6] == wire.KIND_HELLO
        try:
            wire.check(raw, self.link_key if hello else self.key)
        except WireError:
            return False
        return True

    def _take_run_key(self, key: bytes) -> None:
        """An ESC's side: the SSC's proof came; its records, and ours, are
        signed with this run's key from now on, and the link is pinned."""
        self.key = key
        if self.encrypt:
            self.cipher = wire.cipher_key(key)
        for enc in self.encoders:
            enc.rekey(key)
        if self.fast is not None:
            self.fast.rekey(key)
        self.links.authenticated()
        self.post("handshake done: this run's key taken from the SSC's proof", logging.DEBUG)
        self.urgent = self.dirty = True

    def _reply(self) -> bool:
        """An ESC's usual step on a stream socket, in one kernel call
        (``ddm_reply``): the command received and admitted, then the new
        feedback emitted and sent back as the reply. True when that was the
        whole step: nothing came, or whole records, every one admitted (the
        exchange counted, the starving index paid back, the latency taken by
        the kernel). Else the general path takes the step on, with what the
        call received."""
        fd = self.accel.reply_fd(self.ready_fds)
        if fd < 0:
            return False
        fast = self.fast
        assert fast is not None
        if self.accel.generation != self.send_generation:
            self._refresh_send_fds()
        got = fast.reply_call(fast.admit_plan, fast.emit_plan, fast.send_plan, self.accel.rx, fd)
        if got == REPLIED:
            self.dirty = True
            return True
        if got == NOTHING:
            return True
        return self._replied(got)

    def _answer(self, raw: bytes) -> int:
        """The ddm's usual step for one record, made in the transport's
        thread as it arrives (``Transport.answer_with``): the record
        admitted by the kernel; in an ESC, the newest feedback emitted and
        sent back as the reply; in the SSC, the exchange published (its
        manager watches every robot's updates). Anything else (the ddm
        stepping now, an ESC's first command, an e-stop, a record to
        refuse, a lost link) is the ddm's own step's: the record goes to
        its queue untouched."""
        if not self.step_lock.acquire(blocking=False):
            return NOT_TAKEN
        try:
            fast = self.fast
            if not self.answering or self.lost or self.estop_flag[0]:
                return NOT_TAKEN
            esc = self.kind == "esc"
            if esc and not self.commanded:
                return NOT_TAKEN
            assert fast is not None
            if fast.admit_call(fast.admit_plan, raw) < 0:
                return NOT_TAKEN
            self.dirty = True
            self.answered_here += 1
            if not esc:
                self._publish()
                return ANSWERED
            self.steps += 1
            mask = fast.emit_call(fast.emit_plan)
            if mask < 0:  # a torn read of the feedback: the ddm reads it again
                self.owed = True
                return OWED
            if mask:
                self.sends += 1
                try:
                    self.transport.send(bytes(fast.wire_views[0]), self.answer_gid)
                except TransportError:
                    return OWED  # (closed: the ddm's receive says so)
            if not self.steps & 63:
                self._publish()
            return ANSWERED
        finally:
            self.step_lock.release()

    def _replied(self, got: int) -> bool:
        """What ddm_reply did not take whole: the reply's trouble (a torn
        read of the feedback, a send not made whole), or a receive the
        general path takes on."""
        fast = self.fast
        assert fast is not None
        if not self.accel.received(got):
            return False
        self.dirty = True
        if fast.reply["trouble"]:
            self.accel.send_result(self.gid[self.robots[0]], int(fast.send_status[0]))
        elif fast.reply["emitted"] == -1:  # a torn read of the feedback: read it again
            self._send(False)
        return True

    def _refresh_send_fds(self) -> None:
        """Each robot's socket for the send kernels (a peer came or went)."""
        fast = self.fast
        assert fast is not None
        self.send_generation = self.accel.generation
        for i, robot in enumerate(self.gid[r] for r in self.robots):
            fast.send_fds[i] = self.accel.send_fd(robot)

    def _status(self, estop: bool) -> None:
        """The node's status for viewers on other hosts (off the hot path:
        once in ``status_every`` steps)."""
        import os
        import socket

        self.links.status(
            {
                "node": self.spec.node,
                "kind": self.kind,
                "robots": self.robots,
                "host": socket.gethostname(),
                "pid": os.getppid(),  # the node's manager
                "steps": self.steps,
                "updates": [int(ex["updates"]) for ex in self.ex],
                "estop": bool(estop),
                "lost": self.lost,
            }
        )

    def _corrupt_command(self, i: int) -> None:
        """The fault harness's command fault on what the kernel just
        admitted into robot i's block (the same point as the Python path's:
        after admission, before the node reads it)."""
        assert self.hooks is not None
        payload = self.in_blocks[i].read()
        bad = self.hooks.command(payload)
        if bad is not payload:
            self.in_blocks[i].publish(bad)

    def _check_links(self) -> None:
        """Robots whose link alone was lost (the SSC's side): their data go
        stale (the manager's starving check), the others' exchange goes on,
        the group's e-stop included."""
        for robot, why in self.links.lost_links().items():
            i = self.local.get(robot)
            if i is None or self.ex[i]["link_lost"]:
                continue
            self.ex[i]["link_lost"] = 1
            self.ex[i]["fresh"] = 0
            self.dirty = self.urgent = True
            if self._finished(i):
                # the session is over: the ESC ended its node and closed its end
                self.post(f"{why}; {self.robots[i]} done (session finished)", logging.INFO)
            else:
                self.post(f"{why}; {self.robots[i]} no longer exchanged", logging.ERROR)

    def _finished(self, i: int) -> bool:
        """The SSC's side: the last command sent to robot i said the session finished."""
        if self.kind == "esc":
            return False
        rec = self.out_recs[i]
        return int(rec["seq_src"]) > 0 and int(rec["session_status"]) == SessionStatus.FINISHED

    def _receive(self) -> int:
        """Admit what came; the number of fresh records."""
        fresh = 0
        received = self.transport.receive(self.ready_fds)
        taken = self.accel.taken  # (admitted as they came: ddm_recv)
        if taken:
            self.dirty = True
        refused = self.links.refused()
        if refused != self.refused_seen:
            for ex in self.ex:
                ex["foreign"] += refused - self.refused_seen
            self.refused_seen = refused
            self.dirty = self.urgent = True
        fast = self.fast
        size, hello, in_kind, gids = wire.SIZE, wire.KIND_HELLO, self.in_kind, self.local
        keyless = not self.handshake.run_key  # an ESC before the SSC's proof
        for raw in received:
            self.dirty = True
            if fast is not None:
                i = fast.admit_call(fast.admit_plan, raw)
                if i >= 0:
                    taken += 1  # admitted, published and counted (FastPath.admit)
                    if self.corrupting:
                        self._corrupt_command(i)
                    continue
            if (
                keyless
                and len(raw) == size
                and raw[6] != hello
                and (raw[6] != in_kind or raw[7] not in gids)
            ):
                continue  # another robot's traffic: without the run key, not ours to judge
            # every record is checked (another node's traffic on a broadcast
            # medium too: a forgery is counted whoever it claims to be);
            # hellos are signed with the link's key, the rest with the run's
            key = self.link_key if len(raw) == size and raw[6] == hello else self.key
            try:
                kind, robot, source, seq, stamp, estop = wire.check(raw, key)
            except WireError as exc:
                field = "forged" if exc.reason == "auth" else "malformed"
                for ex in self.ex:
                    ex[field] += 1
                    ex["dropped"] += 1
                if field == "forged" and self.kind == "esc":
                    # not the SSC: whoever holds the link goes (a new
                    # connection may take it: the SSC reconnecting)
                    self.links.drop_unauthenticated()
                continue
            if kind == wire.KIND_HELLO:
                self._hello(raw, robot)
                continue
            i = self.local.get(robot)
            if kind != self.in_kind or i is None:
                continue  # another node's traffic on a broadcast medium (authentic)
            ex = self.ex[i]
            if fast is not None:
                why = fast.refuse(self.admission, i, source, kind, robot, seq, stamp)
            else:
                why = self.admission.refuse(source, kind, robot, seq, stamp)
            if why:
                ex[why] += 1
                ex["dropped"] += 1
                continue
            self.links.authenticated()
            now = time.monotonic_ns()
            if estop and not ex["estop_in"]:
                self.urgent = True
                name = source.rstrip(b"\0")
                ex["estop_in"] = 1
                ex.array["estop_source"] = name[:16]
                self.post(f"e-stop from {name.decode(errors='replace')}", logging.ERROR)
                self.estop_request = True
            payload: Any = memoryview(raw)[wire.PAYLOAD_AT : wire.PAYLOAD_AT + self.in_size]
            if self.cipher:
                payload = memoryview(wire.crypt(self.cipher, kind, robot, seq, payload))
            if self.hooks is not None:
                payload = self.hooks.command(payload)
            self.in_blocks[i].publish(payload)
            fresh += 1
            if not ex["fresh"]:
                self.urgent = True
            if not self.commanded:
                self.commanded = True
                self._open_gate()
                if self.replying:  # ... feedback goes out as the replies to commands
                    ex["feedback_wanted"] = 0
            ex["updates"] += 1
            ex["last_update_ns"] = now
            ex["fresh"] = 1
            if self.kind == "esc":
                # a fresh command pays back every command the sender sent on
                # the strength of the old one
                self.sent_block.read_into(self.sent_rec.bytes)
                self.delivered_rec["count"] = self.sent_rec["count"]
                self.delivered_rec["stamp_ns"] = now
                self.delivered_block.publish(self.delivered_rec.bytes)
                stamp = wire.payload_stamp(raw) if not self.cipher else _stamp_of(payload)
                if 0 < stamp <= now:
                    if fast is not None:
                        fast.add_latency(now - stamp)
                    else:
                        self.latency.add(now - stamp)
        if taken:
            self.links.authenticated()
        return fresh + taken

    def _send(self, estop: bool) -> None:
        proven = self.handshake.proven
        if not self.shaken and not any(proven):
            return  # nobody may take our records yet (the handshake)
        if self.fast is not None and not estop:
            mask = self.fast.emit_call(self.fast.emit_plan)  # FastPath.emit
            if mask >= 0:  # else a torn read: the Python path reads again
                if not self.shaken:  # only to the robots shaken hands with
                    mask &= sum(1 << i for i, ok in enumerate(proven) if ok)
                if mask:
                    self.sends += 1
                    if self.socket_kernels:
                        self._send_kernel(mask)
                    else:
                        views = self.fast.wire_views
                        for i, robot in self.send_orders[self.sends & 1]:
                            if mask >> i & 1:
                                self.transport.send(bytes(views[i]), robot)
                        self.links.flush()
                    self.dirty = True
                return
        for i, (block, rec) in enumerate(zip(self.out_blocks, self.out_recs, strict=True)):
            if not self.shaken and not proven[i]:
                continue  # (the handshake)
            block.read_into(rec.bytes)
            produced = int(rec["seq_src"])
            if produced == 0 and not estop:
                continue  # nothing produced yet
            if produced == self.last_out[i] and (not estop or self.estop_sent):
                continue
            self._send_one(i, rec, estop)
            self.last_out[i] = produced
        self.links.flush()
        if estop:
            self.estop_sent = True

    def _send_kernel(self, mask: int) -> None:
        """The records emitted (mask) sent on their sockets by ddm_send, the
        robots in turn; what it could not send whole goes to the transport."""
        fast = self.fast
        assert fast is not None
        transport = self.transport
        if self.accel.generation != self.send_generation:  # a peer came or went
            self._refresh_send_fds()
        trouble = fast.send_call(fast.send_plan, mask, self.sends & 1)
        if trouble:
            for i, robot in self.send_orders[0]:
                if trouble >> i & 1:
                    result = int(fast.send_status[i])
                    if result == 0:  # no socket: the transport's own send counts it
                        transport.send(bytes(fast.wire_views[i]), robot)
                    else:
                        self.accel.send_result(robot, result)

    def _send_one(self, i: int, rec: Record, estop: bool) -> None:
        self.seq[i] += 1
        payload: Any = rec.bytes
        if self.cipher:
            payload = wire.crypt(self.cipher, self.out_kind, self.gid[self.robots[i]],
                                 self.seq[i], payload)  # fmt: skip
        data = self.encoders[i].encode(self.seq[i], time.monotonic_ns(), payload, estop)
        self.transport.send(data, self.gid[self.robots[i]])
        self.ex[i]["sent"] += 1
        self.dirty = True

    def _publish(self) -> None:
        if self.publish_call is not None:  # the kernels' arena, in one call
            self.publish_call(self.publish_plan)
        else:
            for block, ex in zip(self.exchange_blocks, self.ex, strict=True):
                block.publish(ex.bytes)
        self.dirty = self.urgent = False

    def cleanup(self) -> None:
        with self.step_lock:
            self.answering = False  # the transport's thread answers no more
            self._open_gate()
        with contextlib.suppress(Exception):
            self.manager_block.read_into(self.mgr.bytes)
            if self.mgr["estop"] and not self.lost:
                # the node ended on a fault: tell every peer, once more
                for i, (block, rec) in enumerate(zip(self.out_blocks, self.out_recs, strict=True)):
                    if self.handshake.proven[i]:
                        block.read_into(rec.bytes)
                        self._send_one(i, rec, True)
                self.links.flush()
        if self.fast is not None:
            self.latency.count = self.fast.latency_count()
        lat = self.latency.summary_us()
        for ex in self.ex:
            ex.array["latency_us"] = np.array([lat["p50"], lat["p99"], lat["max"]])
            ex["latency_n"] = self.latency.count
            ex["fresh"] = 0
        with contextlib.suppress(Exception):
            self._publish()
        with contextlib.suppress(Exception):
            self.transport.close()

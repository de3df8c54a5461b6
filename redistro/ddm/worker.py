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
call (the C ``_kernels.CompiledAnswer``), else by its Python reference
(:mod:`redistro.ddm.answer`). The step's state is shared under one lock,
and whatever the answer does not take whole goes to the ddm's own step.

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
import logging
import os
import time
from typing import Any

import numpy as np

from redistro.config import Config
from redistro.ddm import record as wire
from redistro.ddm.admit import PythonAdmission
from redistro.ddm.answer import ThreadAnswer
from redistro.ddm.greeting import Greeting
from redistro.ddm.handshake import Handshake
from redistro.ddm.kernel_path import KernelPath
from redistro.ddm.socket_steps import SocketSteps
from redistro.ddm.transport import (
    NO_ACCELERATOR,
    Accelerator,
    Transport,
    transport_class,
)
from redistro.errors import TransportError
from redistro.ipc.bell import Ringer
from redistro.ipc.session import Manifest
from redistro.kernels import KERNELS
from redistro.localdata.block import Record
from redistro.localdata.layout import COMMAND, COUNTER, EXCHANGE, FEEDBACK, MANAGER, SessionStatus
from redistro.process import hooks
from redistro.process.spec import NodeSpec
from redistro.process.stats import Samples
from redistro.process.worker import Worker


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
        # there: the step's state is then shared under its lock
        self.answers = ThreadAnswer(self)

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
        self.kernel_path: KernelPath | None = None
        self.socket_kernels = False  # (see _plan_fast)
        self.replies_in_kernel = False
        self.publish_call: Any = None
        self._ends(n)
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
        self._open_transport()
        for ex in self.ex:  # the acquisition wakes this ddm for every sample, until ...
            ex["feedback_wanted"] = 1

    def _ends(self, n: int) -> None:
        """The Local Data blocks records come into and go out from."""
        ld = self.ld
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

    def _open_transport(self) -> None:
        """This ddm's end of the link (wrapped by a fault harness's hooks),
        its links and accelerator, and the compiled path over it."""
        ld = self.ld
        # what acts on this ddm from outside (the fault harness; none normally)
        make = hooks.factory("ddm_hooks")
        self.hooks = make(self.spec.node, self.kind) if make else None
        if self.hooks is not None:
            self.hooks.before_open()
        s = self.spec
        self.transport: Transport = self._given or open_transport(
            self.cfg, s.session_id, link_id(s), s.node, self.kind, self.robots, self.link_key
        )
        self.refused_seen = 0
        self.greeting = Greeting(self)
        self.python_admission = PythonAdmission(self)
        self.socket_steps = SocketSteps(self)
        self.greeted = self.kind == "esc"  # the SSC's hellos are not all answered yet
        self.shaken = False  # every local robot's handshake done (the usual step's test)
        if self.hooks is not None:
            names = {g: r for r, g in self.gid.items()}
            self.transport = self.hooks.transport(self.transport, names)
        self.links = self.transport.links  # (what the links do beside carrying records)
        self.accel: Accelerator = self.transport.accelerator or NO_ACCELERATOR
        self.links.verify_with(self.greeting.authentic)
        # (in lockstep an ESC sends each sample as it comes, replying or not:
        # the plant waits for it before the SSC's tick; a receive rings it)
        lockstep = self.spec.clock == "lockstep"
        self.replying = self.kind == "esc" and self.transport.replies and not lockstep
        self.ring = Ringer(self.spec.session_id).ring if lockstep else None
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

    def _plan_fast(self, ld: Any) -> None:
        """The compiled common case (:mod:`redistro.ddm.kernel_path`), over records
        and counters the Python path shares."""
        n = len(self.robots)
        esc = self.kind == "esc"
        kpath = KernelPath(
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
        self.kernel_path = kpath
        self.ex = kpath.ex
        self.out_recs = kpath.out
        self.seq = kpath.seq
        self.last_out = kpath.last_out
        # the robots in turn: the first send of a step wakes its ESC ddm on
        # the other CPU, the next robot's waits behind it (30-40 µs on two
        # vCPUs); a fixed order would make one robot the late one every cycle
        order = list(enumerate(self.gid[r] for r in self.robots))
        self.send_orders = (order, order[::-1])
        self.sends = 0
        # a transport on stream sockets: the records received and admitted,
        # and sent, by the kernels, without the interpreter between the
        # system calls and the records (ddm_recv, ddm_send)
        self.socket_kernels = self.accel.admit_with(kpath.recv_call, kpath.admit_plan, kpath.state)
        # an ESC that replies on a stream socket: its usual step is one
        # kernel call (ddm_reply: the command received and admitted, the
        # feedback emitted and sent back)
        self.replies_in_kernel = self.socket_kernels and self.replying
        if self.replies_in_kernel:
            self.socket_steps.bind(kpath, self.accel)
        self.publish_call = kpath.publish_call
        self.publish_plan = kpath.publish_plan
        if not self.socket_kernels and self.ring is None:  # (lockstep: the step rings)
            self.answers.offer(ld)

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
        if not (self.kind == "esc" and self.answers.on and self.commanded and self.answers.taken):
            return period / 1e9
        quiet = max(1, self.heartbeat_cycles // 4)
        phase = (time.monotonic_ns() - int(self.ex[0]["last_update_ns"])) % period
        # in whole milliseconds, as epoll waits (it rounds up: the wake's
        # lateness would read that rounding)
        return max(1, (quiet * period + period // 2 - phase) // 1_000_000) / 1e3

    def step(self, cycle: int) -> None:
        # (the usual ESC over sockets is tested first: nobody else answers)
        if not self.replies_in_kernel and self.answers.on:
            with self.answers.lock:  # (zenoh's thread may be answering)
                self._step(cycle)
        else:
            self._step(cycle)

    def _step(self, cycle: int) -> None:
        if self.lost:
            return  # the managers see the data go stale (starving)
        estop = bool(self.estop_flag[0])  # the manager's e-stop, read alone
        try:
            if self.kind == "esc":
                if (
                    self.replies_in_kernel
                    and self.commanded
                    and not estop
                    and self.socket_steps.reply()
                ):
                    self.steps += 1
                    if not self.steps & 63:
                        self._publish()
                    return
                fresh = self._receive()
                new_estop = estop and not self.estop_sent
                owed = self.answers.take_owed()
                if owed or not (self.replying and self.commanded and not fresh and not new_estop):
                    self._send(estop)  # (replying, feedback goes out with a command only)
            else:
                # the SSC sends first: the worker woke it for a fresh command,
                # which must not wait behind the feedback's admission
                self._send(estop)
                if not self.greeted:
                    self.greeting.greet()
                self._receive()
                self._check_links()  # the connecting side loses one robot's link at a time
        except TransportError as exc:
            # no retry: a lost link is a fault; the data stop and the
            # managers' starving checks end the session within their limits
            self.lost = True
            self.answers.open_state()
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
        if self.answers.state is not None and self.kind == "esc":
            steps += int(self.answers.state["answered"])
        if every and steps - self.status_at >= every:
            # (by count: an ESC's answers in the transport's thread step the
            # count too, as the Python answer's do; the SSC's do not)
            self.status_at = steps
            self.links.status(status_doc(self, estop))  # (for viewers on other hosts)

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
        kpath = self.kernel_path
        for raw in received:
            self.dirty = True
            if kpath is not None:
                i = kpath.admit_call(kpath.admit_plan, raw)
                if i >= 0:
                    taken += 1  # admitted, published and counted (KernelPath.admit)
                    if self.corrupting:
                        self._corrupt_command(i)
                    continue
            fresh += self.python_admission.take(raw)
        if taken:
            self.links.authenticated()
        if (fresh or taken) and self.ring is not None:
            self.ring()  # (lockstep: the plant may wait for these)
        return fresh + taken

    def _send(self, estop: bool) -> None:
        proven = self.handshake.proven
        if not self.shaken and not any(proven):
            return  # nobody may take our records yet (the handshake)
        if self.kernel_path is not None and not estop:
            mask = self.kernel_path.emit_call(self.kernel_path.emit_plan)  # KernelPath.emit
            if mask >= 0:  # else a torn read: the Python path reads again
                if not self.shaken:  # only to the robots shaken hands with
                    mask &= sum(1 << i for i, ok in enumerate(proven) if ok)
                if mask:
                    self.sends += 1
                    if self.socket_kernels:
                        self.socket_steps.send(mask)
                    else:
                        views = self.kernel_path.wire_views
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
        with self.answers.lock:
            self.answers.on = False  # the transport's thread answers no more
            self.answers.open_state()
        with contextlib.suppress(Exception):
            self.manager_block.read_into(self.mgr.bytes)
            if self.mgr["estop"] and not self.lost:
                # the node ended on a fault: tell every peer, once more
                for i, (block, rec) in enumerate(zip(self.out_blocks, self.out_recs, strict=True)):
                    if self.handshake.proven[i]:
                        block.read_into(rec.bytes)
                        self._send_one(i, rec, True)
                self.links.flush()
        if self.kernel_path is not None:
            self.latency.count = self.kernel_path.latency_count()
        lat = self.latency.summary_us()
        for ex in self.ex:
            ex.array["latency_us"] = np.array([lat["p50"], lat["p99"], lat["max"]])
            ex["latency_n"] = self.latency.count
            ex["fresh"] = 0
        with contextlib.suppress(Exception):
            self._publish()
        with contextlib.suppress(Exception):
            self.transport.close()


def status_doc(d: Ddm, estop: bool) -> dict[str, object]:
    """What viewers (``redistro top --zenoh``) see of a node."""
    import socket

    return {
        "node": d.spec.node,
        "kind": d.kind,
        "robots": d.robots,
        "host": socket.gethostname(),
        "pid": os.getppid(),  # the node's manager
        "steps": d.steps,
        "updates": [int(ex["updates"]) for ex in d.ex],
        "estop": bool(estop),
        "lost": d.lost,
    }

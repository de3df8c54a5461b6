"""Lockstep: the plant paces the nodes (``session.clock: lockstep``).

In a real-time session every manager ticks on its interval timer and the
plant steps on the wall clock. In lockstep the plant is the clock: it
ticks every node of the running group (a SIGALRM to its manager, the
signal its interval timer would send), steps ``physics_hz / rate_hz``
physics steps, and waits until the tick's work is over before the next.
A tick goes in two phases, in a fixed order:

1. the ESCs: each manager took the tick, its on-cycle workers signed it
   (acquisition: the sample of this step; sender: the command of the
   SSC's last cycle to the boards), and the sample reached the SSC's
   Local Data (``feedback[r].step``);
2. the SSC, while the physics steps to the next tick (it reads no
   board): its worker signed the tick, and its command reached each
   ESC's Local Data (``command[0].seq_src``).

Nothing else changes: every process, semaphore, Local Data segment and
DDM is the one a real-time session runs. The session owner names the
group's nodes in ``lockstep.json`` in the session's runtime folder; until
every one of them is in its Routine and every DDM link has shaken hands,
the plant serves the boards (brakes, encoder presets) without stepping
the physics, so the first tick comes after the same state in every run.
A node that ends (its work done, a fault) leaves the group; a wait that
is not met within ``WAIT_S`` (a hung or stopped process) lets the tick
go on, and the node's own heartbeat check finds the culprit. A node whose
process is runnable then, only starved of CPU by a loaded host, is
waited for again, up to ``WAIT_MAX_S``.
"""

from __future__ import annotations

import json
import os
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from redistro.errors import TornReadTimeout
from redistro.ipc import sched
from redistro.ipc.bell import LOOK_S
from redistro.localdata.layout import ProcState
from redistro.localdata.view import NodeView
from redistro.log.ring import Progress

NODES_FILE = "lockstep.json"  # in the session's runtime folder: the group's nodes
# the longest a phase waits for a node (a hung one: its heartbeat check);
# a node at the default scheduling was once starved over 0.5 s on a loaded
# host, and the tick stepped without it (a run no longer the same to the bit)
WAIT_S = 2.0
# ... and again while the node is runnable, only starved of CPU (a loaded
# host: a real-time session beside it), or its log still drains, up to this
WAIT_MAX_S = 60.0
LIVE = (int(ProcState.ROUTINE), int(ProcState.IDLE))
# how often the plant looks for a group coming up (the boards are served
# every millisecond meanwhile): each look attaches every node's segment
LOOK_UP_NS = 10_000_000


def write_nodes(folder: Path, nodes: list[str], rate_hz: float) -> None:
    """The session owner's word to the plant: the group now starting."""
    from redistro import files

    doc = {"nodes": nodes, "rate_hz": rate_hz}
    files.replace(folder / NODES_FILE, json.dumps(doc) + "\n")


class Counter:
    """One counter of a node's Local Data as a watcher polls it: a single
    load of the word first (cheap, and false nearly always), then, when it
    seems there, the word again under the block's seqlock (a bare load may
    see it half written)."""

    def __init__(self, view: NodeView, block: str, index: int | None, name: str) -> None:
        self.block = view.block(block, index)
        self.name = name
        self.word = self.block.counter(name)

    def value(self) -> int:
        """The counter, consistent (under its block's seqlock); -1 when its
        writer stayed inside a write (held off by the host): look again."""
        if self.word is not None:
            for _ in range(8):
                v = self.block.load(self.word)
                if v is not None:
                    return v
        try:
            return int(self.block.read()[self.name])
        except TornReadTimeout:
            return -1

    def at_least(self, target: int) -> bool:
        if self.word is not None and self.word[0] < target:
            return False
        return self.value() >= target

    def equals(self, other: Counter) -> bool:
        if self.word is not None and other.word is not None and self.word[0] != other.word[0]:
            return False
        a = self.value()
        return a >= 0 and a == other.value()


@dataclass
class _Node:
    name: str
    view: NodeView
    pid: int
    on_cycle: list[int]  # proc rows of the workers on the cycle
    ddm: bool  # the node has a ddm (its robots' data cross to another node)
    live: bool = True
    counters: list[Counter] = field(default_factory=list)  # its cycle, its workers' heartbeats
    log: Any = None  # its log ring's progress (redistro.log.ring.Progress), if it logs
    pids: list[int] = field(default_factory=list)  # its manager's and workers'

    def __post_init__(self) -> None:
        self.state_word = self.view.block("manager").word("state")
        self.counters = [Counter(self.view, "manager", None, "cycle")]
        self.counters += [Counter(self.view, "proc", j, "heartbeat_cycle") for j in self.on_cycle]

    def state(self) -> int:
        return int(self.state_word[0])

    def signed(self, cycle: int) -> bool:
        """The manager took tick ``cycle`` and every on-cycle worker signed it."""
        return all(c.at_least(cycle) for c in self.counters)


@dataclass
class Group:
    """The nodes the plant ticks, and what each phase waits for."""

    session_id: str
    escs: list[_Node] = field(default_factory=list)
    ssc: _Node | None = None
    cycle: int = 0
    waits_missed: int = 0  # phases that gave up (a node hung or ended)
    missed: list[dict[str, Any]] = field(default_factory=list)  # the first ones: tick, phase
    samples: list[tuple[_Node, Counter, Counter]] = field(default_factory=list)
    commands: list[tuple[_Node, Counter, Counter]] = field(default_factory=list)
    # what the plant does while it waits: the CAN backplane's frames
    # answered (the drivers read and write during their tick); else a nap
    pause: Any = None
    bell: Any = None  # the nodes' bell (redistro.ipc.bell): else a look every 20 µs
    rung: int = 0  # waits woken by the bell
    unrung: int = 0  # ... and by its look anyway (LOOK_S): a phase no node rang for
    period_ns: int = 0  # the nodes' period: a paused task's ticks come no faster
    pace_ns: int = 0  # session.lockstep_pace: no tick sooner after the last (0: at once)
    paused_word: Any = None  # the SSC's plan: the operator paused the task
    last_ns: int = 0  # when the last tick began
    paced: int = 0  # ticks held back to the wall clock (the task paused, or the pace)

    def nodes(self) -> list[_Node]:
        return [*self.escs, *([self.ssc] if self.ssc is not None else [])]

    def close(self) -> None:
        for n in self.nodes():
            n.view.close()
            if n.log is not None:
                n.log.close()

    @classmethod
    def open(cls, session_id: str, names: list[str]) -> Group | None:
        """The group once every node is in its Routine (None: not yet)."""
        g = cls(session_id)
        for name in names:
            view = NodeView.open(session_id, name)
            if view is None:
                g.close()
                return None
            node = _node(name, view)
            if node is None:
                view.close()
                g.close()
                return None
            node.log = Progress.attach(session_id, name)
            if name == "ssc":
                g.ssc = node
                g.paused_word = _paused_word(view)
            else:
                g.escs.append(node)
        return g

    def linked(self) -> bool:
        """Every DDM link has shaken hands (records may flow both ways)."""
        if self.ssc is None:
            return True
        if not self.samples:
            self._crossings()
        try:
            for i, esc in enumerate(self.escs):
                if not esc.ddm or not int(esc.view.read("exchange", 0)["linked"]):
                    return False
                if not int(self.ssc.view.read("exchange", i)["linked"]):
                    return False
        except TornReadTimeout:
            return False  # (a writer held off: look again)
        return True

    def tick(self, step: Any) -> None:
        """One tick of every node, phase by phase, and ``step()``, the
        physics to the next tick; returns once all is over. The physics
        steps while the SSC runs: they need only the senders' outputs of
        this tick, and the SSC reads nothing of the boards."""
        if self.logging:
            self._wait(self._logs_kept, "logs")
        if self.paused_word is not None and self.paused_word[0] and self.period_ns:
            self._pace(self.last_ns + max(self.period_ns, self.pace_ns))
        elif self.pace_ns:
            self._pace(self.last_ns + self.pace_ns)
        self.last_ns = time.monotonic_ns()
        if self.bell is not None:  # (rings of the last tick after its waits: stale)
            while self.bell.try_acquire():
                pass
        self.cycle += 1
        k = self.cycle
        _send(self.escs)
        self._wait(lambda: all(n.signed(k) for n in self._live(self.escs)), "escs")
        if self.ssc is None or not self.ssc.live:
            step()
            return
        self._wait(self._feedback_in, "feedback")
        _send([self.ssc])
        step()
        self._wait(lambda: self.ssc is None or not self.ssc.live or self.ssc.signed(k), "ssc")
        self._wait(self._commands_in, "commands")

    def _pace(self, due_ns: int) -> None:
        """A tick held to the wall clock waits for its time: a paused task's
        (the operator's hand, a jog, a look at the arms, works in wall time,
        and the group held still needs no CPU), and with a pace every tick
        (a run watched live)."""
        self.paced += 1
        while (now := time.monotonic_ns()) < due_ns:
            if self.pause is not None:
                self.pause(due_ns)
            else:
                time.sleep((due_ns - now) / 1e9)

    def _live(self, nodes: list[_Node]) -> list[_Node]:
        for n in nodes:
            if n.live and n.state() not in LIVE:
                n.live = False
        return [n for n in nodes if n.live]

    def _crossings(self) -> None:
        """Each robot's sample at its ESC and at the SSC; its command at the
        SSC and at its ESC."""
        assert self.ssc is not None
        ssc = self.ssc.view
        self.samples = [
            (e, Counter(e.view, "feedback", 0, "step"), Counter(ssc, "feedback", i, "step"))
            for i, e in enumerate(self.escs)
        ]
        self.commands = [
            (e, Counter(ssc, "command", i, "seq_src"), Counter(e.view, "command", 0, "seq_src"))
            for i, e in enumerate(self.escs)
        ]

    @property
    def logging(self) -> bool:
        return any(n.log is not None for n in self.nodes())

    def _logs_kept(self) -> bool:
        """No logging worker is more than half its ring behind (its writer
        starved of CPU by ticks as fast as the CPUs allow: the ring would
        overwrite cycles not yet logged, and the log would differ run to run)."""
        return all(n.log.lag() <= n.log.slots // 2 for n in self.nodes() if n.live and n.log)

    def _feedback_in(self) -> bool:
        return all(a.equals(b) for e, a, b in self.samples if e.live)

    def _commands_in(self) -> bool:
        return all(a.equals(b) for e, a, b in self.commands if e.live)

    def _wait(self, done: Any, phase: str) -> None:
        start = time.monotonic()
        deadline = start + WAIT_S
        lags = None
        while not done():
            now = time.monotonic()
            if now > deadline:
                if now < start + WAIT_MAX_S and self._going(phase, lags):
                    deadline, lags = now + WAIT_S, self._lags()
                    continue
                self.waits_missed += 1
                if len(self.missed) < 10:  # (which tick, phase and nodes: the plant's report)
                    self.missed.append(
                        {"tick": self.cycle, "phase": phase, "nodes": self._behind(phase)}
                    )
                return
            if not self._live(self.nodes()):
                return
            if self.pause is not None:
                self.pause(time.monotonic_ns() + 200_000)
            elif self.bell is not None:
                if self.bell.acquire(LOOK_S):  # a node rang, or a look anyway
                    self.rung += 1
                else:
                    self.unrung += 1
            else:
                time.sleep(20e-6)  # the nodes run above the plant: let them

    def _behind(self, phase: str) -> list[str]:
        """The nodes a phase still waits for."""
        k = self.cycle
        if phase == "escs":
            return [n.name for n in self._live(self.escs) if not n.signed(k)]
        if phase == "ssc":
            return [n.name for n in self._live([self.ssc] if self.ssc else []) if not n.signed(k)]
        if phase in ("feedback", "commands"):
            pairs = self.samples if phase == "feedback" else self.commands
            return [e.name for e, a, b in pairs if e.live and not a.equals(b)]
        return [n.name for n in self.nodes() if n.log and n.log.lag() > n.log.slots // 2]

    def _lags(self) -> list[int]:
        return [n.log.lag() for n in self.nodes() if n.log is not None]

    def _going(self, phase: str, lags: list[int] | None) -> bool:
        """Whether a wait past ``WAIT_S`` is a node starved of CPU, not hung:
        one of the nodes' processes is runnable (a stopped or blocked one is
        not); for the logs, one drained since the last look (a first look:
        yes)."""
        if phase == "logs":
            return lags is None or self._lags() != lags
        return any(n.live and any(sched.runnable(pid) for pid in n.pids) for n in self.nodes())

    def over(self) -> bool:
        """Every node of the group has ended (or left its Routine)."""
        return not self._live(self.nodes())


def _paused_word(view: NodeView) -> Any:
    """The SSC's first plan row's ``paused`` flag (every row carries it)."""
    try:
        return view.block("plan", 0).word("paused")
    except (KeyError, IndexError, ValueError):
        return None


def _node(name: str, view: NodeView) -> _Node | None:
    """A node's handle, once its manager waits for its first tick."""
    try:
        m = view.manager()
        if int(m["state"]) not in LIVE or int(m["cycle"]) != 0:
            return None
        static = view.static
        stages = [int(s) for s in static["proc_stage"]]
        roles = view.ld.proc_roles()
        pids = [int(view.read("proc", j)["pid"]) for j in range(len(roles))]
    except Exception:
        return None
    on_cycle = [j for j, s in enumerate(stages[: len(roles)]) if s >= 0]
    node = _Node(name, view, int(m["pid"]), on_cycle, "ddm" in roles)
    node.pids = [node.pid, *(p for p in pids if p > 0)]
    return node


def _send(nodes: list[_Node]) -> None:
    for n in nodes:
        if n.live:
            try:
                os.kill(n.pid, signal.SIGALRM)
            except ProcessLookupError:
                n.live = False


class Conductor:
    """The plant's side of lockstep: which group runs, and when it ticks."""

    def __init__(
        self, session_id: str, folder: Path | None, physics_hz: float, pace: float = 0.0
    ) -> None:
        self.session_id = session_id
        self.path = folder / NODES_FILE if folder is not None else None
        self.physics_hz = physics_hz
        self.pace = pace  # session.lockstep_pace
        self.seen_ns = 0
        self.names: list[str] = []
        self.rate_hz = 0.0
        self.group: Group | None = None
        self.groups = 0  # groups run so far (each starts the plant's noise afresh)
        self.ticks = 0
        self.waits_missed = 0
        self.missed: list[dict[str, Any]] = []
        self.paced = 0
        self.pause: Any = None  # (Group.pause)
        self.bell: Any = None  # (Group.bell)
        self.rung = self.unrung = 0
        self.looked_ns = 0  # when ready() last looked for a group coming up

    @property
    def steps_per_tick(self) -> int:
        return max(1, round(self.physics_hz / self.rate_hz)) if self.rate_hz else 1

    def ready(self) -> bool:
        """A group is running, or has just come up (every node in its
        Routine, every link shaken hands)."""
        if self.group is not None:
            if not self.group.over():
                return True
            self._end_group()
        now = time.monotonic_ns()
        if now - self.looked_ns < LOOK_UP_NS:
            return False
        self.looked_ns = now
        self._read_names()
        if not self.names:
            return False
        g = Group.open(self.session_id, self.names)
        if g is None:
            return False
        if not g.linked():
            g.close()
            return False
        g.pause = self.pause
        g.bell = self.bell
        g.period_ns = round(1e9 / self.rate_hz) if self.rate_hz else 0
        g.pace_ns = round(g.period_ns / self.pace) if self.pace else 0
        self.group = g
        self.groups += 1
        self.names = []  # (a group runs once)
        return True

    def tick(self, step: Any) -> None:
        """A tick of the group, ``step()`` stepping the physics to the next."""
        assert self.group is not None
        self.group.tick(step)
        self.ticks += 1

    def _end_group(self) -> None:
        if self.group is not None:
            self.waits_missed += self.group.waits_missed
            self.missed += self.group.missed[: 10 - len(self.missed)]
            self.paced += self.group.paced
            self.rung += self.group.rung
            self.unrung += self.group.unrung
            self.group.close()
            self.group = None

    def _read_names(self) -> None:
        if self.path is None:
            return
        try:
            st = self.path.stat()
        except OSError:
            return
        if st.st_mtime_ns == self.seen_ns:
            return
        self.seen_ns = st.st_mtime_ns
        try:
            doc = json.loads(self.path.read_text())
            self.names = [str(n) for n in doc["nodes"]]
            self.rate_hz = float(doc["rate_hz"])
        except (OSError, ValueError, KeyError, TypeError):
            self.names = []

    def close(self) -> None:
        self._end_group()

    def report(self) -> dict[str, Any]:
        return {
            "groups": self.groups,
            "ticks": self.ticks,
            "waits_missed": self.waits_missed,
            "missed": self.missed,
            "paced_ticks": self.paced,
            "bell": {"rung": self.rung, "unrung": self.unrung},
        }

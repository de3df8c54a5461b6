"""A manager's states and what moves it between them.

A node's manager goes through the runtime's four states (DESIGN: the
process model): Initialization (Local Data, the robot frozen, the workers
spawned and ready), Routine (a timer tick taken: heartbeats checked, the
cycle published, the syncs sent), Idle (after the syncs, until the next
tick: messages drained, the node's own slow work) and Cleanup (the workers
ended, the result written, the IPC removed). A fault in any state but
Cleanup goes to Cleanup; nothing leaves Cleanup but the end.

:class:`Lifecycle` holds the state and refuses a move the table does not
list, so the manager's sequence (:mod:`redistro.process.manager`) can be
read, and tested, apart from what it does in each state.
"""

from __future__ import annotations

import enum
from collections.abc import Callable

from redistro.localdata.layout import ProcState


class Event(enum.Enum):
    __hash__ = object.__hash__  # (as State's)

    READY = "every worker is ready"
    TICK = "a timer tick"
    SYNCED = "the cycle's syncs went out"
    DONE = "the node's work is done"
    FAULT = "a fault"
    CLEANED = "the workers ended and the result written"


class State(enum.Enum):
    # (members are singletons, equal only to themselves: the identity hash,
    # in C, spares each move two calls of Enum's own, in Python)
    __hash__ = object.__hash__

    INITIALIZATION = ProcState.INITIALIZATION
    ROUTINE = ProcState.ROUTINE
    IDLE = ProcState.IDLE
    CLEANUP = ProcState.CLEANUP
    OVER = ProcState.NONE


# each state's number in Local Data (ProcState), for the manager's block
CODE: dict[State, int] = {s: int(s.value) for s in State}

MOVES: dict[tuple[State, Event], State] = {
    (State.INITIALIZATION, Event.READY): State.ROUTINE,
    (State.ROUTINE, Event.SYNCED): State.IDLE,
    (State.IDLE, Event.TICK): State.ROUTINE,
    (State.ROUTINE, Event.DONE): State.CLEANUP,
    (State.CLEANUP, Event.CLEANED): State.OVER,
    **{(s, Event.FAULT): State.CLEANUP for s in (State.INITIALIZATION, State.ROUTINE, State.IDLE)},
}


class InvalidMove(RuntimeError):
    """An event the present state has no move for."""


class Lifecycle:
    """A manager's state (see the module's text). ``on_change(old, new)`` is
    called on every move (the manager publishes its state there)."""

    def __init__(self, on_change: Callable[[State, State], None] | None = None) -> None:
        self.state = State.INITIALIZATION
        self.on_change = on_change
        self.moves = 0

    def process(self, event: Event) -> State:
        """Move on ``event``; InvalidMove if the table has no such move. A
        fault in Cleanup (a second one) changes nothing: the first is the
        cause."""
        old = self.state
        new = MOVES.get((old, event))
        if new is None:
            if event is Event.FAULT and old in (State.CLEANUP, State.OVER):
                return old
            raise InvalidMove(f"{event.value} in {old.name.lower()}")
        self.state = new
        self.moves += 1
        if self.on_change is not None:
            self.on_change(old, new)
        return new

    @property
    def running(self) -> bool:
        """Routine or Idle: the node's cycle goes on."""
        return self.state in (State.ROUTINE, State.IDLE)

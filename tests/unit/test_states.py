"""The manager's states: every listed move, every other one refused."""

from __future__ import annotations

import itertools

import pytest

from redistro.process.states import MOVES, Event, InvalidMove, Lifecycle, State


def test_a_session_goes_through_the_four_states_in_order() -> None:
    seen: list[tuple[State, State]] = []
    life = Lifecycle(lambda old, new: seen.append((old, new)))
    assert life.state is State.INITIALIZATION and not life.running
    life.process(Event.READY)
    for _ in range(3):  # a cycle: the tick's work, then idle until the next tick
        assert life.running
        life.process(Event.SYNCED)
        assert life.state is State.IDLE
        life.process(Event.TICK)
    life.process(Event.DONE)
    assert life.state is State.CLEANUP and not life.running
    life.process(Event.CLEANED)
    assert life.state is State.OVER
    assert seen[0] == (State.INITIALIZATION, State.ROUTINE)
    assert seen[-2:] == [(State.ROUTINE, State.CLEANUP), (State.CLEANUP, State.OVER)]
    assert life.moves == len(seen) == 9


@pytest.mark.parametrize("start", [State.INITIALIZATION, State.ROUTINE, State.IDLE])
def test_a_fault_goes_to_cleanup_from_any_running_state(start: State) -> None:
    life = Lifecycle()
    life.state = start
    assert life.process(Event.FAULT) is State.CLEANUP
    assert life.process(Event.FAULT) is State.CLEANUP  # a second fault: the first is the cause
    assert life.moves == 1


def test_every_move_not_in_the_table_is_refused() -> None:
    for state, event in itertools.product(State, Event):
        life = Lifecycle()
        life.state = state
        if (state, event) in MOVES:
            assert life.process(event) is MOVES[(state, event)]
        elif event is Event.FAULT:  # (in Cleanup or over: ignored)
            assert life.process(event) is state
        else:
            with pytest.raises(InvalidMove, match=event.value):
                life.process(event)
            assert life.state is state and life.moves == 0


def test_the_states_are_the_ones_local_data_shows() -> None:
    from redistro.localdata.layout import ProcState

    assert {s.value for s in State} == set(ProcState)

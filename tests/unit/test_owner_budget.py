"""The nodes' time budget: on the plant's clock when there is one, with a
wall-clock backstop for a stalled plant; on the wall clock otherwise."""

from __future__ import annotations

from redistro.process.session_owner import MIN_CLOCK_RATE, _Budget


class FakeClock:
    def __init__(self, t: float | None = 100.0) -> None:
        self.t = t

    def __call__(self) -> float | None:
        return self.t


def test_a_slow_plant_is_not_a_fault() -> None:
    clock = FakeClock(100.0)
    b = _Budget(20.0, 5.0, start=0.0, clock=clock)
    # the wall clock far past budget + margin, the plant at 0.1 of real time
    clock.t = 100.0 + 0.1 * 200.0
    assert b.exceeded(200.0) is None
    clock.t = 100.0 + 25.5  # the plant's clock past budget + margin
    why = b.exceeded(255.0)
    assert why is not None and "20.0 s of the plant's time" in why


def test_a_stalled_plant_meets_the_wall_clock_backstop() -> None:
    clock = FakeClock(100.0)
    b = _Budget(20.0, 5.0, start=0.0, clock=clock)
    backstop = 5.0 + 20.0 / MIN_CLOCK_RATE
    assert b.exceeded(backstop - 0.1) is None
    why = b.exceeded(backstop + 0.1)
    assert why is not None and "below" in why


def test_an_unreadable_clock_is_skipped() -> None:
    clock = FakeClock(100.0)
    b = _Budget(20.0, 5.0, start=0.0, clock=clock)
    clock.t = None  # the plant's status could not be read this time
    assert b.exceeded(30.0) is None


def test_without_a_clock_the_budget_is_wall_time() -> None:
    b = _Budget(20.0, 5.0, start=10.0, clock=None)
    assert b.exceeded(34.9) is None
    why = b.exceeded(35.1)
    assert why is not None and "(20.0 s)" in why


def test_a_clock_not_yet_readable_counts_from_its_first_reading() -> None:
    """The plant starts beside the nodes: its clock comes later."""
    clock = FakeClock(None)
    b = _Budget(20.0, 5.0, start=10.0, clock=clock)
    assert b.exceeded(35.1) is None  # not the wall clock: the backstop
    clock.t = 0.5
    assert b.exceeded(36.0) is None  # (the first reading)
    clock.t = 0.5 + 24.9
    assert b.exceeded(80.0) is None
    clock.t = 0.5 + 25.1
    why = b.exceeded(81.0)
    assert why is not None and "25.1 s since they started" in why
    clock.t = None  # a plant never read: the backstop
    b = _Budget(20.0, 5.0, start=10.0, clock=clock)
    why = b.exceeded(10.0 + 5.0 + 20.0 / MIN_CLOCK_RATE + 0.1)
    assert why is not None and "below" in why


def test_no_budget_never_stops() -> None:
    b = _Budget(None, 5.0, start=0.0, clock=FakeClock())
    assert b.exceeded(1e9) is None


def test_an_operators_pause_adds_to_the_budget() -> None:
    """A task paused by its operator (``redistro ctl pause``) for 30 s of
    the plant's time may run 30 s longer; past that, it is stopped."""
    clock = FakeClock(100.0)
    paused = [30.0]
    b = _Budget(20.0, 5.0, start=0.0, clock=clock, paused=lambda: paused[0])
    clock.t = 100.0 + 25.5 + 29.0  # past budget + margin, within them and the pause
    assert b.exceeded(60.0) is None
    clock.t = 100.0 + 25.5 + 31.0
    why = b.exceeded(62.0)
    assert why is not None and "20.0 s of the plant's time" in why

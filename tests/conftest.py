"""Shared fixtures. The autouse fixture fails any test that leaves IPC objects
in /dev/shm (shared memory or semaphores) or child processes behind."""

from __future__ import annotations

import contextlib
import os
import signal
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from redistro.ipc import signals

SHM = Path("/dev/shm")

# make test runs three pytest workers: the real-time sessions in one, the
# lockstep sessions in the second, whose Python is tests/apart-python (a
# /dev/shm and SysV IPC of its own), the unit tests and the front door's (CPU
# only) in the third, tests/units-python (a network of its own too, at nice
# 10). Each worker keeps its sessions' locks in a runtime folder of its own:
# none reaps another's sessions, nor takes a live one of another's for dead.
WORKER = os.environ.get("PYTEST_XDIST_WORKER", "")
RUNTIME = f"{tempfile.gettempdir()}/redistro-{os.getuid()}-test-{WORKER}"
if WORKER:
    os.environ["REDISTRO_RUNTIME_DIR"] = RUNTIME
PYTHONS = {"apart-python": "apart", "units-python": "units"}  # the workers' Pythons


def redistro_shm_entries() -> set[str]:
    """The project's IPC objects, and zenoh's shared-memory files (the
    sessions turn zenoh's shared memory off: none may appear)."""
    return {e for e in os.listdir(SHM) if "redistro" in e or e.endswith(".zenoh")}


def descendants(root: int) -> set[int]:
    parent: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_bytes()
        except OSError:
            continue
        parent[int(entry)] = int(stat[stat.rfind(b")") + 2 :].split()[1])
    out: set[int] = set()
    frontier = [root]
    while frontier:
        p = frontier.pop()
        for child, par in parent.items():
            if par == p and child not in out:
                out.add(child)
                frontier.append(child)
    return out


def is_zombie(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_bytes()
    except OSError:
        return True  # gone
    return stat[stat.rfind(b")") + 2 :].split()[0] == b"Z"


def reap_zombies() -> None:
    """Reap our zombie children (orphans re-parented to us, the subreaper)."""
    for pid in signals.children_of(os.getpid()):
        if is_zombie(pid):
            with contextlib.suppress(ChildProcessError):
                os.waitpid(pid, os.WNOHANG)


@pytest.fixture(scope="session", autouse=True)
def _subreaper() -> None:
    # Orphans of killed test sessions re-parent to pytest, so the leak check sees them.
    signals.become_subreaper()


@pytest.fixture(autouse=True)
def no_leaks() -> Iterator[None]:
    from redistro.ipc import sysv

    shm_before = redistro_shm_entries()
    cards_before = sysv.our_keys()
    procs_before = descendants(os.getpid())
    yield
    deadline = time.monotonic() + 10.0
    while True:
        reap_zombies()
        procs = {p for p in descendants(os.getpid()) - procs_before if not is_zombie(p)}
        shm = redistro_shm_entries() - shm_before
        cards = sysv.our_keys() - cards_before
        if (not procs and not shm and not cards) or time.monotonic() > deadline:
            break
        time.sleep(0.05)  # polling the OS for a condition, with a deadline
    problems = []
    if procs:
        cmdlines = []
        for pid in procs:
            with contextlib.suppress(OSError):
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")
                cmdlines.append(f"{pid}: {cmd.decode()[:120]}")
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        problems.append(f"child processes left: {cmdlines}")
    if shm:
        from redistro.ipc import names, session

        for entry in shm:
            session.unlink(*names.entry_to_name(entry))
        problems.append(f"/dev/shm entries left: {sorted(shm)}")
    if cards:
        for key in cards:
            sysv.remove_key(key)
        problems.append(f"SysV memory cards left: {sorted(hex(k) for k in cards)}")
    if problems:
        reap_zombies()
        pytest.fail("; ".join(problems))


# the longest tests first in each worker (its run ends sooner): the lockstep
# campaigns in the second; the spare ones (below) longest first, the
# operator's, the ESC sessions (up to a minute each), then the 10-40 s
# lockstep ones (a minute-long one taken last once kept a worker 70 s
# after the others); the first worker's benchmarks last (below)
FIRST = (
    "test_lockstep.py",
    "test_faults_lockstep.py",
    "test_operator.py",
    "test_esc_session.py",
    "test_peg_search.py",
    "test_moves.py",
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    items.sort(key=_rank)


# the benchmarks' own tests last: by then the unit tests are over
LAST = ("test_bench.py",)


def _rank(item: pytest.Item) -> int:
    name = item.nodeid.split("::")[0].rsplit("/", 1)[-1]
    if name in LAST:
        return len(FIRST) + 1
    return FIRST.index(name) if name in FIRST else len(FIRST)


# the session tests run in lockstep at the default scheduling (their
# verdicts are the plant's truth and the log, which no schedule changes):
# beside the unit tests, below the real-time sessions of the first worker
LOCKSTEP_MODULES = (
    "test_lockstep.py",
    "test_peg_search.py",
    "test_moves.py",
    "test_operator.py",
    "test_faults_lockstep.py",
)


# a lockstep session the first worker runs between its real-time ones (never
# beside them: that worker runs one test at a time), to even the workers'
# shares
IN_THE_REAL_TIME_WORKER = ("::test_two_arms_insert_a_held_peg_into_a_held_block",)

# sessions long in wall time and light in CPU (the live page paced to real
# time, a plant slowed to a sixth, a self-calibration at real time) that the
# first worker to run short of its own tests takes: the units worker, once
# its tests are done, at nice 0 again (the CPUs otherwise stood idle some
# 85 CPU-s a run while the two session workers ran on alone). The
# operator's module goes whole (its calibration fixture once); each test of
# SPARE_TESTS (a module, or a test's name) alone: the ESC sessions (real
# time, up to a minute) and lockstep sessions of 10-40 s. Whichever worker
# runs short takes the next (the lockstep worker once ran on 60 s after the
# others, 50 CPU-s idle)
SPARE_MODULES = ("test_operator.py",)
SPARE_TESTS = (
    "test_moves.py",
    "::test_a_hole_beyond_the_search_radius",
    "::test_peg_insertion_over_each_transport[reflective]",  # (lockstep, Python path)
    "::test_a_robot_left_at_or_past_its_limit",  # (lockstep)
    "test_esc_session.py",
)


def _scope(nodeid: str) -> str:
    """The worker a test runs in. ``units``: the unit tests and the front
    door's (its refusals start no session); not the transports' contract
    tests, whose zenoh drops records on a loaded host (congestion control
    DROP), as a session's ddm would. ``apart``: the lockstep sessions, but
    those of ``IN_THE_REAL_TIME_WORKER``. ``sessions``: the rest (real-time
    sessions). ``spare``: ``SPARE_MODULES``, and ``spare <test>`` each of
    ``SPARE_TESTS``, for the worker that runs short first. No session runs
    at the units' nice 10: it starved a lockstep session's plant past the
    drivers' I/O timeout before the first tick."""
    path = nodeid.split("::")[0]
    if path.endswith("/test_transports.py") or any(t in nodeid for t in IN_THE_REAL_TIME_WORKER):
        return "sessions"
    name = path.rsplit("/", 1)[-1]
    if "integration/" not in path or name == "test_front_door.py":
        return "units"
    if name in SPARE_MODULES:
        return "spare"
    if name in SPARE_TESTS or any(t in nodeid for t in SPARE_TESTS if t.startswith("::")):
        return f"spare {nodeid}"
    return "apart" if name in LOCKSTEP_MODULES else "sessions"


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    """A session test in the units worker (its nice 10) runs at nice 0, as
    in the others, its module's fixtures too (root may lower it; elsewhere
    it is 0 already)."""
    if _scope(item.nodeid) != "units" and os.getpriority(os.PRIO_PROCESS, 0) > 0:
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, 0, 0)


@pytest.fixture
def above_the_other_workers() -> Iterator[None]:
    """The test at nice -10 where that is allowed (root: make test's three
    workers), the processes it starts too: a benchmark's figures, or
    threads handing records to each other, beside the other workers'
    sessions at nice 0. Not plant_rig's real-time ``above_the_load``: the
    benchmarks' spinning processes would inherit it."""
    before = os.getpriority(os.PRIO_PROCESS, 0)
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, 0, -10)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, 0, before)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """With three workers (make test as root): the tests that start
    real-time sessions (and ``IN_THE_REAL_TIME_WORKER``) in the first; the
    lockstep sessions in the one whose Python is tests/apart-python, the
    unit tests in the one whose Python is tests/units-python (the sessions'
    nodes run at real-time priority, the lockstep ones at the default, the
    unit tests below both); the ``spare`` scopes, one by one, to whichever
    has two tests or fewer left (the units worker first, by far)."""
    from xdist.scheduler import LoadScopeScheduling

    class Apart(LoadScopeScheduling):  # type: ignore[misc]
        def _split_scope(self, nodeid: str) -> str:
            return _scope(nodeid)

        def _assign_work_unit(self, node: Any) -> None:
            python = str(getattr(node.gateway.spec, "python", ""))
            want = next((s for p, s in PYTHONS.items() if python.endswith(p)), "sessions")
            if want in self.workqueue:
                self.workqueue.move_to_end(want, last=False)
            super()._assign_work_unit(node)

    return Apart(config, log)


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    if WORKER:  # the worker's runtime folder, empty once its sessions ended
        with contextlib.suppress(OSError):
            os.rmdir(RUNTIME)

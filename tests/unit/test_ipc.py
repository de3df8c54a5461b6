"""IPC helpers: names, semaphores with deadlines, timer arithmetic, scheduling, reaper."""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path

import pytest

from redistro.faults.local_user import OTHER as SQUATTER
from redistro.faults.local_user import as_other as _as_squatter
from redistro.ipc import names, sched, session
from redistro.ipc.sem import Semaphore
from redistro.ipc.timer import IntervalTimer


def test_names_derive_from_session_node_object() -> None:
    sid = names.new_session_id()
    assert names.is_session_id(sid)
    name = names.object_name(sid, "esc.r1", "localdata")
    assert name == f"/redistro.{sid}.esc.r1.localdata"
    assert names.session_of_entry(name[1:]) == sid
    assert names.session_of_entry("sem." + name[1:]) == sid
    assert names.session_of_entry("sem.mp-abc") is None
    assert names.entry_to_name("sem.redistro.x") == ("sem", "/redistro.x")
    with pytest.raises(ValueError):
        names.object_name("not-a-session", "n", "o")
    with pytest.raises(ValueError):
        names.object_name(sid, "a/b", "o")


def test_semaphore_wait_has_a_monotonic_deadline() -> None:
    with session.Session.create() as s:
        sem = Semaphore.create(names.object_name(s.id, "t", "sem"), s.manifest)
        try:
            t0 = time.monotonic()
            assert sem.acquire(0.05) is False
            waited = time.monotonic() - t0
            assert 0.05 <= waited < 1.0
            sem.release()
            assert sem.acquire(0.05) is True
            assert sem.try_acquire() is False
        finally:
            sem.close()
            sem.unlink()


def test_session_close_removes_what_its_processes_leaked() -> None:
    s = session.Session.create()
    sem = Semaphore.create(names.object_name(s.id, "t", "leak"), s.manifest)
    sem.close()  # "forgot" to unlink
    removed = s.close()
    assert removed == [names.object_name(s.id, "t", "leak")]
    assert not s.directory.exists()


def test_reaper_keeps_live_sessions() -> None:
    with session.Session.create() as s:
        sem = Semaphore.create(names.object_name(s.id, "t", "live"), s.manifest)
        try:
            assert s.id in session.live_sessions()
            assert names.object_name(s.id, "t", "live") not in session.reap()
            assert sem.value == 0  # still there
        finally:
            sem.close()
            sem.unlink()


def test_the_runtime_directory_is_private_or_refused(
    tmp_path: os.PathLike[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from pathlib import Path

    from redistro.errors import IPCError

    root = Path(tmp_path) / "rt"
    monkeypatch.setenv("REDISTRO_RUNTIME_DIR", str(root))
    assert names.checked_runtime_dir(create=False) is None
    assert names.checked_runtime_dir() == root
    assert (os.stat(root).st_mode & 0o777) == 0o700
    os.chmod(root, 0o755)
    with pytest.raises(IPCError, match="mode 0755, expected 0700"):
        session.Session.create()
    with pytest.raises(IPCError, match="mode 0755"):
        session.reap()
    os.rmdir(root)
    other = Path(tmp_path) / "elsewhere"
    other.mkdir(mode=0o700)
    root.symlink_to(other)
    with pytest.raises(IPCError, match="not a folder"):
        session.Session.create()


def test_xdg_runtime_dir_is_used_when_set(
    tmp_path: os.PathLike[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("REDISTRO_RUNTIME_DIR", raising=False)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    assert str(names.runtime_dir()) == f"{tmp_path}/redistro"
    monkeypatch.setenv("XDG_RUNTIME_DIR", "/nonexistent/run/user/1234")  # not there: /tmp
    assert str(names.runtime_dir()).endswith(f"redistro-{os.getuid()}")
    monkeypatch.delenv("XDG_RUNTIME_DIR")
    assert str(names.runtime_dir()).endswith(f"redistro-{os.getuid()}")


def test_the_reaper_leaves_sessions_of_another_runtime_directory(
    tmp_path: os.PathLike[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A dead session's objects are removed only by a reaper of its own
    runtime directory: one started with another REDISTRO_RUNTIME_DIR does
    not see its lock, and must not take it for dead."""
    from pathlib import Path

    monkeypatch.setenv("REDISTRO_RUNTIME_DIR", str(Path(tmp_path) / "a"))
    s = session.Session.create()
    name = names.object_name(s.id, "t", "theirs")
    sem = Semaphore.create(name, s.manifest)
    sem.close()
    try:
        monkeypatch.setenv("REDISTRO_RUNTIME_DIR", str(Path(tmp_path) / "b"))
        assert name not in session.reap()  # not ours to judge
        monkeypatch.setenv("REDISTRO_RUNTIME_DIR", str(Path(tmp_path) / "a"))
        assert name not in session.reap()  # alive: its lock is held
    finally:
        assert s.close() == [name]


def test_timer_due_counts_missed_ticks() -> None:
    t = IntervalTimer(1000.0)
    assert t.period_ns == 1_000_000
    t.start_ns = 0
    assert t.due(1_000_050) == (1_000_000, 50, 0)
    assert t.due(2_000_100) == (2_000_000, 100, 0)
    due, late, missed = t.due(5_000_000 + 10)  # ticks 3 and 4 coalesced
    assert (due, late, missed) == (5_000_000, 10, 2)
    assert IntervalTimer(300.0).period_ns == 3_333_000  # whole microseconds


def test_scheduling_reports_what_was_granted() -> None:
    before = os.sched_getaffinity(0)
    pid = os.fork()
    if pid == 0:  # try in a child so the test process keeps its own scheduling
        g = sched.apply(16, [min(before)], "auto", False)
        ok = g.cpus == [min(before)] and g.policy in ("SCHED_RR", "nice", "default")
        ok = ok and (g.policy != "SCHED_RR" or g.priority == 16)
        os._exit(0 if ok else 1)
    _, status = os.waitpid(pid, 0)
    assert os.WEXITSTATUS(status) == 0
    assert sched.nice_for(19) == -9
    assert sched.cpus_of_mask(sched.cpu_mask([0, 3])) == [0, 3]


def test_batch_puts_the_process_and_its_children_at_sched_batch() -> None:
    """``scheduling.policy: batch``: SCHED_BATCH, whatever the priority asked,
    and a child forked after it inherits it (a session's processes)."""
    pid = os.fork()
    if pid == 0:  # in a child: the test process keeps its own scheduling
        g = sched.apply(16, None, "batch", False)
        code = 0 if g.policy == "SCHED_BATCH" and g.priority == 0 and not g.refused else 1
        if os.sched_getscheduler(0) != os.SCHED_BATCH:
            code = 2
        grandchild = os.fork()
        if grandchild == 0:
            os._exit(0 if os.sched_getscheduler(0) == os.SCHED_BATCH else 1)
        _, st = os.waitpid(grandchild, 0)
        os._exit(code or (3 if os.WEXITSTATUS(st) else 0))
    _, status = os.waitpid(pid, 0)
    assert os.WEXITSTATUS(status) == 0, os.WEXITSTATUS(status)


def test_a_chore_runs_at_the_normal_policy_and_real_time_returns() -> None:
    pid = os.fork()
    if pid == 0:  # in a child: the test process keeps its own scheduling
        code = 0
        try:
            if sched.apply(5, None, "rr").policy != "SCHED_RR":
                os._exit(3)  # real time refused here: nothing to check
            with sched.normal_policy():
                if sched.is_real_time():
                    code = 1
            if not sched.is_real_time() or os.sched_getparam(0).sched_priority != 5:
                code = 2
        except BaseException:
            code = 4
        os._exit(code)
    _, status = os.waitpid(pid, 0)
    code = os.WEXITSTATUS(status)
    if code == 3:
        pytest.skip("SCHED_RR is refused on this host")
    assert code == 0, code


def _cpu_latency_now() -> int:
    with open(sched.CPU_LATENCY_PATH, "rb") as f:
        return int.from_bytes(f.read(4), "little", signed=True)


def test_the_cpu_latency_request_holds_while_its_descriptor_is_open(tmp_path: Path) -> None:
    g = sched.Granted()
    assert sched.hold_cpu_latency(0, g, str(tmp_path / "missing")) is None
    assert g.cpu_latency_us is None and "cpu latency 0 us" in g.refused[0]
    if not os.access(sched.CPU_LATENCY_PATH, os.W_OK):
        pytest.skip("the PM QoS device is not writable here")
    g = sched.Granted()
    fd = sched.hold_cpu_latency(7, g)
    assert fd is not None and g.cpu_latency_us == 7 and not g.refused
    try:
        # the kernel's target is the lowest of the requests held
        assert _cpu_latency_now() <= 7
    finally:
        os.close(fd)


def test_a_library_thread_gets_the_real_time_priority_shared() -> None:
    """A thread started after the process took SCHED_RR (with reset on
    fork, as sched.apply asks) runs at the normal policy; sharing gives it
    the caller's policy and priority (zenoh's I/O threads)."""
    import subprocess
    import sys

    script = """
import os, threading, time
from redistro.ipc import sched
try:
    os.sched_setscheduler(0, os.SCHED_RR | os.SCHED_RESET_ON_FORK, os.sched_param(3))
except PermissionError:
    print("not permitted"); raise SystemExit(0)
ready = threading.Event(); stop = threading.Event(); tid = []
def idle():
    tid.append(threading.get_native_id()); ready.set(); stop.wait(5)
t = threading.Thread(target=idle); t.start(); ready.wait(5)
before = os.sched_getscheduler(tid[0]) & ~os.SCHED_RESET_ON_FORK
raised = sched.share_with_threads()
after = os.sched_getscheduler(tid[0]) & ~os.SCHED_RESET_ON_FORK
prio = os.sched_getparam(tid[0]).sched_priority
stop.set(); t.join()
print(before == os.SCHED_OTHER, raised >= 1, after == os.SCHED_RR, prio)
"""
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=30, check=False
    )
    assert done.returncode == 0, done.stderr[-2000:]
    if done.stdout.strip() == "not permitted":
        pytest.skip("SCHED_RR is not permitted here")
    assert done.stdout.split() == ["True", "True", "True", "3"], done.stdout


def test_a_signal_wait_that_returns_no_signal_waits_on(monkeypatch: pytest.MonkeyPatch) -> None:
    """A manager stopped (SIGSTOP) inside its wait and continued saw
    sigtimedwait return signal number 0 (the record unfilled), and failed on
    it; the wait takes that for no signal and goes on to its deadline."""
    import signal
    from types import SimpleNamespace

    from redistro.ipc import signals

    returns: list[object] = [SimpleNamespace(si_signo=0), SimpleNamespace(si_signo=signal.SIGTERM)]
    asked: list[float] = []

    def fake(sigs: object, timeout: float) -> object:
        asked.append(timeout)
        return returns.pop(0)

    monkeypatch.setattr(signal, "sigtimedwait", fake)
    info = signals.wait(frozenset({signal.SIGTERM}), 1.0)
    assert info is not None and info.si_signo == signal.SIGTERM
    assert len(asked) == 2 and asked[1] <= asked[0] <= 1.0  # the same deadline
    returns[:] = [SimpleNamespace(si_signo=0), None]
    assert signals.wait(frozenset({signal.SIGTERM}), 0.0) is None


@pytest.mark.skipif(os.getuid() != 0, reason="makes objects of another user (root only)")
def test_a_squatters_objects_are_named_at_creation_and_never_reaped(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """Another user creates the names and keys a session will use first: the
    session's creation refuses naming that user (a card takes another random
    key), and no clean-up removes what that user made, though the session's
    manifest lists it."""
    import posix_ipc
    import sysv_ipc

    from redistro.errors import IPCError
    from redistro.ipc import names, session, sysv
    from redistro.ipc.sem import Semaphore
    from redistro.ipc.shm import SharedMemory

    shm_name = "/redistro.20261126T000000-abcdef.esc.r1.ld"
    sem_name = "/redistro.20261126T000000-abcdef.esc.r1.go0"
    squatted = sysv.KEY_BASE | 0x1234

    def squat() -> None:
        posix_ipc.SharedMemory(shm_name, posix_ipc.O_CREX, size=64).close_fd()
        posix_ipc.Semaphore(sem_name, posix_ipc.O_CREX).close()
        sysv_ipc.SharedMemory(squatted, sysv_ipc.IPC_CREX, size=64, mode=0o644)

    _as_squatter(squat)
    manifest = session.Manifest("20261126T000000-abcdef", tmp_path)
    try:
        with pytest.raises(IPCError, match=f"already exists \\(owned by uid {SQUATTER}"):
            SharedMemory.create(shm_name, 128, manifest)
        with pytest.raises(IPCError, match=f"already exists \\(owned by uid {SQUATTER}"):
            Semaphore.create(sem_name, manifest)
        with pytest.raises(IPCError, match=f"created by uid {SQUATTER}"):
            sysv.Card.create(squatted, 128, manifest)
        # a card draws another key when its first is taken
        keys = iter([squatted, squatted + 1])
        monkeypatch.setattr(sysv, "random_key", lambda: next(keys))
        card = sysv.Card.create_new(128, manifest)
        assert card.key == squatted + 1
        card.close()
        # the manifest lists the squatter's three; the clean-up leaves them
        listed = {name for _, name in manifest.entries()}
        assert {shm_name, sem_name, sysv.key_name(squatted)} <= listed
        removed = session._remove_objects(manifest.entries())
        assert removed == [sysv.key_name(squatted + 1)]
        assert names.entry_path("shm", shm_name).exists()
        assert names.entry_path("sem", sem_name).exists()
        assert sysv_ipc.SharedMemory(squatted).cuid == SQUATTER
        assert f"created by uid {SQUATTER}" in caplog.text
        assert f"owned by uid {SQUATTER}" in caplog.text
    finally:
        posix_ipc.unlink_shared_memory(shm_name)
        posix_ipc.unlink_semaphore(sem_name)
        sysv_ipc.SharedMemory(squatted).remove()
        with contextlib.suppress(sysv_ipc.ExistentialError):
            sysv_ipc.SharedMemory(squatted + 1).remove()

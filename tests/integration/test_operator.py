"""The operator's hand on a running session: ``redistro ctl`` and the live
view's buttons (pause, resume, jog, stop, e-stop), and the view's token off
loopback.

Every verdict comes from the plant's truth (the tools' poses and the brakes
in the plant's bank, read by plant step, not by the clock) and from the run's
summary and log. The sessions run in lockstep: a pause of 2 s is 2 s of the
plant's time however fast the host runs it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.helpers import LOCKSTEP, REDISTRO, ROOT, copy_runs, load_json, read_session_id, run_cli

SHORT = "tasks/peg_insertion_short.yaml"
PHYSICS_HZ = 1000
pytestmark = pytest.mark.peg


class Plant:
    """The plant's truth of a running session: each robot's tool and brakes."""

    def __init__(self, sid: str) -> None:
        from redistro.drivers.io.bank import RegisterBank
        from tests.helpers import wait_for

        self.bank = wait_for(lambda: _attach(RegisterBank, sid), 60, "the plant's bank")
        names = self.bank.robot_names
        self.truth = {r: self.bank.truth(names.index(r)) for r in names}
        from redistro.config.loader import load_config
        from redistro.robotmodel import PLATE

        cfg = load_config()  # (the tool centre point: the peg's tip, or the plate's face)
        self.tcp_m = {
            r: cfg.workcell.peg.length_m if cfg.robots[r].peg else PLATE[1] for r in names
        }

    def tool(self, robot: str) -> tuple[np.ndarray[Any, Any], int]:
        """(the tool's position [m], the plant's step) now."""
        d = self.truth[robot].read()
        return d["tool_xyz_m"].copy(), int(d["step"])

    def tcp(self, robot: str) -> np.ndarray[Any, Any]:
        """The tool centre point [m] now: the peg's tip, or the plate's face,
        along the wrist sensor's z axis (a jog moves this point)."""
        d = self.truth[robot].read()
        return np.asarray(d["tool_xyz_m"] + d["tool_rot"] @ np.array([0.0, 0.0, self.tcp_m[robot]]))

    def step(self) -> int:
        return self.tool(next(iter(self.truth)))[1]

    def wait_step(
        self, step: int, timeout_s: float = 120.0, session: subprocess.Popen[str] | None = None
    ) -> None:
        """Until the plant's step counter reaches ``step`` (a deadline; an
        ended ``session`` fails at once)."""
        deadline = time.monotonic() + timeout_s
        while self.step() < step:
            assert time.monotonic() < deadline, f"the plant never reached step {step}"
            if session is not None and session.poll() is not None:
                raise AssertionError(f"the session ended (exit {session.returncode}) at step "
                                     f"{self.step()}, before step {step}")  # fmt: skip
            time.sleep(0.01)  # (polling the plant's step counter, with a deadline)

    def motion(self, seconds: float) -> dict[str, float]:
        """Per robot, how far its tool moved [m] over ``seconds`` of the plant's time."""
        start = {r: self.tool(r)[0] for r in self.truth}
        self.wait_step(self.step() + int(seconds * PHYSICS_HZ))
        return {r: float(np.linalg.norm(self.tool(r)[0] - start[r])) for r in self.truth}

    def close(self) -> None:
        self.bank.close()


def _attach(cls: Any, sid: str) -> Any:
    try:
        return cls.attach(sid)
    except Exception:
        return None


@contextmanager
def running(
    calibrated: Path, tmp: Path, task: str = SHORT, *sets: str
) -> Iterator[tuple[subprocess.Popen[str], str, Path]]:
    """The task (the short main job), in lockstep (``sets``: more config),
    from a private runs folder: (the session's process, its id, its run
    folder); killed if still running."""
    runs = copy_runs(calibrated, tmp)
    out = tmp / "run"
    more = [a for kv in sets for a in ("--set", kv)]
    proc = subprocess.Popen(
        [*REDISTRO, *LOCKSTEP, *more, "--set", f"session.runs_dir={runs}", "session", task,
         "--out", str(out)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        yield proc, read_session_id(proc), out
    except BaseException:
        if proc.poll() is None:
            proc.kill()
        said, err = proc.communicate()
        print(f"the session said:\n{said[-4000:]}\n{err[-4000:]}")  # (in the failure's report)
        raise
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate()


def ctl(sid: str, *args: str) -> subprocess.CompletedProcess[str]:
    return run_cli("ctl", sid, *args, timeout=60)


def _jog(plant: Plant, sid: str, robot: str, mm: tuple[float, float, float]) -> float:
    """``ctl jog``: how far the tool centre point's move [m] missed the step, by the truth."""
    before = plant.tcp(robot)
    done = ctl(sid, "jog", robot, "--mm", *(str(v) for v in mm))
    assert done.returncode == 0 and "jog: done" in done.stdout, done.stdout + done.stderr
    moved = plant.tcp(robot) - before
    return float(np.linalg.norm(moved - np.asarray(mm) / 1000.0))


HOME = 4  # the short main job's last segment: r2's joint move home


def _wait_segment(ssc: Any, robot: int, segment: int, into_s: float) -> None:
    """Until the SSC's plan has ``robot`` ``into_s`` into ``segment`` (polled, to a deadline)."""
    deadline = time.monotonic() + 120.0
    while True:
        plan = ssc.read("plan", robot)
        if int(plan["segment"]) == segment and float(plan["segment_t_s"]) >= into_s:
            return
        assert time.monotonic() < deadline, f"segment {segment} never came: {plan}"
        time.sleep(0.01)  # (polling the controller's plan, with a deadline)


@pytest.fixture(scope="module")
def commanded(calibrated: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The short main job commanded by ``redistro ctl`` in its approach:
    pause, a forged resume, a jog of each arm, resume; then a pause and a
    resume in r2's joint move home; what the truth said."""
    from redistro.ipc import names
    from redistro.localdata.view import SessionViews
    from redistro.ssc.ctl import Client, Command, Order

    tmp = tmp_path_factory.mktemp("ctl")
    seen: dict[str, Any] = {"run": tmp / "run"}
    with running(calibrated, tmp) as (proc, sid, _out):
        plant = Plant(sid)
        views = SessionViews(sid)
        try:
            plant.wait_step(PHYSICS_HZ)  # (the approach: r2 on its way to the hole, 5 s long)
            seen["pause"] = ctl(sid, "pause")
            seen["held"] = plant.motion(2.0)
            forged = Client(sid, names.runtime_dir() / sid, key=os.urandom(32))
            seen["forged"] = forged.send(Order(Command.RESUME), 10.0)
            seen["held_after_forgery"] = plant.motion(0.5)
            ssc = views.get("ssc")
            assert ssc is not None
            seen["paused_after_forgery"] = int(ssc.read("plan", 0)["paused"])
            seen["jog_r2_miss"] = _jog(plant, sid, "r2", (0.0, 0.0, 5.0))  # (law-held)
            seen["jog_r1_miss"] = _jog(plant, sid, "r1", (0.0, 3.0, 0.0))  # (PID-held)
            seen["too_far"] = ctl(sid, "jog", "r2", "--mm", "6", "0", "0")
            seen["resume"] = ctl(sid, "resume")
            seen["resume_again"] = ctl(sid, "resume")
            # r2 homing on a joint move: its Cartesian law holds it too
            _wait_segment(ssc, 1, HOME, 1.0)
            seen["pause_home"] = ctl(sid, "pause")
            seen["held_home"] = plant.motion(2.0)
            seen["resume_home"] = ctl(sid, "resume")
        finally:
            views.close()
            plant.close()
        out, err = proc.communicate(timeout=300)
        seen["returncode"], seen["stdout"] = proc.returncode, out + err[-3000:]
    return seen


def test_ctl_pauses_jogs_refuses_a_forgery_and_resumes_to_an_inserted_peg(
    commanded: dict[str, Any],
) -> None:
    """Paused, every tool holds (under 0.5 mm over 2 s of the plant's time);
    a command signed with another key is refused, counted and changes
    nothing; a jog moves the tool centre point by its step within 0.5 mm (r2 held by its
    Cartesian law, r1 by the joint PID); a jog past 5 mm is bad input; after
    resume the task ends ok with the peg in the hole; paused in r2's joint
    move home, every tool holds as well; each command, its effect and the
    refusal are events in the log."""
    from redistro.log.mcapfile import read_log

    c = commanded
    assert c["pause"].returncode == 0 and "pause: done" in c["pause"].stdout, c["pause"]
    assert max(c["held"].values()) < 0.0005, c["held"]
    assert c["forged"]["ok"] is False, c["forged"]
    assert "not signed with the session's key" in c["forged"]["text"], c["forged"]
    assert max(c["held_after_forgery"].values()) < 0.0005 and c["paused_after_forgery"] == 1
    assert c["jog_r2_miss"] < 0.0005 and c["jog_r1_miss"] < 0.0005, c
    too_far = c["too_far"]
    assert too_far.returncode == 2 and "at most 5" in too_far.stderr, too_far.stderr
    assert c["resume"].returncode == 0 and "resume: done" in c["resume"].stdout
    again = c["resume_again"]  # (not paused: refused by the worker, exit 1)
    assert again.returncode == 1 and "resume: not now" in again.stderr, again.stderr
    # paused in r2's joint move home: held as well
    assert c["pause_home"].returncode == 0 and c["resume_home"].returncode == 0, c
    assert max(c["held_home"].values()) < 0.0005, c["held_home"]
    assert c["returncode"] == 0, c["stdout"][-3000:]
    run = c["run"]
    summary = load_json(run / "summary.json")
    assert summary["result"] == "ok" and summary["inserted"] is True, summary.get("reason")
    assert summary["operator"] == {"accepted": 7, "refused": 1}, summary["operator"]
    events = read_log(run / "session.mcap").events.get("/ssc/operator", [])
    commands = [e["command"] for e in events if e.get("event") == "command"]
    assert commands == ["pause", "jog", "jog", "resume", "resume", "pause", "resume"], events
    effects = [(e["command"], e["status"]) for e in events if e.get("event") == "effect"]
    assert ("pause", "done") in effects and ("jog", "done") in effects, effects
    assert ("resume", "not_now") in effects, effects
    refused = [e for e in events if e.get("event") == "refused"]
    assert len(refused) == 1 and "not signed" in refused[0]["why"], refused
    messages = (run / "messages.log").read_text()
    assert "operator command 1: pause" in messages and "operator command refused" in messages
    again = run_cli("replay", str(run))  # (when the operator acted is no part of the run)
    assert again.returncode == 2 and "its operator commanded it" in again.stderr, again.stderr


@pytest.mark.parametrize("order", ["stop", "estop"])
def test_ctl_stop_ends_in_order_and_estop_brakes_the_group(
    calibrated: Path, tmp_path: Path, order: str
) -> None:
    """``ctl stop`` in the approach ends the session as Ctrl-C does (every
    ESC interrupted, its robot frozen); ``ctl estop`` is the group's e-stop:
    every node ends ``estop``. Either way the plant records each arm fully
    braked after the command."""
    with running(calibrated, tmp_path) as (proc, sid, out):
        plant = Plant(sid)
        try:
            plant.wait_step(2 * PHYSICS_HZ)
            sent_ns, sent_step = time.monotonic_ns(), plant.step()
            done = ctl(sid, order)
            assert done.returncode == 0 and "under way" in done.stdout, done.stdout + done.stderr
        finally:
            plant.close()
        proc.communicate(timeout=120)
        assert proc.returncode == 1
    summary = load_json(out / "summary.json")
    assert summary["operator"] == {"accepted": 1, "refused": 0}
    nodes = summary["nodes"]
    for r in ("r1", "r2"):
        esc = nodes[f"esc.{r}"]
        assert any(t >= sent_ns for t in esc["freeze_monotonic_ns"]), esc
        if order == "estop":
            assert esc["result"] == "estop", esc
    if order == "stop":  # (as Ctrl-C: the owner's SIGINT to every node; a node
        # the SSC's end reached first ends on its e-stop)
        reasons = {n: v["reason"] for n, v in nodes.items()}
        assert "interrupted by SIGINT" in reasons.values(), reasons
        assert all(v["result"] in ("abnormal", "estop") for v in nodes.values()), reasons
    else:
        assert nodes["ssc"]["reason"] == "the operator's e-stop (redistro ctl)", nodes["ssc"]
    # the plant's own record: each arm's every joint braked, after the command
    freezes = load_json(out / "plant.json")["freezes"]
    braked = {f["robot"] for f in freezes if f["step"] >= sent_step}
    assert braked == {"r1", "r2"}, freezes
    # each node's end (its Cleanup) seen by the plant at once: no tick waited out
    assert load_json(out / "plant.json")["lockstep"]["waits_missed"] == 0
    assert f"operator command 1: {order}" in (out / "messages.log").read_text()


def press(tab: Any, button: str, answer: str) -> str:
    """A click on ``button`` (the DOM's click on the button itself: under
    load the page redraws its panel so often that a pointer's click never
    finds it standing still), then the page's text once it shows the
    controller's ``answer``."""
    from tests import browser

    tab.get_by_role("button", name=button, exact=True).dispatch_event("click")
    return browser.wait_text(tab, answer)


def _slow_approach(tmp: Path) -> str:
    """The short main job with an approach of 20 s, run at real time
    (``session.lockstep_pace=1``): the page's Pause lands while r2 moves to
    the hole, mostly, and before the task's end even on a loaded host (once,
    with an approach of 20 s run as fast as the CPUs allowed, the page passed
    on its Pause over 30 s after its Resume: the session had ended)."""
    import yaml

    task = yaml.safe_load((ROOT / SHORT).read_text())
    approach = task["segments"][0]
    assert approach["name"] == "approach", approach
    approach["duration_s"], approach["goal"]["move_s"] = 20, 15
    path = tmp / "peg_insertion_slow_approach.yaml"
    path.write_text(yaml.safe_dump(task, sort_keys=False))
    return str(path)


def test_the_live_page_pauses_jogs_and_resumes_a_session(calibrated: Path, tmp_path: Path) -> None:
    """The live view of the peg insertion in headless Chromium. The
    session runs in lockstep at real time, as one watched live would
    (``session.lockstep_pace=1``); ``ctl pause`` holds it 1 s into the
    approach while the page loads. Then, on the page: Resume; a
    click on Pause holds every robot (under 0.5 mm over 2 s of the plant's
    time); the +z jog button moves r1's tool 5 mm within 0.5 mm; Resume
    lets the task end ok with the peg in the hole."""
    from redistro.view import wait_served
    from tests import browser

    port = browser.free_port()
    task = _slow_approach(tmp_path)
    with running(calibrated, tmp_path, task, "session.lockstep_pace=1") as (proc, sid, out):
        view = subprocess.Popen(
            [*REDISTRO, "view", "--live", sid, "--port", str(port)],
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        plant = Plant(sid)
        try:
            plant.wait_step(PHYSICS_HZ, session=proc)
            held_off = ctl(sid, "pause")
            assert held_off.returncode == 0, held_off.stdout + held_off.stderr
            assert wait_served(port, 60.0), "the live view never served its page"
            with browser.page(f"http://127.0.0.1:{port}/") as tab:
                browser.wait_text(tab, "operator: ready")
                press(tab, "Resume", "resume: done")
                text = press(tab, "Pause", "pause: done")  # (in the approach, mostly)
                held = plant.motion(2.0)
                before = plant.tcp("r1")  # (the panel's first robot: r1, in free space)
                press(tab, "+z", "jog: done")
                miss = plant.tcp("r1") - before - np.array([0.0, 0.0, 0.005])
                press(tab, "Resume", "resume: done")
        finally:
            plant.close()
        proc.communicate(timeout=300)
        _, err = view.communicate(timeout=30)  # (it ends with the session)
        assert view.returncode == 0, err[-2000:]
    assert max(held.values()) < 0.0005, (held, text[text.find("segment:") :][:60])
    assert float(np.linalg.norm(miss)) < 0.0005, miss
    summary = load_json(out / "summary.json")
    assert summary["result"] == "ok" and summary["inserted"] is True, summary.get("reason")
    assert summary["operator"] == {"accepted": 5, "refused": 0}, summary["operator"]
    plant = load_json(out / "plant.json")  # (never faster than real time: paced)
    assert plant["rtf"] <= 1.02 and plant["lockstep"]["paced_ticks"] > 0, plant["lockstep"]


def test_off_loopback_the_page_asks_for_its_token(commanded: dict[str, Any]) -> None:
    """``view RUN --bind`` an address of this host that is not loopback
    (a veth's): the page draws nothing until it is given the token the view
    printed; a wrong one is refused and counted, the right one opens it."""
    from tests import browser

    with browser.host_address() as addr:
        if addr is None:
            pytest.skip("no address but loopback here (needs root and ip)")
        port = browser.free_port()
        view = subprocess.Popen(
            [*REDISTRO, "view", str(commanded["run"]), "--bind", addr, "--port", str(port)],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )  # fmt: skip
        try:
            token = _token(view)
            with browser.page(f"http://{addr}:{port}/") as tab:
                first = browser.wait_text(tab, "needs its token")
                assert "approach" not in first, first[:2000]
                field = tab.get_by_role("dialog").locator("input").first
                field.fill("not-the-token")
                tab.get_by_role("button", name="Open").click()
                browser.wait_text(tab, "wrong token")
                field.fill(token)
                tab.get_by_role("button", name="Open").click()
                text = browser.wait_text(tab, "approach")
            assert "result: ok" in text, text[:2000]
        finally:
            view.send_signal(signal.SIGTERM)
            printed, _ = view.communicate(timeout=30)
    assert "a wrong token from browser" in printed, printed


def _token(view: subprocess.Popen[str]) -> str:
    """The token the view prints (after the library's banner)."""
    assert view.stdout is not None
    for _ in range(40):
        line = view.stdout.readline()
        if line.startswith("token: "):
            return line.split()[1]
        assert line, "the view ended before printing its token"
    raise AssertionError("no token printed")

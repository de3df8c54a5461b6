"""Lockstep (``--clock lockstep``): the plant paces the nodes, and a run is
reproducible to the byte.

The short main job runs once over each transport. Each run starts from the
same calibrated runs folder, ends ``ok`` with the peg in the hole by the
plant's truth, and every run's log has the same digest: the transports
carry the same records in the same order, so the logged data are the same
to the last bit. ``redistro replay`` runs a run again from its folder and
finds it identical; with one gain changed it names the first difference.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from tests.helpers import LOCKSTEP, copy_runs, load_json, run_cli

SHORT = "tasks/peg_insertion_short.yaml"
pytestmark = pytest.mark.peg


def _lockstep(calibrated: Path, tmp: Path, name: str, *sets: str) -> dict[str, Any]:
    runs = copy_runs(calibrated, tmp / name)
    out = tmp / name / "run"
    options = [a for kv in sets for a in ("--set", kv)]
    done = run_cli(
        *LOCKSTEP, "--set", f"session.runs_dir={runs}", *options,
        "session", SHORT, "--out", str(out), "--clock", "lockstep", timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    summary: dict[str, Any] = load_json(out / "summary.json")
    plant = load_json(out / "plant.json")
    assert plant["clock"] == "lockstep" and plant["lockstep"]["waits_missed"] == 0, plant
    assert summary["log"]["dropped"] == 0, summary["log"]
    return summary


def _replay(run: Path, runs: Path, tmp: Path, *sets: str) -> tuple[int, dict[str, Any]]:
    """``redistro replay`` of ``run`` (into ``runs``): exit code, report."""
    report = tmp / "replay.json"
    options = [a for kv in sets for a in ("--set", kv)]
    done = run_cli(
        "--set", "scheduling.policy=batch", "--set", f"session.runs_dir={runs}", *options,
        "replay", str(run), "--json", str(report), timeout=300,
    )  # fmt: skip
    assert done.returncode in (0, 1), done.stdout[-3000:] + done.stderr[-3000:]
    out: dict[str, Any] = load_json(report)
    assert (done.returncode == 0) is out["identical"], out
    return done.returncode, out


@pytest.fixture(scope="module")
def runs(calibrated: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The short main job in lockstep over each transport, from one start."""
    tmp = tmp_path_factory.mktemp("lockstep")
    for transport in ("socket", "reflective", "zenoh"):
        s = _lockstep(calibrated, tmp, transport, f"ddm.transport={transport}")
        assert s["result"] == "ok" and s["inserted"] is True, (transport, s["reason"])
        plant = load_json(tmp / transport / "run" / "plant.json")
        assert plant["lockstep"]["bell"]["rung"] > 0, plant["lockstep"]  # (the nodes rang)
    return tmp


def test_every_transport_gives_the_same_log_to_the_byte_and_replays_it(
    runs: Path, tmp_path: Path
) -> None:
    digests = {
        t: load_json(runs / t / "run" / "summary.json")["log"]["digest"]
        for t in ("socket", "reflective", "zenoh")
    }
    assert len(set(digests.values())) == 1, digests
    _cycle_digests_chain_to_the_runs(runs / "socket" / "run")
    # two runs compared cycle by cycle, from their logs alone
    same = run_cli("log", "diff", str(runs / "socket" / "run"), str(runs / "zenoh" / "run"))
    assert same.returncode == 0 and same.stdout.startswith("identical: true"), same
    # each run again from its folder alone (its config, task and start)
    for transport in ("socket", "reflective", "zenoh"):
        run = runs / transport / "run"
        rc, out = _replay(run, runs / transport / "runs", tmp_path)
        assert rc == 0 and out["replay_digest"] == digests[transport], out
        assert out["result"] == "ok"
    # one gain changed: the replay names the first cycle, channel and field
    # that differ (the admittance acts from the first contact on)
    run = runs / "reflective" / "run"
    rc, out = _replay(run, runs / "reflective" / "runs", tmp_path, "ssc.force.k_adm=0.0021")
    first = out["first_difference"]
    assert rc == 1 and first is not None, out
    assert first["cycle"] > 100 and first["topic"].startswith("/r2/"), first
    assert first["field"] in ("tau_nm", "q_cmd_rad", "ref_xyz_m", "wrench_task"), first
    # the cycles' digests agree on where, and count the cycles that differ
    assert out["nodes"]["ssc"]["first_cycle"] == first["cycle"], out["nodes"]
    assert 0 < out["nodes"]["ssc"]["differing"] <= max(out["nodes"]["ssc"]["cycles"])
    report = tmp_path / "diff.json"
    differ = run_cli("log", "diff", str(run), out["replay"], "--json", str(report))
    assert differ.returncode == 1, differ.stdout + differ.stderr
    assert f"first difference at cycle {first['cycle']}, {first['topic']}" in differ.stdout
    assert load_json(report)["first_difference"] == first


def _cycle_digests_chain_to_the_runs(run: Path) -> None:
    """One digest a logged cycle (``/ssc/digest``); chained, they are the
    node's digest in summary.json."""
    import hashlib

    from redistro.log.mcapfile import read_log

    summary = load_json(run / "summary.json")
    rows = read_log(run / "session.mcap").arrays["/ssc/digest"]
    node = summary["log"]["nodes"]["ssc"]
    assert len(rows) == node["recorded"] > 0
    assert (rows["log_cycle"][1:] > rows["log_cycle"][:-1]).all()
    chain = hashlib.blake2b(rows["digest"].tobytes(), digest_size=16).hexdigest()
    assert chain == node["digest"]
    assert len({bytes(r) for r in rows["digest"]}) == len(rows)  # (each cycle's own)


def test_a_session_over_the_can_backplane_runs_to_its_end_in_lockstep(
    calibrated: Path, tmp_path: Path
) -> None:
    """Every board read and write a CAN FD frame (python-can's udp_multicast,
    authenticated), every node unchanged: too slow for real time on two
    vCPUs, whole in lockstep."""
    s = _lockstep(calibrated, tmp_path, "can", "plant.backplane=can")
    assert s["result"] == "ok" and s["inserted"] is True, s["reason"]
    plant = load_json(tmp_path / "can" / "run" / "plant.json")
    assert plant["backplane"] == "can" and plant["bad_frames"] == 0, plant


def test_the_view_of_a_recorded_run_draws_the_arms_and_its_segments(
    runs: Path, tmp_path: Path
) -> None:
    """``redistro view`` of the socket run, opened in headless Chromium: the
    arms are drawn (their blue-grey in the middle of the picture, where the
    background is white or grey), the panel names every segment, and the
    page's picture goes to the README."""
    from tests import browser

    run = runs / "socket" / "run"
    port = browser.free_port()
    shot = tmp_path / "view.png"
    with browser.served(["view", str(run), "--port", str(port)], port):
        text = browser.screenshot(f"http://127.0.0.1:{port}/", shot)
    for name in ("approach", "insertion", "pullback", "home"):
        assert name in text, text[:2000]
    assert "result: ok" in text
    armed = browser.bluish_pixels(shot, (0.2, 0.15, 0.7, 0.85))
    assert armed > 2000, armed
    browser.keep_for_readme(shot, "docs/figures/view-peg.png")


def test_the_live_view_follows_a_running_session_and_ends_with_it(
    calibrated: Path, tmp_path: Path
) -> None:
    """``redistro view --live`` beside a running main job (lockstep): the
    page draws the arms and names the task's segments; the session ended
    (Ctrl-C), the view ends by itself, exit 0, nothing left behind. The
    session is paused (``ctl pause``) while Chromium loads the page: on a
    loaded host the page once came up after the job's end."""
    import signal
    import subprocess
    import time

    from tests import browser
    from tests.helpers import REDISTRO, ROOT, attach_running, read_session_id

    runs = copy_runs(calibrated, tmp_path)
    session = subprocess.Popen(
        [*REDISTRO, *LOCKSTEP, "--set", f"session.runs_dir={runs}", "session",
         "tasks/peg_insertion.yaml", "--out", str(tmp_path / "run")],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
    )  # fmt: skip
    port = browser.free_port()
    view = None
    try:
        sid = read_session_id(session)
        attach_running(sid, "ssc", min_cycle=1, timeout=120).close()  # (started)
        deadline = time.monotonic() + 120.0
        while run_cli("ctl", sid, "pause", timeout=60).returncode != 0:  # (not yet taken)
            assert time.monotonic() < deadline and session.poll() is None, "no pause taken"
            time.sleep(0.2)  # (polling the session's start, with a deadline)
        view = subprocess.Popen(
            [*REDISTRO, "view", "--live", sid, "--port", str(port)],
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        from redistro.view import wait_served

        assert wait_served(port, 60.0), "the live view never served its page"
        text = browser.screenshot(f"http://127.0.0.1:{port}/", tmp_path / "live.png")
        assert "peg_insertion" in text and "running" in text, text[:2000]
        assert "segment:" in text, text[:2000]
        assert browser.bluish_pixels(tmp_path / "live.png", (0.2, 0.15, 0.7, 0.85)) > 2000
        session.send_signal(signal.SIGINT)  # the session's ordered end ...
        session.communicate(timeout=120)
        _, err = view.communicate(timeout=30)  # ... ends the view
        assert view.returncode == 0, err[-2000:]
    finally:
        for p in (session, view):
            if p is not None and p.poll() is None:
                p.kill()
                p.communicate()

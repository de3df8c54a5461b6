"""Peg insertion under uncertainty: the plant's hole is off where the
controller believes it (``workcell.hole``) and the insertion has to find it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from redistro.config import load_config
from redistro.control.search import Phase
from tests.helpers import LOCKSTEP, ROOT, copy_runs, load_json, run_cli

pytestmark = pytest.mark.peg

SEARCH = str(ROOT / "tests/data/peg_search.yaml")  # the short task's search, shorter
NARROW = str(ROOT / "tests/data/peg_search_narrow.yaml")  # ... searching 2 mm only
CFG = load_config(ROOT / "config/redistro.yaml")
MOUTH_Z = CFG.workcell.hole.xyz_m[2]
PEAK_N = 60.0  # the campaign's bound on the peak contact force


def test_a_campaign_finds_holes_2_to_3_mm_off(calibrated: Path, tmp_path: Path) -> None:
    """``redistro bench peg``: three whole insertions with the hole 2-3 mm
    off and turned up to 2 degrees; every peg reaches the bottom."""
    runs = copy_runs(calibrated, tmp_path)
    figures, plot = tmp_path / "peg.json", tmp_path / "peg.png"
    done = run_cli(
        *LOCKSTEP,
        "--set",
        f"session.runs_dir={runs}",
        "bench",
        "peg",
        "--task",
        SEARCH,
        "--trials",
        "3",
        "--offset-radius-mm",
        "3",
        "--offset-min-mm",
        "2",
        "--yaw-deg",
        "2",
        "--seed",
        "11",
        "--json",
        str(figures),
        "--plot",
        str(plot),
        timeout=900,
    )
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-3000:]
    out = load_json(figures)
    s = out["summary"]
    assert s["trials"] == 3 and s["inserted"] == 3, s
    assert s["guard_trips"] == 0 and s["max_peak_force_n"] <= PEAK_N, s
    for t in out["trials"]:
        assert 2.0 <= t["offset_mm"] <= 3.0 and abs(t["yaw_deg"]) <= 2.0, t
        assert t["result"] == "ok" and t["search_end"] == "in_hole", t
        assert t["search_mm"] > 0 and t["contact_to_bottom_s"] > 0, t
        assert abs(t["depth_mm"] - CFG.workcell.hole.depth_m * 1e3) <= 2.0, t
    # each trial drew its own hole, and the plant (not the controller) says where
    assert len({tuple(t["offset_xy_mm"]) for t in out["trials"]}) == 3
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the log has the search: the tip's path in the hole's plane
    run = Path(out["trials"][0]["run_dir"])
    drawn = run_cli("log", "plot", str(run), timeout=300)
    assert drawn.returncode == 0, drawn.stdout[-2000:] + drawn.stderr[-2000:]
    assert (run / "plots" / "r2-hole-plane.png").stat().st_size > 10_000


@pytest.mark.parametrize("parallel", [False, True], ids=["serial", "parallel"])
def test_a_hole_beyond_the_search_radius_ends_failed_and_lifted(
    calibrated: Path, tmp_path: Path, parallel: bool
) -> None:
    """4 mm off, beyond the task's 2 mm search (the shipped tasks search
    5 mm: docs/PERFORMANCE.md has the 8 mm case): the session ends
    ``failed`` with the reason, exit 1, no guard trip and no e-stop, the
    tool lifted off the fixture. Parallel (ssc.parallel_arms): r2's arm
    worker finds no hole, the clock's worker stops the task, r1's arm
    worker holds."""
    from redistro.log.mcapfile import read_log

    runs = copy_runs(calibrated, tmp_path)
    out = tmp_path / "run"
    done = run_cli(
        *LOCKSTEP,
        "--set",
        f"session.runs_dir={runs}",
        "--set",
        f"ssc.parallel_arms={str(parallel).lower()}",
        "--set",
        "plant.hole.offset_xyz_m=[0.004, 0, 0]",
        "session",
        NARROW,
        "--out",
        str(out),
        timeout=600,
    )
    assert done.returncode == 1, done.stdout[-4000:] + done.stderr[-3000:]
    summary = load_json(out / "summary.json")
    assert summary["result"] == "failed", summary["reason"]
    assert "hole not found within 2 mm" in summary["reason"], summary["reason"]
    assert "hole not found within 2 mm" in done.stdout
    assert "violations" not in summary, summary["violations"]
    assert {n: r["result"] for n, r in summary["nodes"].items()} == {
        "esc.r1": "ok",
        "esc.r2": "ok",
        "ssc": "failed",
    }
    assert summary["inserted"] is False and summary["search"]["phase"] == "not_found"
    assert summary["plant_insertion_depth_m"] < 0.005  # (the plant's truth: never in)
    assert summary["plant"]["hole"]["lateral_offset_m"] == pytest.approx(0.004)
    # the insertion's figures cover the whole segment: the search, then the 2 s lift
    insertion = next(
        s for s in summary["segments"] if (s["name"], s["robot"]) == ("insertion", "r2")
    )
    assert insertion["duration_s"] > insertion["first_contact_s"] + 2.0, insertion
    # the tool lifted off the fixture before the task ended
    sl = read_log(out / "session.mcap")
    plan = sl.arrays["/r2/plan"]
    assert plan["tcp_xyz_m"][-1, 2] > MOUTH_Z + 0.005, plan["tcp_xyz_m"][-1]
    # r1, moving in the same segment, stopped at the failure and held where
    # it was (the lift's clock restarts: its move's reference would go back)
    r1 = sl.arrays["/r1/plan"]
    n = min(len(r1), len(plan))
    lifting = (plan["segment"][:n] == 2) & (plan["phase"][:n] == Phase.NOT_FOUND)
    # (from the cycle after: the search gives up within r2's law, after r1's
    # plan went out; parallel, r1's arm worker hears it from the clock's a
    # cycle later)
    after = 2 if parallel else 1
    assert lifting.sum() > after and not r1["moving"][:n][lifting][after:].any()
    q1 = sl.arrays["/r1/feedback"]["q_rad"][:, 0]
    there = int(np.argmax(q1 > 0.14))  # (its goal 0.15 rad; 0 where it started)
    assert there > 0 and float(q1[there:].min()) > 0.08, (there, q1[there:].min())

"""A node's typed result: what its manager writes, the owner reads back, and
``summary.json`` is built from, one name per figure."""

from __future__ import annotations

import json
from pathlib import Path

from redistro.config.loader import load_config
from redistro.config.task import load_task
from redistro.process.result import EscResult, NodeResult, SscResult, WorkerResult
from redistro.session.summary import build_summary

ROOT = Path(__file__).parents[2]


def _esc(robot: str, **kw: object) -> NodeResult:
    r = NodeResult(node=f"esc.{robot}", kind="esc", rate_hz=200.0, cycles=1000, overruns=3)
    r.workers = [WorkerResult(name="acquisition", cycles=1000, compute_us={"p50": 12.0})]
    r.esc = EscResult(robot=robot, ddm={"sent": 10}, positions={"q_rad": [0.0] * 7})
    for k, v in kw.items():
        setattr(r, k, v)
    return r


def test_a_result_comes_back_from_its_file_as_it_was_written() -> None:
    r = _esc("r1", result="unsafe", reason="r1: torque", fault_monotonic_ns=5, fault_cycle=7)
    assert r.esc is not None
    r.esc.violation = {"quantity": "torque", "joint": 3}
    r.esc.freeze_monotonic_ns = [4, 9]
    back = NodeResult.from_dict(json.loads(json.dumps(r.as_dict())))
    assert back == r
    assert back.robot == "r1" and not back.ok
    assert isinstance(back.workers[0], WorkerResult) and back.workers[0].compute_us["p50"] == 12.0
    # a file of an older or newer manager: unknown names are left out, not fatal
    d = r.as_dict()
    d["overrun_cycles"] = 3
    assert NodeResult.from_dict(d) == r


def test_the_summary_takes_each_figure_from_the_typed_results() -> None:
    cfg = load_config(ROOT / "config" / "redistro.yaml")
    task = load_task(ROOT / "tasks" / "peg_insertion_short.yaml", cfg)
    ssc = NodeResult(node="ssc", kind="ssc", cycles=900, overruns=1)
    ssc.ssc = SscResult(
        robots=["r1", "r2"],
        ddm={"r1": {"sent": 1}, "r2": {"sent": 2}},
        segments=[{"name": "approach"}],
        insertion_depth_m=0.0399,
        hole_depth_m=0.04,
    )
    late = _esc("r2", result="estop", reason="e-stop from esc.r1", fault_monotonic_ns=20)
    first = _esc("r1", result="unsafe", reason="r1: torque limit", fault_monotonic_ns=10)
    assert first.esc is not None
    first.esc.violation = {"quantity": "torque"}
    first.esc.freeze_monotonic_ns = [11]
    s = build_summary(task, [late, first, ssc], {}, 0.0, 1.0, Path("/tmp/run"))
    # the earliest fault is the cause
    assert (s["result"], s["reason"]) == ("unsafe", "r1: torque limit")
    assert s["nodes"]["esc.r1"]["overruns"] == 3 and s["nodes"]["ssc"]["overruns"] == 1
    assert s["nodes"]["esc.r1"]["robot"] == "r1" and s["nodes"]["ssc"]["robot"] is None
    assert s["nodes"]["esc.r1"]["freeze_monotonic_ns"] == [11]
    assert s["nodes"]["esc.r1"]["workers"][0]["compute_us"] == {"p50": 12.0}
    assert s["violations"] == {"r1": {"quantity": "torque"}}
    assert set(s["positions"]) == {"r1", "r2"}  # the robots', nobody else's
    assert s["ddm"] == {
        "esc.r2": {"sent": 10},
        "esc.r1": {"sent": 10},
        "ssc": {"r1": {"sent": 1}, "r2": {"sent": 2}},
    }
    assert s["segments"] == [{"name": "approach"}] and s["inserted"] is True


def test_no_node_or_a_failed_plant_is_abnormal() -> None:
    cfg = load_config(ROOT / "config" / "redistro.yaml")
    task = load_task(ROOT / "tasks" / "peg_insertion_short.yaml", cfg)
    s = build_summary(task, [], {}, 0.0, 1.0, Path("/tmp/run"))
    assert (s["result"], s["reason"]) == ("abnormal", "no node ran")
    s = build_summary(task, [_esc("r1")], {"state": "failed", "error": "x"}, 0.0, 1.0, Path("/"))
    assert (s["result"], s["reason"]) == ("abnormal", "plant failed: x")
    s = build_summary(task, [_esc("r1", result="weird")], {}, 0.0, 1.0, Path("/"))
    assert s["result"] == "abnormal"
    assert s["inserted"] is False  # no SSC: nothing inserted


def test_every_result_figure_is_shown_or_left_out_on_purpose() -> None:
    """A figure added to the result type shows in summary.json by its name in
    the summary builder's list (or is named as left out): nothing else."""
    import dataclasses

    from redistro.session import summary

    fields = {f.name for f in dataclasses.fields(NodeResult)}
    shown = set(summary.NODE_FIGURES)
    assert not shown & summary.NODE_LEFT_OUT
    assert fields == shown | summary.NODE_LEFT_OUT, fields ^ (shown | summary.NODE_LEFT_OUT)
    worker_fields = {f.name for f in dataclasses.fields(WorkerResult)}
    assert set(summary.WORKER_FIGURES) <= worker_fields
    # a new figure: a field of the result and its name in the list
    r = _esc("r1")
    r.idle_slices = 5
    assert "idle_slices" not in summary.node_entry(r)
    try:
        summary.NODE_FIGURES += ("idle_slices",)
        assert summary.node_entry(r)["idle_slices"] == 5
    finally:
        summary.NODE_FIGURES = summary.NODE_FIGURES[:-1]


def test_inserted_comes_from_the_plant_with_the_belief_beside_it() -> None:
    from redistro.session.summary import _inserted

    s: dict = {}
    _inserted(s, True, 0.0400, 0.04, {"r2": {"depth_m": 0.0401}})
    assert s == {
        "inserted": True,
        "inserted_belief": True,
        "plant_insertion_depth_m": 0.0401,
        "belief_disagrees": False,
    }
    s = {}  # the controller believes it in; the real hole sits 3 mm lower
    _inserted(s, True, 0.0400, 0.04, {"r2": {"depth_m": 0.0370}})
    assert s["inserted"] is False and s["inserted_belief"] is True and s["belief_disagrees"]
    s = {}  # no plant's peg (a node alone): the belief
    _inserted(s, True, 0.0400, 0.04, {})
    assert s == {"inserted": True}


def test_an_insertion_into_an_objects_hole_is_judged_by_the_objects_in_that_hole(
    tmp_path: Path,
) -> None:
    """The plant's depths for the verdict: the objects that went into the
    task's target hole (its force move relative to ``block.hole``), not
    the flange pegs, nor objects in another object's hole."""
    from redistro.session.summary import _plant_depths

    cfg = load_config(ROOT / "tests" / "data" / "dual_peg_cell.yaml")
    task = tmp_path / "t.yaml"
    task.write_text(
        "task: t\nkind: strategy\nrobots: [r1, r2]\nsegments:\n"
        "  - {name: grasp, robot: r1, skill: grasp, scheme: position, duration_s: 2,\n"
        "     goal: {relative_to: block, pos_xyz_rot_xyz: [0, 0.07, 0.005, 0, 3.14159265, 0]}}\n"
        "  - {name: insert, robot: r2, scheme: force, duration_s: 5,\n"
        "     goal: {relative_to: block.hole, pos_xyz_rot_xyz: [0, 0, 0.12, 0, 3.14159265, 0],\n"
        "       force_xyz_torque_xyz: [0, 0, -8, 0, 0, 0], selection_vector: [0, 0, 1, 0, 0, 0]}}\n"
    )
    plant = {
        "pegs": {"r2": {"depth_m": 0.03}},
        "in_holes": {
            "peg": {"hole_of": "block", "depth_m": 0.039},
            "pin": {"hole_of": "crate", "depth_m": 0.02},
        },
    }
    assert _plant_depths(load_task(task, cfg), plant) == {"peg": plant["in_holes"]["peg"]}
    peg_task = load_task(ROOT / "tasks" / "peg_insertion_short.yaml", load_config())
    assert _plant_depths(peg_task, plant) == plant["pegs"]

"""``redistro bench dual --task carry|peg``: a campaign of two-arm jobs with
an object where the controller does not believe it is.

Each trial is a real session of the job under a config that has its
objects: the carry (``tasks/dual_carry_short.yaml`` by default,
``config/dual_arm.yaml``) with the carried object's truth
(``plant.objects.<name>``) drawn, or the dual-arm peg insertion
(``tasks/dual_peg_short.yaml``, ``config/dual_peg.yaml``) with the truth
of the object whose hole the peg goes into (r1 grasps it where it is: the
hole is off through the grasp). An offset uniform over the disc of
``--offset-radius-mm``, a yaw uniform within ``--yaw-deg``, seeded
``--seed + trial``. Per trial: the result, ``placed`` (carry) or
``inserted`` (peg) by the plant's truth, the displacement's error, the
squeeze's RMS error and peak over every carrying hand and segment, the
peak contact force, the nearest the arms came (the SSC's watch), guard
trips. The campaign's summary: the success rate and the medians.
"""

from __future__ import annotations

import dataclasses
import math
import random
from collections.abc import Callable
from typing import Any

from redistro.bench.campaign import median, run_trials
from redistro.config.model import Config, ObjectTruth
from redistro.config.task import Task, insertion_object
from redistro.errors import ConfigError

# a job's verdict, by the plant's truth
VERDICT = {"carry": "placed", "peg": "inserted"}
TASK_FILES = {"carry": "tasks/dual_carry_short.yaml", "peg": "tasks/dual_peg_short.yaml"}


def carried_object(task: Task) -> str:
    """The object the task carries (a ConfigError when it carries none)."""
    names = {s.carry.object for s in task.segments if s.carry.object}
    if len(names) != 1:
        raise ConfigError(
            f"{task.source}: bench dual --task carry needs a task that carries one object"
        )
    return names.pop()


def target_object(task: Task, job: str) -> str:
    """The object whose truth a trial draws: the one the carry carries, or
    the one whose hole the insertion works at (a ConfigError when none)."""
    if job == "carry":
        return carried_object(task)
    hole = insertion_object(task)
    if not hole:
        raise ConfigError(
            f"{task.source}: bench dual --task peg needs a task that inserts into one held "
            "object's hole (a force move relative to <object>.hole)"
        )
    return hole


def trial_config(cfg: Config, name: str, radius_m: float, yaw_deg: float, seed: int) -> Config:
    """The config of one trial: the object's truth drawn from ``seed``."""
    rng = random.Random(seed)
    r = radius_m * math.sqrt(rng.random())
    a = 2.0 * math.pi * rng.random()
    truth = ObjectTruth(
        offset_xy_m=[round(r * math.cos(a), 6), round(r * math.sin(a), 6)],
        yaw_deg=round(yaw_deg * (2.0 * rng.random() - 1.0), 4),
    )
    objects = {**cfg.plant.objects, name: truth}
    return dataclasses.replace(cfg, plant=dataclasses.replace(cfg.plant, objects=objects))


def trial_row(
    k: int, seed: int, truth: ObjectTruth, rc: int, summary: dict[str, Any]
) -> dict[str, Any]:
    carrying = [s for s in summary.get("segments") or [] if "squeeze_rms_error_n" in s]
    clearance = summary.get("clearance") or {}
    return {
        "trial": k,
        "seed": seed,
        "offset_xy_mm": [round(v * 1e3, 3) for v in truth.offset_xy_m],
        "yaw_deg": truth.yaw_deg,
        "result": summary.get("result"),
        "reason": summary.get("reason"),
        "placed": bool(summary.get("placed")),
        "inserted": bool(summary.get("inserted")),
        "depth_mm": _mm(summary.get("plant_insertion_depth_m")),
        "peak_force_n": (summary.get("search") or {}).get("peak_force_n"),
        "object_pose_error_m": summary.get("object_pose_error_m"),
        "object_pose_error_rad": summary.get("object_pose_error_rad"),
        "squeeze_rms_error_n": max((s["squeeze_rms_error_n"] for s in carrying), default=None),
        "squeeze_peak_n": max((s["squeeze_peak_n"] for s in carrying), default=None),
        "min_arm_distance_m": clearance.get("arms_min_m"),
        "guard_trips": len(summary.get("violations") or {}),
        "exit_code": rc,
        "run_dir": summary.get("run_dir"),
    }


def _mm(v: float | None) -> float | None:
    return round(v * 1e3, 3) if v is not None else None


def run(
    cfg: Config,
    task: Task,
    *,
    job: str,
    trials: int,
    radius_m: float,
    yaw_deg: float,
    seed: int,
    on_trial: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    name = target_object(task, job)
    cfgs = [trial_config(cfg, name, radius_m, yaw_deg, seed + k) for k in range(trials)]
    rows, out_root = run_trials(
        cfg,
        task.source,
        "dual",
        trials,
        lambda k: cfgs[k],
        lambda k, rc, summary: trial_row(k, seed + k, cfgs[k].plant.objects[name], rc, summary),
        on_trial,
    )
    verdict = VERDICT[job]
    good = [r for r in rows if r[verdict]]
    peaks = [float(r["squeeze_peak_n"]) for r in rows if r["squeeze_peak_n"] is not None]
    forces = [float(r["peak_force_n"]) for r in rows if r["peak_force_n"] is not None]
    return {
        "task": task.source,
        "job": job,
        "verdict": verdict,
        "object": name,
        "transport": cfg.ddm.transport,
        "offset_radius_mm": radius_m * 1e3,
        "yaw_deg": yaw_deg,
        "seed": seed,
        "runs_dir": str(out_root),
        "interrupted": len(rows) < trials,
        "summary": {
            "trials": len(rows),
            verdict: len(good),
            "success_rate": round(len(good) / len(rows), 3) if rows else None,
            "median_object_pose_error_m": median(rows, "object_pose_error_m", 6),
            "median_object_pose_error_rad": median(rows, "object_pose_error_rad", 6),
            "median_squeeze_rms_error_n": median(rows, "squeeze_rms_error_n", 6),
            "max_squeeze_peak_n": max(peaks) if peaks else None,
            "median_peak_force_n": median(rows, "peak_force_n"),
            "max_peak_force_n": max(forces) if forces else None,
            "min_arm_distance_m": min(
                (r["min_arm_distance_m"] for r in rows if r["min_arm_distance_m"] is not None),
                default=None,
            ),
            "guard_trips": sum(int(r["guard_trips"]) for r in rows),
        },
        "trials": rows,
    }


def print_campaign(out: dict[str, Any]) -> None:
    from rich.console import Console
    from rich.table import Table

    verdict = out["verdict"]
    t = Table(title=f"bench dual: {out['task']} ({out['object']}) over {out['transport']}")
    for col in ("trial", "offset mm", "yaw deg", "result", verdict, "error mm", "error mrad",
                "squeeze rms N", "squeeze peak N", "peak force N", "arms m"):  # fmt: skip
        t.add_column(col, justify="right")

    def mm(v: float | None, k: float = 1e3) -> str:
        return f"{v * k:.2f}" if v is not None else "-"

    for r in out["trials"]:
        off = math.hypot(*r["offset_xy_mm"])
        t.add_row(
            str(r["trial"]), f"{off:.2f}", str(r["yaw_deg"]), str(r["result"]),
            "yes" if r[verdict] else "no", mm(r["object_pose_error_m"]),
            mm(r["object_pose_error_rad"]), str(r["squeeze_rms_error_n"]),
            str(r["squeeze_peak_n"]), str(r["peak_force_n"]), str(r["min_arm_distance_m"]),
        )  # fmt: skip
    console = Console()
    console.print(t)
    s = out["summary"]
    what = (
        f"median error {mm(s['median_object_pose_error_m'])} mm "
        f"{mm(s['median_object_pose_error_rad'])} mrad; squeeze RMS error median "
        f"{s['median_squeeze_rms_error_n']} N, peak {s['max_squeeze_peak_n']} N"
        if out["job"] == "carry"
        else f"peak contact force median {s['median_peak_force_n']} N, "
        f"max {s['max_peak_force_n']} N"
    )
    console.print(
        f"{verdict} {s[verdict]}/{s['trials']}; {what}; "
        f"arms at least {s['min_arm_distance_m']} m apart; guard trips {s['guard_trips']}"
    )


def plot_campaign(out: dict[str, Any], path: str) -> None:
    """The grasp offsets drawn, coloured by outcome, and each trial's errors."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    verdict = out["verdict"]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 4.5))
    for ok, colour, label in ((True, "tab:green", verdict), (False, "tab:red", f"not {verdict}")):
        pts = [t for t in out["trials"] if t[verdict] == ok]
        if pts:
            ax.scatter([t["offset_xy_mm"][0] for t in pts], [t["offset_xy_mm"][1] for t in pts],
                       c=colour, label=label, s=30)  # fmt: skip
    r = out["offset_radius_mm"]
    ax.add_patch(Circle((0, 0), r, fill=False, ls="--", color="grey"))
    lim = max(r, 1.0) * 1.15
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.set_aspect("equal")
    ax.set_xlabel("object offset x [mm]")
    ax.set_ylabel("object offset y [mm]")
    ax.legend(loc="upper right", fontsize=8)
    ks = [t["trial"] for t in out["trials"]]
    if out["job"] == "carry":
        err = [(t["object_pose_error_m"] or math.nan) * 1e3 for t in out["trials"]]
        sq = [t["squeeze_rms_error_n"] or math.nan for t in out["trials"]]
        bx.plot(ks, err, "o-", label="displacement error [mm]")
        bx.plot(ks, sq, "s-", label="squeeze RMS error [N]")
        bx.axhline(2.0, ls=":", color="grey")
    else:
        bx.plot(ks, [t["peak_force_n"] or math.nan for t in out["trials"]], "o-",
                label="peak contact force [N]")  # fmt: skip
        bx.plot(ks, [t["depth_mm"] or math.nan for t in out["trials"]], "s-",
                label="depth by the plant [mm]")  # fmt: skip
    bx.set_xlabel("trial")
    bx.legend(fontsize=8)
    s = out["summary"]
    fig.suptitle(f"{s[verdict]}/{s['trials']} {verdict} ({out['transport']})")
    fig.tight_layout()
    from redistro import files

    with files.writing(path, text=False) as f:
        fig.savefig(f, dpi=110, format="png")
    plt.close(fig)

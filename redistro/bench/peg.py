"""``redistro bench peg``: a campaign of whole peg insertions with the hole
where the controller does not believe it is.

Each trial is a real session of the task (the plant, the ESCs, the SSC, the
ddms) with ``plant.hole`` drawing a random offset: lateral uniform over the
disc of ``--offset-radius-mm``, yaw uniform within ``--yaw-deg``, seeded
``--seed + trial``. The controller gets only the drawn work-cell
(``workcell.hole``); it has to find the hole. Per trial: the offset drawn
(from the plant's own report), the result, inserted or not, the depth, the
time from the first contact to the bottom, the peak contact force, the
search's path and how it ended. The campaign's summary: the success rate and
the medians. ``--plot`` draws the offsets coloured by outcome.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from redistro.bench.campaign import median, run_trials
from redistro.config.model import Config


def trial_config(
    cfg: Config, radius_m: float, yaw_deg: float, seed: int, min_radius_m: float = 0.0
) -> Config:
    hole = dataclasses.replace(
        cfg.plant.hole,
        offset_radius_m=radius_m,
        offset_min_radius_m=min_radius_m,
        yaw_range_deg=yaw_deg,
        seed=seed,
    )
    return dataclasses.replace(cfg, plant=dataclasses.replace(cfg.plant, hole=hole))


def trial_row(k: int, seed: int, rc: int, summary: dict[str, Any]) -> dict[str, Any]:
    """One trial's figures from its summary.json."""
    hole = (summary.get("plant") or {}).get("hole") or {}
    search = summary.get("search") or {}
    off = hole.get("offset_xyz_m") or [None, None, None]
    depth = summary.get("insertion_depth_m")
    return {
        "trial": k,
        "seed": seed,
        "offset_xy_mm": [round(v * 1e3, 3) if v is not None else None for v in off[:2]],
        "offset_mm": round(hole["lateral_offset_m"] * 1e3, 3) if hole else None,
        "yaw_deg": hole.get("yaw_deg"),
        "result": summary.get("result"),
        "reason": summary.get("reason"),
        "inserted": bool(summary.get("inserted")),
        "depth_mm": round(depth * 1e3, 2) if depth is not None else None,
        "contact_to_bottom_s": search.get("contact_to_bottom_s"),
        "peak_force_n": search.get("peak_force_n"),
        "search_mm": round(search["search_m"] * 1e3, 1) if "search_m" in search else None,
        "search_end": search.get("phase"),
        "guard_trips": len(summary.get("violations") or {}),
        "exit_code": rc,
        "run_dir": summary.get("run_dir"),
    }


def campaign_summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    inserted = [r for r in rows if r["inserted"]]
    forces = [float(r["peak_force_n"]) for r in rows if r.get("peak_force_n") is not None]
    return {
        "trials": len(rows),
        "inserted": len(inserted),
        "success_rate": round(len(inserted) / len(rows), 3) if rows else None,
        "median_contact_to_bottom_s": median(inserted, "contact_to_bottom_s"),
        "median_peak_force_n": median(rows, "peak_force_n"),
        "max_peak_force_n": max(forces) if forces else None,
        "median_search_mm": median(inserted, "search_mm"),
        "guard_trips": sum(int(r["guard_trips"]) for r in rows),
        "results": {
            res: sum(r["result"] == res for r in rows) for res in {r["result"] for r in rows}
        },
    }


def run(
    cfg: Config,
    task_path: str,
    *,
    trials: int,
    radius_m: float,
    yaw_deg: float,
    seed: int,
    min_radius_m: float = 0.0,
    overrides: list[str],
    on_trial: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    rows, out_root = run_trials(
        cfg,
        task_path,
        "peg",
        trials,
        lambda k: trial_config(cfg, radius_m, yaw_deg, seed + k, min_radius_m),
        lambda k, rc, summary: trial_row(k, seed + k, rc, summary),
        on_trial,
    )
    return {
        "task": task_path,
        "transport": cfg.ddm.transport,
        "offset_radius_mm": radius_m * 1e3,
        "offset_min_mm": min_radius_m * 1e3,
        "yaw_deg": yaw_deg,
        "seed": seed,
        "overrides": overrides,
        "runs_dir": str(out_root),
        "interrupted": len(rows) < trials,
        "summary": campaign_summary(rows),
        "trials": rows,
    }


def print_campaign(out: dict[str, Any]) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"bench peg: {out['task']} over {out['transport']}")
    for col in ("trial", "offset mm", "yaw deg", "result", "inserted", "depth mm",
                "contact->bottom s", "peak N", "search mm", "search end"):  # fmt: skip
        t.add_column(col, justify="right")
    for r in out["trials"]:
        t.add_row(
            str(r["trial"]),
            str(r["offset_mm"]),
            str(r["yaw_deg"]),
            str(r["result"]),
            "yes" if r["inserted"] else "no",
            str(r["depth_mm"]),
            str(r["contact_to_bottom_s"]),
            str(r["peak_force_n"]),
            str(r["search_mm"]),
            str(r["search_end"]),
        )
    console = Console()
    console.print(t)
    s = out["summary"]
    console.print(
        f"inserted {s['inserted']}/{s['trials']}; median contact->bottom "
        f"{s['median_contact_to_bottom_s']} s; peak force median {s['median_peak_force_n']} N, "
        f"max {s['max_peak_force_n']} N; median search {s['median_search_mm']} mm; "
        f"guard trips {s['guard_trips']}"
    )


def plot_campaign(out: dict[str, Any], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    fig, ax = plt.subplots(figsize=(5.5, 5.5))
    r = out["offset_radius_mm"]
    ax.add_patch(Circle((0, 0), r, fill=False, ls="--", color="grey", label=f"{r:g} mm"))
    for ok, colour, label in ((True, "tab:green", "inserted"), (False, "tab:red", "not inserted")):
        pts = [
            t["offset_xy_mm"]
            for t in out["trials"]
            if t["inserted"] == ok and t["offset_xy_mm"][0] is not None
        ]
        if pts:
            ax.scatter([p[0] for p in pts], [p[1] for p in pts], c=colour, label=label, s=30)
    ax.set_aspect("equal")
    lim = max(r, 1.0) * 1.15
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.set_xlabel("hole offset x [mm]")
    ax.set_ylabel("hole offset y [mm]")
    s = out["summary"]
    ax.set_title(
        f"{s['inserted']}/{s['trials']} inserted, yaw within ±{out['yaw_deg']:g}°"
        f" ({out['transport']})"
    )
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    from redistro import files

    with files.writing(path, text=False) as f:
        fig.savefig(f, dpi=110, format="png")
    plt.close(fig)

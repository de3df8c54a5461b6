"""``redistro node``: one node of a strategy task, started alone.

The nodes of a robot group need not share a host: an ESC runs beside the
plant (it drives the plant's boards), the SSC anywhere its DDM reaches the
ESCs' DDMs (socket transport: ``ddm.esc_hosts``/``ddm.esc_ports``;
reflective: ``ddm.peers``). Nodes started alone meet on a *link id*
(``--link``): the ports no config names are derived from it, as a session
derives them from its session id. Each node has its own session (its own
Local Data, run folder and summary) and no global clock: the SSC's worker
waits for every robot's first feedback (the start-up datum), the ESCs wait
for the first command (frozen until then, ``starving`` if none comes within
``ddm.connect_timeout_s``).

    redistro plant                                     # prints its session id
    redistro node esc r2 tasks/peg_insertion.yaml --plant SID --link L
    redistro node esc r1 tasks/peg_insertion.yaml --plant SID --link L
    redistro node ssc tasks/peg_insertion.yaml --link L
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from redistro import files
from redistro.config.hardware import load_hardware
from redistro.config.model import Config
from redistro.config.task import load_task
from redistro.errors import ConfigError, IPCError, LayoutError
from redistro.esc.plan import esc_spec
from redistro.ipc import session as ipc_session
from redistro.process.session_owner import run_nodes, write_json
from redistro.session.preflight import (
    check_key,
    check_motion,
    check_zenoh_tls,
    check_zenoh_users,
    positions_file,
    unknown_positions,
)
from redistro.session.progress import Progress, ddm_pace
from redistro.session.summary import build_summary, wall_budget_s
from redistro.ssc.plan import ssc_spec

DEFAULT_LINK = "redistro"


def run_node(
    cfg: Config,
    kind: str,
    task_path: str,
    *,
    robot: str = "",
    plant_session: str = "",
    link: str = DEFAULT_LINK,
    out_dir: str | None = None,
    say: Callable[[str], None] | None = None,
) -> int:
    """Run one node (``esc`` of ``robot`` beside the plant of ``plant_session``,
    or ``ssc``) of a strategy task to its end; exit code 0 when it ends ok."""
    say = say or (lambda text: print(text, flush=True))
    task = load_task(task_path, cfg)
    _check_node(cfg, task, task_path, kind, robot, plant_session, link)
    hardware = load_hardware(cfg)
    for name in ipc_session.reap():
        print(f"reaped {name} (left by a dead session)", file=sys.stderr)
    started = time.time()
    with ipc_session.Session.create() as s:
        run_dir = Path(out_dir) if out_dir else Path(cfg.session.runs_dir) / s.id
        files.make_folder(run_dir, "run folder")
        messages = str(run_dir / "messages.log")
        os.close(files.create(messages))  # (new: the manager only appends to it)
        if kind == "esc":
            spec = esc_spec(
                cfg,
                task,
                robot,
                hardware[robot],
                s.id,
                positions_file=str(positions_file(cfg, robot)),
                messages_path=messages,
                link=link,
                plant_session=plant_session,
                run_dir=str(run_dir),
            )
            where = f"plant of session {plant_session}"
        else:
            spec = ssc_spec(
                cfg,
                task,
                s.id,
                run_dir=str(run_dir),
                messages_path=messages,
                link=link,
            )
            where = f"robots {', '.join(task.robots)}"
        say(f"session {s.id}")
        say(
            f"node {spec.node} of task {task.task} ({where}); link {link!r}; "
            f"ddm {cfg.ddm.transport} {ddm_pace(cfg)}; run folder {run_dir}"
        )
        progress = Progress(s.id, [spec], say)
        progress.ssc_segments = [(g.name, g.duration_s) for g in task.segments]
        try:
            # the node waits for its peers (datum, first command) within its
            # connect timeout; then the task runs on the boards' clock
            budget = wall_budget_s(task) + cfg.ddm.connect_timeout_s
            results = run_nodes([spec], s, budget_s=budget, on_wait=progress)
        finally:
            progress.close()
    summary = build_summary(task, results, {}, started, time.time(), run_dir)
    _node_summary(cfg, summary, results, run_dir, spec.node, link, robot, plant_session)
    write_json(run_dir / "summary.json", summary)
    for r in results:
        say(f"{r.node}: {r.result} {r.reason}".rstrip())
    say(f"result: {summary['result']}" + (f" ({summary['reason']})" if summary["reason"] else ""))
    say(f"wrote {run_dir / 'summary.json'}")
    return 0 if summary["result"] == "ok" else 1


def _check_node(
    cfg: Config, task: Any, task_path: str, kind: str, robot: str, plant_session: str, link: str
) -> None:
    """Everything a node alone needs, before anything starts (ConfigError)."""
    if task.kind != "strategy":
        raise ConfigError(f"{task_path}: a node runs alone only in a strategy task (kind strategy)")
    if not link:
        raise ConfigError("--link: expected a non-empty id")
    from redistro.config.checks import ZENOH_GROUP

    if not ZENOH_GROUP.match(link):
        # it names the group's zenoh keys and derives its ports
        raise ConfigError(f"--link: expected 1-64 letters, digits, _ or -, got {link!r:.60}")
    if kind == "esc":
        if robot not in task.robots:
            raise ConfigError(
                f"robot {robot!r}: not in the task's robots ({', '.join(task.robots)})"
            )
        if not plant_session:
            raise ConfigError("--plant: the session id of a running plant is needed")
        _check_plant(plant_session)
        why = unknown_positions(cfg, task).get(robot)
        if why:
            raise ConfigError(f"motion refused: {why}; run tasks/self_calibration.yaml first")
    check_key(cfg, needed=True)
    check_zenoh_users(cfg, ["ssc" if kind == "ssc" else f"esc.{robot}"], link)
    check_zenoh_tls(cfg)
    check_motion(cfg, task)


def _node_summary(
    cfg: Config,
    summary: dict[str, Any],
    results: list[Any],
    run_dir: Path,
    node: str,
    link: str,
    robot: str,
    plant_session: str,
) -> None:
    """A node's summary: its log, its link; an ESC's plant and positions
    (the SSC's figures are the SSC's; the plant is another process)."""
    from redistro.log.mcapfile import finish_run_log

    with contextlib.suppress(Exception):  # the log never fails the node
        log_info = finish_run_log(run_dir, {r.node: r.cycles for r in results})
        if log_info:
            summary["log"] = log_info
    summary["node"] = node
    summary["link"] = link
    summary.pop("plant", None)  # the plant is another process (maybe another host)
    if robot and node.startswith("esc"):
        summary["plant_session"] = plant_session
        for key in ("segments", "insertion_depth_m", "hole_depth_m", "inserted"):
            summary.pop(key, None)  # the SSC's figures
        src = positions_file(cfg, robot)
        if src.exists():
            files.replace(run_dir / f"positions.{robot}.json", src.read_bytes())


def _check_plant(session_id: str) -> None:
    from redistro.drivers.io.bank import RegisterBank

    try:
        bank = RegisterBank.attach(session_id)
    except (IPCError, LayoutError, OSError, ValueError) as exc:
        raise ConfigError(
            f"--plant {session_id}: no running plant of that session ({exc})"
        ) from None
    bank.close()

"""``redistro replay RUN``: run a recorded lockstep session again and compare.

A lockstep session (``--clock lockstep``) writes ``replay.json`` into its
run folder before anything starts (:mod:`redistro.session.start`): its
config (resolved), its task file's text, and the state it started from
(the joint positions files and the arms' pose kept between sessions).
The plant's truth (the hole's offset, the noise's seed) is in the
config. ``replay`` restores that state into a folder of its own under the
runs folder, runs the same task in lockstep (``--set`` values go on top:
one gain changed, say), and compares the logs: ``identical`` when the
digests agree, else the first cycle, channel and field that differ. Exit
0 when identical, 1 when not, 2 on bad input.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any

from redistro import files
from redistro.config.model import Config
from redistro.errors import ConfigError, clipped
from redistro.session.start import REPLAY_FILE

KEYS = ("clock", "config", "task_name", "task_text", "start")


def load_run(arg: str) -> tuple[Path, dict[str, Any], dict[str, Any]]:
    """The run folder, its replay.json and its summary; ConfigError (one
    line) when it is not a recorded lockstep run that can be replayed."""
    run = Path(arg)
    where = clipped(arg)
    if not run.is_dir():
        raise ConfigError(f"replay: {where}: no such run folder")
    summary_path = run / "summary.json"
    if not summary_path.is_file():
        raise ConfigError(f"replay: {where}: not a run folder (no summary.json)")
    if not (run / REPLAY_FILE).is_file():
        raise ConfigError(f"replay: {where}: not a lockstep run (no {REPLAY_FILE})")
    doc = _json(run / REPLAY_FILE)
    summary = _json(summary_path)
    missing = [k for k in KEYS if k not in doc]
    if missing or doc.get("clock") != "lockstep" or not isinstance(doc.get("start"), dict):
        why = f"no {missing[0]}" if missing else "not a lockstep run"
        raise ConfigError(f"replay: {where}/{REPLAY_FILE}: {why}")
    digest = summary.get("log", {}).get("digest") if isinstance(summary.get("log"), dict) else None
    if not isinstance(digest, str) or not (run / "session.mcap").is_file():
        raise ConfigError(f"replay: {where}: the run has no session log to compare with")
    operator = summary.get("operator")
    if isinstance(operator, dict) and operator.get("accepted"):
        raise ConfigError(
            f"replay: {where}: its operator commanded it (redistro ctl, "
            f"{operator['accepted']} commands): a replay cannot repeat when they came"
        )
    return run, doc, summary


def _json(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ConfigError(f"replay: {clipped(str(path))}: not readable JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"replay: {clipped(str(path))}: not a JSON object")
    return doc


def replay_config(doc: dict[str, Any], overrides: list[str], folder: Path) -> Config:
    """The run's config, ``overrides`` on top, its runs folder and the
    arms' pose file in ``folder``, in lockstep."""
    from redistro.config.loader import reload_config

    if not isinstance(doc["config"], dict):
        raise ConfigError(f"replay: {REPLAY_FILE}: config: not a mapping")
    cfg = reload_config(doc["config"], overrides, REPLAY_FILE)
    session = dataclasses.replace(cfg.session, runs_dir=str(folder), clock="lockstep")
    plant = dataclasses.replace(cfg.plant, pose_file=str(folder / cfg.session.plant_pose_file))
    return dataclasses.replace(cfg, session=session, plant=plant)


def restore(cfg: Config, doc: dict[str, Any], folder: Path) -> Path:
    """The run's start state and task into ``folder``; the task's path."""
    from redistro.session.preflight import positions_file

    start = doc["start"]
    for robot, text in dict(start.get("positions") or {}).items():
        if isinstance(text, str):
            path = positions_file(cfg, str(robot))
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
    if isinstance(start.get("plant_pose"), str):
        Path(cfg.plant.pose_file).write_text(start["plant_pose"])
    task = folder / Path(str(doc["task_name"])).name
    task.write_text(str(doc["task_text"]))
    return task


def run_replay(arg: str, overrides: list[str], runs_dir: str, json_path: str | None) -> int:
    import tempfile

    from redistro.session.run import run_session

    run, doc, summary = load_run(arg)
    replay_config(doc, overrides, Path(runs_dir))  # (a bad --set: refused before anything)
    Path(runs_dir).mkdir(parents=True, exist_ok=True)
    prefix = f"replay-{time.strftime('%Y%m%dT%H%M%S')}-"
    folder = Path(tempfile.mkdtemp(prefix=prefix, dir=runs_dir))  # (a new one, whatever ran)
    cfg = replay_config(doc, overrides, folder)
    task = restore(cfg, doc, folder)
    out = folder / "run"
    run_session(cfg, str(task), out_dir=str(out), say=lambda line: print(f"  {line}"))
    try:
        again = json.loads((out / "summary.json").read_text())
    except (OSError, ValueError):
        again = {}
    report = compare(run, out, summary, again)
    print(report_line(report))
    if json_path:
        files.replace(Path(json_path), json.dumps(report, indent=1) + "\n")
    return 0 if report["identical"] else 1


def compare(run: Path, again: Path, summary: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    """The recorded run against its replay: the digests, and when they
    differ the first cycle, channel and field that do."""
    a = summary.get("log", {}).get("digest")
    b = (new.get("log") or {}).get("digest")
    report: dict[str, Any] = {
        "run": str(run),
        "replay": str(again),
        "identical": bool(a) and a == b,
        "digest": a,
        "replay_digest": b,
        "result": new.get("result", "none"),
    }
    if not report["identical"] and (again / "session.mcap").is_file():
        from redistro.log.diff import compare_logs

        try:
            found = compare_logs(run / "session.mcap", again / "session.mcap")
        except ValueError as exc:  # (a log that does not read: named in the report)
            report["unreadable"] = str(exc)
            return report
        report["nodes"] = found["nodes"]
        report["first_difference"] = found.get("first_difference")
        # (a run recorded before the cycles' digests chained its log.digest
        # otherwise: the same data, cycle by cycle, is the same run)
        report["identical"] = bool(found["identical"])
    return report


def report_line(report: dict[str, Any]) -> str:
    from redistro.log.diff import report_line as line

    if report["identical"]:
        return f"identical: true (log.digest {report['digest']})"
    if report.get("unreadable"):
        return f"identical: false ({report['unreadable']})"
    if not report.get("first_difference"):
        return f"identical: false (the replay ended {report['result']}, no log to compare)"
    return line(report)

"""``redistro``: the one command-line entry point.

Nothing heavy is imported at module level: :func:`main` blocks the runtime
signals before numpy (and its threads) exist.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
from typing import Any, NoReturn

from redistro.errors import ConfigError, RedistroError


class _Parser(argparse.ArgumentParser):
    """argparse that reports a bad command line as one ConfigError line."""

    def error(self, message: str) -> NoReturn:
        raise ConfigError(f"{self.prog}: {message}")


def _common(dest_suffix: str) -> _Parser:
    """--config/--set/-v, accepted before or after the subcommand."""
    p = _Parser(add_help=False)
    p.add_argument(
        "--config",
        dest="config" + dest_suffix,
        default=None,
        help="config file (default: config/redistro.yaml if present)",
    )
    p.add_argument(
        "--set",
        dest="set" + dest_suffix,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set bench.rate_hz=500",
    )
    p.add_argument(
        "-v", "--verbose", dest="verbose" + dest_suffix, action="store_true", help="debug logs"
    )
    return p


def _clock_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--clock",
        choices=("realtime", "lockstep"),
        default=None,
        help="what paces the nodes (session.clock): their timers, or the plant, "
        "as fast as the CPUs allow",
    )


def _campaign_args(
    p: argparse.ArgumentParser, what: str, *, trials: int, radius_mm: float, yaw_deg: float
) -> None:
    """A campaign's options (bench peg, bench dual): trials, the offset of
    ``what`` drawn per trial, the seed, the outputs."""
    p.add_argument("--trials", type=_positive_int, default=trials, help="sessions to run")
    p.add_argument(
        "--offset-radius-mm",
        type=float,
        default=radius_mm,
        help=f"the {what}'s offset, uniform over the disc of this radius [mm]",
    )
    p.add_argument(
        "--yaw-deg",
        type=float,
        default=yaw_deg,
        help=f"the {what}'s yaw, uniform within +- this [deg]",
    )
    p.add_argument("--seed", type=int, default=0, help="trial k draws with seed + k")
    _clock_arg(p)
    p.add_argument("--json", dest="json_path", default=None, help="write the figures here")
    p.add_argument("--plot", default=None, help="draw the offsets by outcome into this PNG")


@functools.cache
def _parser() -> argparse.ArgumentParser:
    """The command line's parser (kept: parsing leaves it as it was, and a
    caller of :func:`main` in one process, the tests', builds it once)."""
    p = _Parser(
        prog="redistro", description="A multi-process robot controller.", parents=[_common("")]
    )
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    common = _common("_sub")

    bench = sub.add_parser("bench", help="benchmarks")
    bsub = bench.add_subparsers(dest="bench", required=True, parser_class=_Parser)
    c = bsub.add_parser("cycle", help="a real manager with N busy workers", parents=[common])
    c.add_argument("--rate", type=float, default=None, help="cycle rate [Hz] (bench.rate_hz)")
    c.add_argument("--workers", type=int, default=5)
    c.add_argument("--seconds", type=float, default=5.0)
    c.add_argument("--work-us", type=float, default=0.0, help="busy work per worker per cycle")
    c.add_argument(
        "--stages",
        default=None,
        help="stage sizes, e.g. 1,1,1 (serial, default), 3 or parallel, 2,1",
    )
    c.add_argument("--pin", action="store_true", help="pin each parallel worker to a CPU")
    c.add_argument(
        "--compare-stages",
        action="store_true",
        help="run the same work serial, then as one parallel stage",
    )
    c.add_argument("--no-baseline", action="store_true", help="skip the cyclictest baseline")
    c.add_argument("--message-every", type=int, default=0, help=argparse.SUPPRESS)
    c.add_argument("--json", dest="json_path", default=None, help="write the figures here")
    i = bsub.add_parser(
        "ipc", help="Local Data snapshot vs multiprocessing Pipe and Queue", parents=[common]
    )
    i.add_argument("--samples", type=int, default=5000)
    i.add_argument("--gap-us", type=float, default=200.0, help="pause between records")
    i.add_argument(
        "--robots", type=int, default=2, help="robots in the record (one block each): 1 or 2"
    )
    i.add_argument("--json", dest="json_path", default=None)

    pb = bsub.add_parser(
        "plant", help="plant real-time factor and driver cycle cost", parents=[common]
    )
    pb.add_argument("--backplane", choices=["shm", "can"], default=None, help="plant.backplane")
    pb.add_argument("--seconds", type=float, default=5.0)
    pb.add_argument("--rate", type=float, default=200.0, help="driver cycle rate [Hz]")
    pb.add_argument("--json", dest="json_path", default=None)

    gr = bsub.add_parser(
        "group",
        help="a whole robot group's session, measured per process (plant, nodes, ddms, log)",
        parents=[common],
    )
    gr.add_argument("task", help="task file, e.g. tasks/peg_insertion.yaml")
    gr.add_argument("--json", dest="json_path", default=None, help="write the figures here")
    _clock_arg(gr)

    pg = bsub.add_parser(
        "peg",
        help="a campaign of peg insertions with the hole off where the controller believes it",
        parents=[common],
    )
    pg.add_argument(
        "--task", default="tasks/peg_insertion_short.yaml", help="the peg insertion task"
    )
    _campaign_args(pg, "hole", trials=20, radius_mm=3.0, yaw_deg=2.0)
    pg.add_argument(
        "--offset-min-mm",
        type=float,
        default=0.0,
        help="... over the ring outside this radius [mm] (default 0: the whole disc)",
    )

    du = bsub.add_parser(
        "dual",
        help="a campaign of two-arm jobs (a carry, a peg insertion) with the object off "
        "where the controller believes it",
        parents=[common],
    )
    du.add_argument("--task", choices=["carry", "peg"], default="carry", help="the two-arm job")
    du.add_argument(
        "--task-file",
        default=None,
        help="the job's task file (default tasks/dual_carry_short.yaml, tasks/dual_peg_short.yaml)",
    )
    _campaign_args(du, "object", trials=10, radius_mm=5.0, yaw_deg=3.0)

    dd = bsub.add_parser(
        "ddm",
        help="the DDM transports alone: N ESC ddms and their SSC ddm, no plant",
        parents=[common],
    )
    dd.add_argument("--transport", required=True, choices=["socket", "reflective", "zenoh"])
    dd.add_argument("--robots", type=_positive_int, default=2, help="ESC ddms (1-16)")
    dd.add_argument("--rate", type=float, default=200.0, help="commands per robot per second")
    dd.add_argument("--seconds", type=float, default=10.0, help="how long to measure")
    dd.add_argument(
        "--floor",
        action="store_true",
        help="then the socket floor (bare receives and replies; over zenoh, the zenoh floor "
        "too: bare zenoh-python puts and replies), the same robots and rate, 3 s",
    )
    dd.add_argument("--json", dest="json_path", default=None, help="write the figures here")

    kb = bsub.add_parser(
        "kernels",
        help="each compiled kernel against its numpy reference, CPU per call",
        parents=[common],
    )
    kb.add_argument("--calls", type=int, default=5000, help="calls timed per piece")
    kb.add_argument("--json", dest="json_path", default=None, help="write the figures here")

    cl = bsub.add_parser(
        "clearance",
        help="the SSC's clearance watch: CPU per cycle, arms at rest and one swinging in",
        parents=[common],
    )
    cl.add_argument("--rate", type=float, default=None, help="cycles per second (ssc.rate_hz)")
    cl.add_argument("--seconds", type=float, default=10.0, help="the arms at rest this long")
    cl.add_argument("--json", dest="json_path", default=None, help="write the figures here")

    pl = sub.add_parser("plant", help="run the simulated plant alone", parents=[common])
    pl.add_argument("--gui", action="store_true", help="open the PyBullet window")
    pl.add_argument("--seconds", type=float, default=0.0, help="stop after this long (0: Ctrl-C)")

    se = sub.add_parser(
        "session", help="run a task: plant on, nodes, plant off, run folder", parents=[common]
    )
    se.add_argument("task", help="task file, e.g. tasks/self_calibration.yaml")
    se.add_argument("--out", default=None, help="run folder (default: runs/<session-id>/)")
    _clock_arg(se)

    no = sub.add_parser(
        "node", help="one node of a strategy task, alone (nodes may run on different hosts)"
    )
    nsub = no.add_subparsers(dest="node_kind", required=True, parser_class=_Parser)
    ne = nsub.add_parser(
        "esc", help="the ESC of one robot, beside a running plant", parents=[common]
    )
    ne.add_argument("robot", help="the robot, e.g. r2")
    ne.add_argument("task", help="strategy task file, e.g. tasks/peg_insertion.yaml")
    ne.add_argument("--plant", required=True, help="session id of the running plant")
    ns = nsub.add_parser("ssc", help="the SSC of the robot group", parents=[common])
    ns.add_argument("task", help="strategy task file, e.g. tasks/peg_insertion.yaml")
    for q in (ne, ns):
        q.add_argument(
            "--link",
            default="redistro",
            help="id the group's nodes meet on (ports not set in config derive from it)",
        )
        q.add_argument("--out", default=None, help="run folder (default: runs/<session-id>/)")

    vw = sub.add_parser(
        "view", help="a recorded run in the browser, in 3D, with a timeline", parents=[common]
    )
    vw.add_argument("run", nargs="?", default=None, help="the run folder (with its session.mcap)")
    vw.add_argument(
        "--live",
        nargs="?",
        const="",
        default=None,
        metavar="SESSION",
        help="a running session instead (its id; default: the only one)",
    )
    vw.add_argument("--port", type=int, default=8080, help="the page's port (default 8080)")
    vw.add_argument(
        "--bind", default="127.0.0.1", help="the address (not loopback: the page asks a token)"
    )

    ct = sub.add_parser(
        "ctl",
        help="the operator's pause, resume, stop, e-stop and jog of a running session",
        parents=[common],
    )
    ct.add_argument("session", help="the session's id (the first line `redistro session` prints)")
    ct.add_argument("order", choices=["pause", "resume", "stop", "estop", "jog"])
    ct.add_argument("robot", nargs="?", default=None, help="jog: the robot whose tool moves")
    ct.add_argument("--mm", nargs=3, type=float, default=[0.0, 0.0, 0.0],
                    metavar=("X", "Y", "Z"),
                    help="jog: the tool's step along world x, y, z [mm] (at most 5)")  # fmt: skip
    ct.add_argument("--deg", nargs=3, type=float, default=[0.0, 0.0, 0.0],
                    metavar=("RX", "RY", "RZ"),
                    help="jog: its turn about world x, y, z [degrees] (at most 2)")  # fmt: skip
    ct.add_argument("--key", default=None, help="the key file (default: the session's own)")
    ct.add_argument("--timeout", type=float, default=15.0, help="wait this long for the answer [s]")

    rp = sub.add_parser(
        "replay",
        help="run a recorded lockstep session again and compare its log, cycle by cycle",
        parents=[common],
    )
    rp.add_argument("run", help="the run folder of a lockstep session")
    rp.add_argument("--json", dest="json_path", default=None, help="write the comparison here")

    fa = sub.add_parser(
        "faults", help="break a running session on purpose, scenario by scenario", parents=[common]
    )
    fa.add_argument("--only", action="append", default=[], metavar="NAME", help="run only NAME")
    _clock_arg(fa)
    fa.add_argument("--list", action="store_true", help="list the scenarios and stop")
    fa.add_argument("--json", dest="json_path", default=None, help="write the table as JSON")
    fa.add_argument("--seed", type=int, default=0, help="seed of the injection moments")
    fa.add_argument(
        "--retries",
        type=int,
        default=0,
        help="run a failed scenario again up to N times (the row keeps the failed attempts)",
    )

    sub.add_parser("clean", help="remove IPC objects left by dead sessions", parents=[common])
    ck = sub.add_parser(
        "check",
        help="check a task and the config as a session would, start nothing",
        parents=[common],
    )
    ck.add_argument("task", help="task YAML file")

    lg = sub.add_parser("log", help="read a run's session log back")
    lsub = lg.add_subparsers(dest="log_command", required=True, parser_class=_Parser)
    ls = lsub.add_parser(
        "summary", help="task, result, segments, figures, faults as tables", parents=[common]
    )
    lp = lsub.add_parser(
        "plot", help="PNG figures of joints, wrench, pose, timing", parents=[common]
    )
    lp.add_argument("--out", default=None, help="folder for the PNGs (default: RUN/plots)")
    le = lsub.add_parser("export", help="one CSV per topic", parents=[common])
    le.add_argument("--csv", required=True, metavar="DIR", help="folder for the CSV files")
    ls.add_argument("--json", action="store_true", help="print the summary as JSON")
    ld = lsub.add_parser(
        "diff",
        help="two runs' logs compared cycle by cycle: identical, or the first cycle, "
        "channel and field that differ (exit 0 identical, 1 not)",
        parents=[common],
    )
    ld.add_argument("--json", dest="json_path", metavar="FILE", help="the report as JSON")
    for q in (ls, lp, le, ld):
        q.add_argument("run", help="run folder, session id under runs/, or a session.mcap")
    ld.add_argument("other", help="the run to compare RUN with (as RUN)")

    tp = sub.add_parser("top", help="live view of the running sessions", parents=[common])
    tp.add_argument("session", nargs="?", default=None, help="only this session id")
    tp.add_argument("--once", action="store_true", help="one sample, then exit")
    tp.add_argument("--json", action="store_true", help="with --once: print JSON")
    tp.add_argument("--interval", type=float, default=1.0, help="refresh period [s]")
    tp.add_argument(
        "--zenoh",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="also the groups seen through this zenoh session (tcp/host:port of an SSC's "
        "ddm; ddm.zenoh.users_file names the viewer's password); repeatable",
    )
    _bridge_parser(sub, common)
    return p


def _bridge_parser(sub: Any, common: argparse.ArgumentParser) -> None:
    br = sub.add_parser(
        "bridge",
        help="a running session's joint states, wrenches and segment as ROS 2 topics "
        "over Zenoh (rmw_zenoh's conventions), read-only",
        parents=[common],
    )
    br.add_argument("session", nargs="?", default=None, help="its id (default: the only one)")
    br.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="zenoh endpoint to listen on (default: the session's ros2.listen); repeatable",
    )


def main(argv: list[str] | None = None) -> int:
    from redistro.ipc.signals import block_runtime_signals

    block_runtime_signals()
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    try:
        args = _parser().parse_args(argv)
        config, overrides = _config_args(args)
        verbose = args.verbose or getattr(args, "verbose_sub", False)
        import logging

        logging.basicConfig(
            level=logging.DEBUG if verbose else logging.INFO,
            format="%(message)s",
            stream=sys.stderr,
        )
        from redistro.config import load_config

        cfg = load_config(config, overrides)
        return _dispatch(args, cfg)
    except ConfigError as exc:
        print(one_line(f"redistro: error: {exc}"), file=sys.stderr)
        return 2
    except RedistroError as exc:
        print(one_line(f"redistro: {exc}"), file=sys.stderr)
        return 1


def one_line(text: str, limit: int = 400) -> str:
    """A message as one printable line: control characters (line breaks among
    them, which include \x1c-\x1e and \x85 for str.splitlines) escaped, cut
    to ``limit`` characters in all (its prefix included)."""
    if not text.isprintable():
        text = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)
    return text if len(text) <= limit else text[: limit - 3] + "..."


RUN_FILES = ("messages.log", "summary.json", "session.mcap", "plant.json")


def _check_outputs(args: argparse.Namespace) -> None:
    """Every output named on the command line is writable, before anything runs."""
    import math

    from redistro.files import check_out_dir, check_out_file

    for attr, option in (("out", "--out"), ("csv", "--csv")):
        value = getattr(args, attr, None)
        if value:
            check_out_dir(value, option)
    run = getattr(args, "out", None) if args.command in ("session", "node") else None
    if run:  # a run folder is new: another run's files would be mixed in (or refused midway)
        from pathlib import Path

        from redistro.errors import clipped

        held = [n for n in RUN_FILES if os.path.lexists(Path(run) / n)]
        if held:
            raise ConfigError(
                f"--out {clipped(run)}: holds a run already ({held[0]}): give a new or empty folder"
            )
    for attr, option in (("json_path", "--json"), ("json_out", "--json"), ("plot", "--plot")):
        value = getattr(args, attr, None)
        if isinstance(value, str) and value:
            check_out_file(value, option)
    interval = getattr(args, "interval", None)
    if interval is not None and not (math.isfinite(interval) and 0.05 <= interval <= 3600):
        raise ConfigError(f"--interval: expected a number of seconds in 0.05..3600, got {interval}")


def _dispatch(args: argparse.Namespace, cfg: Any) -> int:
    _check_outputs(args)
    if args.command == "clean":
        return _clean()
    if args.command == "check":
        from redistro.session.preflight import preflight

        task = preflight(cfg, args.task)
        segments = f"{len(task.segments)} segments"
        print(f"ok: {task.task} ({task.kind}, {segments}) on {', '.join(task.robots)}")
        return 0
    if args.command == "session":
        from redistro.session.run import run_session

        return run_session(cfg, args.task, out_dir=args.out)
    if args.command == "view":
        from redistro.view import run_view

        return run_view(args.run, args.port, args.bind, args.live)
    if args.command == "ctl":
        from redistro.ctl import run_ctl

        return run_ctl(
            args.session, args.order, args.robot, args.mm, args.deg, args.key, args.timeout
        )
    if args.command == "replay":
        from redistro.session.replay import run_replay

        return run_replay(args.run, _config_args(args)[1], cfg.session.runs_dir, args.json_path)
    if args.command == "node":
        from redistro.session.node import run_node

        return run_node(
            cfg,
            args.node_kind,
            args.task,
            robot=getattr(args, "robot", ""),
            plant_session=getattr(args, "plant", ""),
            link=args.link,
            out_dir=args.out,
        )
    if args.command == "faults":
        from redistro.faults.cli import run_faults

        config, overrides = _config_args(args)
        cfg_args = (["--config", config] if config else []) + [
            a for o in overrides for a in ("--set", o)
        ]
        if args.retries < 0:
            raise ConfigError(f"--retries: expected >= 0, got {args.retries}")
        return run_faults(
            cfg, args.only, args.json_path, args.seed, cfg_args, args.list, args.retries
        )
    if args.command == "bench":
        from redistro.bench.commands import run_bench

        return run_bench(args, cfg, _config_args(args)[1])
    if args.command == "plant":
        return _plant(args, cfg)
    if args.command == "log":
        return _log(args, cfg)
    if args.command == "top":
        from redistro.top import run_top

        if args.zenoh:
            from redistro.top import run_zenoh_top

            return run_zenoh_top(args.zenoh, cfg, args.json, args.interval)
        return run_top(args.session, args.once, args.json, args.interval)
    if args.command == "bridge":
        from redistro.ros2bridge import run_bridge

        return run_bridge(args.session, args.listen or None)
    raise ConfigError(f"unknown command {args.command}")


def _log(args: argparse.Namespace, cfg: Any) -> int:
    from pathlib import Path

    from redistro.files import check_out_dir
    from redistro.log import inspect

    if args.log_command == "plot" and not args.out:
        # the default folder, inside the run: tested as --out is, before any work
        run_dir, _ = inspect.resolve_run(args.run, cfg.session.runs_dir)
        check_out_dir(str(run_dir / "plots"), "--out")
    if args.log_command == "diff":
        return _log_diff(args, cfg.session.runs_dir)
    run, sl, summary = inspect.load(args.run, cfg.session.runs_dir)
    if args.log_command == "summary":
        rows = inspect.summary_rows(run, sl, summary)
        if args.json:
            print(json.dumps(rows, indent=1, default=str))
        else:
            inspect.print_summary(rows)
        return 0
    if args.log_command == "plot":
        out = Path(args.out) if args.out else run / "plots"
        try:
            written = inspect.plot_run(sl, out)
        except ConfigError:
            raise
        except (KeyError, ValueError, IndexError) as exc:  # a log whose channels do not fit
            raise ConfigError(f"{args.run}: cannot be plotted ({exc!r:.120})") from None
        for path in written:
            print(f"wrote {path}")
        return 0
    for path in inspect.export_csv(sl, Path(args.csv)):
        print(f"wrote {path}")
    return 0


def _log_diff(args: argparse.Namespace, runs_dir: str) -> int:
    from pathlib import Path

    from redistro import files
    from redistro.log import diff, inspect

    _, a = inspect.resolve_run(args.run, runs_dir)
    _, b = inspect.resolve_run(args.other, runs_dir)
    try:
        report = diff.compare_logs(a, b)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    print(diff.report_line(report, "a", "b"))
    if args.json_path:
        doc = {"a": str(a), "b": str(b), **report}
        files.replace(Path(args.json_path), json.dumps(doc, indent=1) + "\n")
    return 0 if report["identical"] else 1


def _clean() -> int:
    from redistro.ipc import session

    removed = session.reap()
    for name in removed:
        print(f"removed {name}")
    live = session.live_sessions()
    if not removed:
        print("nothing to remove")
    if live:
        print(f"kept {len(live)} live session(s): {', '.join(live)}")
    return 0


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected 1 or more, got {value}")
    return value


def _config_args(args: argparse.Namespace) -> tuple[str | None, list[str]]:
    config = getattr(args, "config_sub", None) or args.config
    clock = [f"session.clock={args.clock}"] if getattr(args, "clock", None) else []
    return config, [*args.set, *getattr(args, "set_sub", []), *clock]


def _plant(args: argparse.Namespace, cfg: Any) -> int:
    import signal
    import time
    from pathlib import Path

    from redistro.config.hardware import load_hardware
    from redistro.ipc import session, signals
    from redistro.plant.launch import PlantProcess
    from redistro.session.run import plant_config

    if args.seconds < 0:
        raise ConfigError(f"--seconds: expected >= 0, got {args.seconds}")
    hardware = load_hardware(cfg)
    for name in session.reap():
        print(f"reaped {name} (left by a dead session)", file=sys.stderr)
    with session.Session.create() as s:
        print(f"session {s.id}", flush=True)
        run_dir = Path(cfg.session.runs_dir) / s.id
        plant = PlantProcess.start(s, run_dir, plant_config(cfg), gui=args.gui, hardware=hardware)
        try:
            end = time.monotonic() + args.seconds if args.seconds else None
            while plant.proc.poll() is None and (end is None or time.monotonic() < end):
                info = signals.wait(
                    frozenset({signal.SIGINT, signal.SIGTERM}),
                    1.0 if end is None else max(0.0, min(1.0, end - time.monotonic())),
                )
                st = plant.status()
                print(
                    f"t={st['sim_time_ns'] / 1e9:8.2f} s  rtf {st['rtf']:.3f}  "
                    f"late {st['late_steps']}"
                )
                if info is not None:
                    break
        finally:
            plant.stop()
        print(json.dumps(plant.result()))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""``redistro bench ...``: each benchmark's command, behind the CLI's parser.

The parser and the one-line refusals live in :mod:`redistro.cli`; these
handlers get the parsed arguments and the loaded config, check what is
theirs to check (a refusal is a :class:`ConfigError`, before anything
starts), run the benchmark and print or write its figures.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import Any

from redistro.errors import ConfigError


def run_bench(args: argparse.Namespace, cfg: Any, overrides: list[str]) -> int:
    """overrides: the command line's ``--set`` items, recorded with the figures."""
    if args.bench == "cycle":
        return _bench_cycle(args, cfg)
    if args.bench == "ipc":
        return _bench_ipc(args)
    if args.bench == "plant":
        return _bench_plant(args, cfg)
    if args.bench == "group":
        return _bench_group(args, cfg, overrides)
    if args.bench == "peg":
        return _bench_peg(args, cfg, overrides)
    if args.bench == "dual":
        return _bench_dual(args, cfg)
    if args.bench == "kernels":
        return _bench_kernels(args, cfg)
    if args.bench == "ddm":
        return _bench_ddm(args, cfg)
    if args.bench == "clearance":
        return _bench_clearance(args, cfg)
    raise ConfigError(f"bench {args.bench}: no such benchmark")


def _bench_cycle(args: argparse.Namespace, cfg: Any) -> int:
    import time
    from pathlib import Path

    from redistro.bench import cycle
    from redistro.bench.baseline import cpu_steal_ticks, cyclictest, steal_report
    from redistro.ipc import session
    from redistro.process.session_owner import write_json

    rate = args.rate if args.rate is not None else cfg.bench.rate_hz
    cycle.check_args(rate, args.workers, args.seconds, args.work_us)
    stages = cycle.parse_stages(args.stages, args.workers)
    if args.message_every < 0:
        raise ConfigError("--message-every: expected >= 0")
    for name in session.reap():
        print(f"reaped {name} (left by a dead session)", file=sys.stderr)

    baseline = None
    if not args.no_baseline:
        baseline = cyclictest(rate, args.seconds, cfg.scheduling.priorities.get("manager", 20))

    def once(stage_list: list[int], label: str) -> dict[str, Any]:
        steal0, t0 = cpu_steal_ticks(), time.monotonic()
        result, run_dir = cycle.run_once(
            cfg,
            rate_hz=rate,
            workers=args.workers,
            seconds=args.seconds,
            work_us=args.work_us,
            stages=stage_list,
            pin=args.pin,
            message_every=args.message_every,
        )
        s = cycle.summarize(result, args.workers, args.work_us, run_dir)
        s["host_steal"] = steal_report(steal0, cpu_steal_ticks(), time.monotonic() - t0)
        if baseline is not None:
            s["baseline_lateness_us"] = baseline
        cycle.print_summary(label, s)
        return s

    if args.compare_stages:
        serial = once(list(range(args.workers)), "serial")
        parallel = once([0] * args.workers, "parallel")
        p50s, p50p = serial["makespan_us"].get("p50"), parallel["makespan_us"].get("p50")
        out: dict[str, Any] = {
            "serial": serial,
            "parallel": parallel,
            "makespan_speedup_p50": round(p50s / p50p, 2) if p50s and p50p else None,
        }
        ok = serial["result"] == "ok" and parallel["result"] == "ok"
    else:
        out = once(stages, "bench cycle")
        ok = out["result"] == "ok"
    if args.json_path:
        write_json(Path(args.json_path), out)
        print(f"wrote {args.json_path}")
    return 0 if ok else 1


def _bench_group(args: argparse.Namespace, cfg: Any, overrides: list[str]) -> int:
    from pathlib import Path

    from redistro.bench import group
    from redistro.process.session_owner import write_json

    _writable("--json", args.json_path)
    out = group.run(cfg, args.task, overrides)
    group.print_figures(out)
    if args.json_path:
        write_json(Path(args.json_path), out)
        print(f"wrote {args.json_path}")
    return 0 if out["result"] == "ok" else 1


def _writable(flag: str, path: str | None) -> None:
    from redistro.files import check_out_file

    if path:
        check_out_file(path, flag)


def _check_campaign(args: argparse.Namespace, max_radius_mm: float) -> None:
    """A campaign's options (bench peg, bench dual), before anything runs."""
    _writable("--json", args.json_path)
    _writable("--plot", args.plot)
    r = args.offset_radius_mm
    if not 0 <= r <= max_radius_mm:
        raise ConfigError(f"--offset-radius-mm: expected 0 to {max_radius_mm:g}, got {r:g}")
    if not 0 <= args.yaw_deg <= 10:
        raise ConfigError(f"--yaw-deg: expected 0 to 10, got {args.yaw_deg:g}")
    if not 0 <= args.seed <= 2**32 - 1 - args.trials:
        raise ConfigError(f"--seed: expected 0 to {2**32 - 1 - args.trials}, got {args.seed}")


def _write_campaign(
    args: argparse.Namespace,
    out: dict[str, Any],
    show: Callable[[dict[str, Any]], None],
    plot: Callable[[dict[str, Any], str], None],
) -> None:
    """A campaign's table, its JSON (--json) and its plot (--plot)."""
    from pathlib import Path

    from redistro.process.session_owner import write_json

    show(out)
    if args.json_path:
        write_json(Path(args.json_path), out)
        print(f"wrote {args.json_path}")
    if args.plot:
        plot(out, args.plot)
        print(f"wrote {args.plot}")


def _bench_peg(args: argparse.Namespace, cfg: Any, overrides: list[str]) -> int:

    from rich.progress import Progress

    from redistro.bench import peg
    from redistro.session.preflight import preflight

    _check_campaign(args, max_radius_mm=20)
    radius = args.offset_radius_mm / 1e3
    if not 0 <= args.offset_min_mm <= args.offset_radius_mm:
        raise ConfigError(
            f"--offset-min-mm: expected 0 to --offset-radius-mm, got {args.offset_min_mm:g}"
        )
    cfg = peg.trial_config(cfg, radius, args.yaw_deg, args.seed, args.offset_min_mm / 1e3)
    task = preflight(cfg, args.task)
    if task.kind != "strategy":
        raise ConfigError(f"{args.task}: bench peg needs a strategy task, not {task.kind}")
    with Progress(transient=False) as bar:
        job = bar.add_task(f"bench peg ({cfg.ddm.transport})", total=args.trials)

        def done(row: dict[str, Any]) -> None:
            bar.advance(job)
            mark = "inserted" if row["inserted"] else f"not inserted: {row['reason'] or ''}"
            bar.console.print(
                f"trial {row['trial']}: offset {row['offset_mm']} mm, yaw {row['yaw_deg']} deg, "
                f"{row['result']}, {mark}"
            )

        out = peg.run(
            cfg,
            args.task,
            trials=args.trials,
            radius_m=radius,
            yaw_deg=args.yaw_deg,
            seed=args.seed,
            min_radius_m=args.offset_min_mm / 1e3,
            overrides=overrides,
            on_trial=done,
        )
    _write_campaign(args, out, peg.print_campaign, peg.plot_campaign)
    return 0 if out["summary"]["inserted"] == out["summary"]["trials"] else 1


def _bench_dual(args: argparse.Namespace, cfg: Any) -> int:

    from rich.progress import Progress

    from redistro.bench import dual
    from redistro.config.task import load_task
    from redistro.session.preflight import preflight

    _check_campaign(args, max_radius_mm=10)
    task_file = args.task_file or dual.TASK_FILES[args.task]
    dual.target_object(load_task(task_file, cfg), args.task)
    task = preflight(cfg, task_file)
    with Progress(transient=False) as bar:
        job = bar.add_task(f"bench dual ({cfg.ddm.transport})", total=args.trials)

        def done(row: dict[str, Any]) -> None:
            bar.advance(job)
            err, verdict = row["object_pose_error_m"], dual.VERDICT[args.task]
            bar.console.print(
                f"trial {row['trial']}: offset {row['offset_xy_mm']} mm, yaw {row['yaw_deg']} "
                f"deg, {row['result']}, {verdict if row[verdict] else 'not ' + verdict}"
                + (f" ({err * 1e3:.2f} mm off)" if err is not None else "")
            )

        out = dual.run(
            cfg,
            task,
            job=args.task,
            trials=args.trials,
            radius_m=args.offset_radius_mm / 1e3,
            yaw_deg=args.yaw_deg,
            seed=args.seed,
            on_trial=done,
        )
    _write_campaign(args, out, dual.print_campaign, dual.plot_campaign)
    return 0 if out["summary"][out["verdict"]] == out["summary"]["trials"] else 1


def _bench_kernels(args: argparse.Namespace, cfg: Any) -> int:
    from pathlib import Path

    from redistro.bench import kernels
    from redistro.process.session_owner import write_json

    if args.calls < 1:
        raise ConfigError(f"--calls {args.calls}: must be at least 1")
    _writable("--json", args.json_path)
    out = kernels.run(cfg, args.calls)
    kernels.print_figures(out)
    if args.json_path:
        write_json(Path(args.json_path), out)
        print(f"wrote {args.json_path}")
    return 0


def _bench_clearance(args: argparse.Namespace, cfg: Any) -> int:
    from pathlib import Path

    from redistro.bench import clearance
    from redistro.process.session_owner import write_json

    rate = args.rate if args.rate is not None else cfg.ssc.rate_hz
    if not 1 <= rate <= 10_000:
        raise ConfigError(f"--rate {rate:g}: expected 1-10000 Hz")
    if not 0 < args.seconds <= 600:
        raise ConfigError(f"--seconds {args.seconds:g}: expected more than 0, at most 600")
    if not {"r1", "r2"} <= set(cfg.robots):
        raise ConfigError(f"{cfg.source}: bench clearance needs robots r1 and r2")
    _writable("--json", args.json_path)
    out = clearance.run(cfg, rate, args.seconds)
    clearance.print_figures(out)
    if args.json_path:
        write_json(Path(args.json_path), out)
        print(f"wrote {args.json_path}")
    return 0


def _bench_ipc(args: argparse.Namespace) -> int:
    from pathlib import Path

    from redistro.bench import ipc
    from redistro.process.session_owner import write_json

    if args.samples < 10:
        raise ConfigError(f"--samples: expected >= 10, got {args.samples}")
    if not args.gap_us >= 0:
        raise ConfigError(f"--gap-us: expected >= 0, got {args.gap_us}")
    if args.robots not in (1, 2):
        raise ConfigError(f"--robots: expected 1 or 2, got {args.robots}")
    out = ipc.run(args.samples, args.gap_us, args.robots)
    print(f"record: {out['record']}, {out['record_bytes']} bytes, {out['blocks']} block(s)")
    for key in ("localdata", "pipe", "queue"):
        r = out[key]
        print(f"{key:10s} median {r['median_us']:8.2f} us  p99 {r['p99_us']:8.2f} us")
    print(
        f"Local Data snapshot is {out['speedup_median']['vs_queue']}x faster than "
        f"multiprocessing.Queue (median)"
    )
    if args.json_path:
        write_json(Path(args.json_path), out)
        print(f"wrote {args.json_path}")
    return 0


def _bench_plant(args: argparse.Namespace, cfg: Any) -> int:
    import dataclasses
    from pathlib import Path

    from redistro.bench import plant
    from redistro.config.hardware import load_hardware
    from redistro.ipc import session
    from redistro.process.session_owner import write_json

    if not args.seconds > 0:
        raise ConfigError(f"--seconds: expected > 0, got {args.seconds}")
    if not 0 < args.rate <= 10000:
        raise ConfigError(f"--rate: expected a number in (0, 10000] Hz, got {args.rate}")
    if args.backplane:
        cfg = dataclasses.replace(
            cfg, plant=dataclasses.replace(cfg.plant, backplane=args.backplane)
        )
    load_hardware(cfg)  # bad hardware files fail here, before any process starts
    for name in session.reap():
        print(f"reaped {name} (left by a dead session)", file=sys.stderr)
    out = plant.run(cfg, args.seconds, args.rate)
    plant.print_summary(out)
    if args.json_path:
        write_json(Path(args.json_path), out)
        print(f"wrote {args.json_path}")
    return 0


def _bench_ddm(args: argparse.Namespace, cfg: Any) -> int:
    from pathlib import Path

    from redistro.bench import ddm
    from redistro.process.session_owner import write_json

    if not 1 <= args.robots <= 16:
        raise ConfigError(f"--robots {args.robots}: expected 1 to 16")
    if not 1 <= args.rate <= 5000:
        raise ConfigError(f"--rate {args.rate:g}: expected 1 to 5000 Hz")
    if not 1 <= args.seconds <= 3600:
        raise ConfigError(f"--seconds {args.seconds:g}: expected 1 to 3600")
    _writable("--json", args.json_path)
    out = ddm.run(cfg, args.transport, args.robots, args.rate, args.seconds)
    if args.floor:
        # what the host alone gives a ddm's exchange now: bare receives and
        # replies on TCP loopback, one per robot sent to in turn, at the same
        # rate and priority (redistro.bench.floor); over zenoh, also what
        # zenoh-python alone gives the same command/reply (.zenoh_floor)
        from redistro.bench import floor

        floors = {"socket_floor": ("redistro.bench.floor", 30.0)}
        if args.transport == "zenoh":  # (its sessions take a few seconds to meet)
            floors["zenoh_floor"] = ("redistro.bench.zenoh_floor", 60.0)
        for key, (module, start_s) in floors.items():
            out[key] = floor.measure(
                args.rate,
                3.0,
                cfg.scheduling.priorities.get("ddm", 19),
                cfg.scheduling.cpu_latency_us,
                robots=args.robots,
                module=module,
                start_s=start_s,
            )
    ddm.print_figures(out)
    if args.json_path:
        write_json(Path(args.json_path), out)
        print(f"wrote {args.json_path}")
    return 0 if out["connected"] and not out["error"] else 1

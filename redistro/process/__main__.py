"""Process entry point: ``python -m redistro.process {manager|worker|plant|logwriter|bridge} ...``.

The runtime signals are blocked and the math libraries limited to one thread
*before* anything that may start a thread (numpy/OpenBLAS, pybullet,
pinocchio) is imported: a process-directed signal landing on such a thread
would kill the process.
"""

import gc
import os
import sys

from redistro.ipc.signals import block_runtime_signals

block_runtime_signals()
# no collector passes while the modules load (a tenth of numpy's import):
# a manager and a worker collect once, freeze and stay so before their
# Routine, the plant before its loop; the others turn it back on once
# their imports are done
gc.disable()
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


def main(argv: list[str] | None = None) -> int:
    import argparse
    import logging

    parser = argparse.ArgumentParser(prog="python -m redistro.process")
    sub = parser.add_subparsers(dest="what", required=True)
    m = sub.add_parser("manager")
    m.add_argument("--spec", required=True)
    w = sub.add_parser("worker")
    w.add_argument("--spec", required=True)
    w.add_argument("--index", type=int, required=True)
    w.add_argument("--manager-pid", type=int, required=True)
    w.add_argument("--wake-fd", type=int, default=-1)
    p = sub.add_parser("plant")
    p.add_argument("--session", required=True)
    p.add_argument("--resolved", required=True, help="the config, resolved (JSON)")
    p.add_argument("--result")
    p.add_argument("--gui", action="store_true")
    p.add_argument("--seconds", type=float, default=0.0)
    lw = sub.add_parser("logwriter")
    lw.add_argument("--fd", type=int, required=True)
    lw.add_argument("--out", required=True)
    lw.add_argument("--ready-fd", type=int, default=-1)
    b = sub.add_parser("bridge")
    b.add_argument("--session", required=True)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=os.environ.get("REDISTRO_LOG_LEVEL", "INFO"),
        format="%(message)s",
        stream=sys.stderr,
    )
    if args.what == "logwriter":
        from redistro.log.writer import run_writer

        gc.enable()
        return run_writer(args.fd, args.out, args.ready_fd)
    if args.what == "bridge":
        from redistro.errors import RedistroError
        from redistro.ros2bridge import run_bridge

        gc.enable()
        try:
            return run_bridge(args.session)
        except RedistroError as exc:  # (beside a session: one line, the session goes on)
            print(f"redistro bridge: {exc}", file=sys.stderr)
            return 2
    if args.what == "plant":
        from redistro.plant.process import run_plant  # (its loop sees to the collector)

        return run_plant(
            args.session,
            args.resolved,
            result_path=args.result,
            gui=args.gui,
            seconds=args.seconds,
        )
    if args.what == "manager":
        from redistro.process.manager import run_manager

        return run_manager(args.spec)
    from redistro.process.worker import run_worker

    return run_worker(args.spec, args.index, args.manager_pid, args.wake_fd)


if __name__ == "__main__":
    sys.exit(main())

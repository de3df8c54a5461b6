"""``redistro ctl SESSION pause|resume|stop|estop|jog``: the operator's hand.

Everything is checked before anything is sent: the session runs and has an
SSC, the robot is one of its group, a jog's step is within 5 mm and 2
degrees. The command goes to the SSC manager signed with the session's key
(``ssc/ctl.py``); what it answers is printed: exit 0 when it was done, 1 when
the controller refused it (not paused, a joint limit, too close), 2 for bad
input.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from redistro.errors import ConfigError, clipped
from redistro.ssc.ctl import JOG_MAX_M, JOG_MAX_RAD, Client, Command, Order, session_dir

ORDERS = ("pause", "resume", "stop", "estop", "jog")


def order_of(command: str, robot: str | None, mm: list[float], deg: list[float]) -> Order:
    """The command as signed, from the command line, its robot's index still
    0 (ConfigError: one line)."""
    cmd = Command[command.upper()]
    if cmd != Command.JOG:
        if robot is not None:
            raise ConfigError(f"ctl {command}: takes no robot (got {clipped(robot)})")
        return Order(cmd)
    if robot is None:
        raise ConfigError("ctl jog: name the robot whose tool moves")
    if not all(math.isfinite(v) for v in (*mm, *deg)):
        raise ConfigError("ctl jog: --mm and --deg take finite numbers")
    step = [v / 1000.0 for v in mm] + [math.radians(v) for v in deg]
    moved, turned = math.hypot(*step[:3]), math.hypot(*step[3:])
    if moved > JOG_MAX_M + 1e-12:
        raise ConfigError(f"ctl jog: --mm moves {moved * 1e3:.3g} mm; at most {JOG_MAX_M * 1e3:g}")
    if turned > JOG_MAX_RAD + 1e-12:
        raise ConfigError(f"ctl jog: --deg turns {math.degrees(turned):.3g}°; at most 2")
    if moved == 0.0 and turned == 0.0:
        raise ConfigError("ctl jog: give a step (--mm X Y Z and/or --deg RX RY RZ)")
    s0, s1, s2, s3, s4, s5 = step
    return Order(cmd, 0, (s0, s1, s2, s3, s4, s5))


def group_robots(directory: Path, session: str) -> list[str]:
    """The robots of the session's SSC, in its order (ConfigError: none)."""
    from redistro.ros2bridge import node_specs

    specs = node_specs(directory, 10.0, "ctl")
    ssc = specs.get("ssc")
    if ssc is None:
        raise ConfigError(f"ctl: session {session} has no SSC to command")
    return list(ssc.robots)


def run_ctl(
    session: str,
    command: str,
    robot: str | None,
    mm: list[float],
    deg: list[float],
    key_file: str | None,
    timeout_s: float,
) -> int:
    if not (math.isfinite(timeout_s) and 0.1 <= timeout_s <= 600):
        raise ConfigError(f"ctl: --timeout: expected 0.1..600 s, got {timeout_s}")
    order = order_of(command, robot, mm, deg)
    sid, directory = session_dir(session)
    robots = group_robots(directory, sid)
    if robot is not None:
        if robot not in robots:
            group = ", ".join(robots)
            raise ConfigError(f"ctl jog: no robot {clipped(robot)} in the group ({group})")
        order = Order(order.command, robots.index(robot), order.step)
    key = None
    if key_file is not None:
        from redistro.ddm import record as wire

        try:
            key = wire.load_key(key_file)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"ctl: --key {clipped(key_file)}: {exc}") from None
    reply = Client(sid, directory, key).send(order, timeout_s)
    text = str(reply.get("text", ""))
    if reply.get("ok"):
        print(text, flush=True)
        return 0
    print(f"redistro: ctl {command}: {text}", file=sys.stderr, flush=True)
    return 1

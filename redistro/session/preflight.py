"""Pre-flight: every check of a session's input before anything is reaped,
created or started (``redistro check TASK`` runs these alone): the task
against the config, the joint positions, the motions against the limits,
the DDM key."""

from __future__ import annotations

from pathlib import Path

from redistro.config.hardware import load_hardware
from redistro.config.model import Config
from redistro.config.task import Task, load_task
from redistro.drivers import positions
from redistro.errors import ConfigError


def positions_file(cfg: Config, robot: str) -> Path:
    return Path(cfg.session.runs_dir) / cfg.session.positions_dir / f"{robot}.json"


def unknown_positions(cfg: Config, task: Task) -> dict[str, str]:
    """Robots of the task whose joint positions are not known, and why."""
    out: dict[str, str] = {}
    for r in task.robots:
        try:
            positions.read(positions_file(cfg, r), [r])
        except positions.PositionsUnknown as exc:
            out[r] = str(exc)
    return out


def check_positions(cfg: Config, task: Task) -> None:
    """Motion needs known joint positions, unless the task is the self-calibration
    (or a strategy task that runs one first when they are unknown)."""
    if task.kind == "self_calibration":
        return
    if task.kind == "strategy" and task.calibrate_if_needed:
        return
    for why in unknown_positions(cfg, task).values():
        raise ConfigError(f"motion refused: {why}; run tasks/self_calibration.yaml first")


def check_motion(cfg: Config, task: Task) -> None:
    """Every recorded position inside the joint limits, or past them no
    further than a joint can be pushed (``RECOVERY_BAND_RAD``: beyond, the
    file cannot be right), every joint goal inside them less the margin,
    every joint move within the speed limit, after a Cartesian segment too,
    every goal wrench within the guard's limits (redistro/config/limits.py),
    and the arms kept apart all along (redistro/ssc/clearance.py)."""
    from redistro.config.limits import RECOVERY_BAND_RAD, joint_limits, task_motion_problems
    from redistro.ssc.reach import goal_postures

    limits = joint_limits(cfg)
    start: dict[str, list[float]] = {}
    for r in task.robots:
        path = positions_file(cfg, r)
        try:
            q = positions.read(path, [r]).q_rad[r]
        except positions.PositionsUnknown:
            continue
        problem = limits.outside(q, margin=False, slack=RECOVERY_BAND_RAD)
        if problem:
            raise ConfigError(
                f"{path}: q_rad.{r}: {problem}; the file cannot be right "
                "(run tasks/self_calibration.yaml)"
            )
        start[r] = q
    for problem in task_motion_problems(cfg, task, start, goal_postures(cfg, task, start)):
        raise ConfigError(problem)
    from redistro.ssc.clearance import clearance_problems

    for problem in clearance_problems(cfg, task, start):
        raise ConfigError(problem)


def check_runs_dir(cfg: Config) -> None:
    """``session.runs_dir``: a safe folder that exists or can be made (not on
    a pseudo-filesystem, nobody else may write there: :mod:`redistro.files`)."""
    from redistro.files import check_out_dir

    check_out_dir(cfg.session.runs_dir, f"{cfg.origin('session.runs_dir')}: session.runs_dir")


def check_workcell(cfg: Config) -> None:
    """The plant can build the work-cell (the hole where its truth puts it, on
    a table clear of the robots' bases)."""
    from redistro.plant.truth import placement_problem

    problem = placement_problem(cfg)
    if problem:
        raise ConfigError(f"{cfg.source}: {problem}")


def check_key(cfg: Config, needed: bool = False) -> None:
    """``ddm.key_file`` readable and private (needed: nodes started alone
    share no session folder, so they need it)."""
    from redistro.ddm import record as wire

    if not cfg.ddm.key_file:
        if needed:
            raise ConfigError(
                f"{cfg.origin('ddm.key_file')}: ddm.key_file: nodes started alone need a "
                "shared key file (32 random bytes as hex, mode 0600, the same on every node; "
                "e.g. python3 -c 'import os; print(os.urandom(32).hex())' > link.key)"
            )
        return
    try:
        wire.load_key(cfg.ddm.key_file)
    except ValueError as exc:
        raise ConfigError(f"{cfg.origin('ddm.key_file')}: ddm.key_file: {exc}") from None


def check_zenoh_tls(cfg: Config, needed: bool = False) -> None:
    """Over zenoh with ``tls/`` endpoints (or ``ddm.zenoh.tls.cert_file``
    set; ``needed``: a viewer's ``tls/`` endpoint): the CA, the node's
    certificate and its key readable, PEM, the key private (mode 0600)."""
    from redistro.config.inputs import read_text
    from redistro.ddm import record as wire

    z = cfg.ddm.zenoh
    endpoints = (*z.listen, *z.connect)
    used = needed or (
        cfg.ddm.transport == "zenoh"
        and (bool(z.tls.cert_file) or any(e.startswith("tls/") for e in endpoints))
    )
    if not used:
        return
    for field, path, marker in (
        ("ca_file", z.tls.ca_file, "CERTIFICATE"),
        ("cert_file", z.tls.cert_file, "CERTIFICATE"),
        ("key_file", z.tls.key_file, "PRIVATE KEY"),
    ):
        where = f"{cfg.origin('ddm.zenoh.tls.' + field)}: ddm.zenoh.tls.{field}"
        if not path:
            raise ConfigError(f"{where}: a tls/ endpoint needs it (a PEM file)")
        try:
            text = (
                wire.read_private(path, "key", 1 << 16)
                if field == "key_file"
                else read_text(path, "certificate", 1 << 16)
            )
        except (ValueError, ConfigError) as exc:
            raise ConfigError(f"{where}: {exc}") from None
        if "-----BEGIN " not in text or marker not in text:
            raise ConfigError(f"{where}: {path} holds no PEM {marker.lower()}")


def check_zenoh_users(cfg: Config, nodes: list[str], link: str | None) -> None:
    """Over zenoh: ``ddm.zenoh.users_file`` readable and private. Nodes
    started alone (``link`` given) share no session folder: they need the
    file, with a password for each of ``nodes`` (``<node>@<group>``)."""
    if cfg.ddm.transport != "zenoh":
        return
    from redistro.ddm import zenoh_transport as zt

    where = f"{cfg.origin('ddm.zenoh.users_file')}: ddm.zenoh.users_file"
    if not cfg.ddm.zenoh.users_file:
        if link is not None:
            example = zt.user_of(nodes[0], zt.group_of(cfg, link))
            raise ConfigError(
                f"{where}: nodes started alone over zenoh need a users file "
                "(name:password lines, mode 0600, the same on every host; "
                f"the users are <node>@<group>, e.g. {example})"
            )
        return
    try:
        users = zt.read_users(cfg.ddm.zenoh.users_file)
    except ValueError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    if link is None:
        return  # a session's group is its id: its users are checked as it starts
    group = zt.group_of(cfg, link)
    missing = [zt.user_of(n, group) for n in nodes if zt.user_of(n, group) not in users]
    if missing:
        raise ConfigError(f"{where}: no password for {', '.join(missing)}")


def check_clock(cfg: Config) -> None:
    """A lockstep session ticks every node on the same plant step: one rate
    for all, a whole number of physics steps per tick."""
    if cfg.session.clock != "lockstep":
        return
    if cfg.esc.rate_hz != cfg.ssc.rate_hz:
        raise ConfigError(
            f"session.clock lockstep: esc.rate_hz ({cfg.esc.rate_hz:g}) and ssc.rate_hz "
            f"({cfg.ssc.rate_hz:g}) must be equal"
        )
    steps = cfg.plant.physics_hz / cfg.esc.rate_hz
    if abs(steps - round(steps)) > 1e-9:
        raise ConfigError(
            f"session.clock lockstep: plant.physics_hz ({cfg.plant.physics_hz:g}) must be a "
            f"whole multiple of esc.rate_hz ({cfg.esc.rate_hz:g})"
        )


def preflight(cfg: Config, task_path: str) -> Task:
    """Every check a session makes before it reaps, creates or starts anything:
    the task against the config, the hardware files and their ratings, the
    recorded joint positions, joint goals and speeds against the limits, and
    the Cartesian goals' reach. ConfigError (one line) on the first problem."""
    task = load_task(task_path, cfg)
    load_hardware(cfg)
    check_runs_dir(cfg)
    check_clock(cfg)
    check_workcell(cfg)
    check_key(cfg)
    check_zenoh_users(cfg, ["ssc", *(f"esc.{r}" for r in task.robots)], None)
    check_zenoh_tls(cfg)
    check_positions(cfg, task)
    check_motion(cfg, task)
    from redistro.ssc.reach import unreachable_goals

    for problem in unreachable_goals(cfg, task):
        raise ConfigError(problem)
    return task

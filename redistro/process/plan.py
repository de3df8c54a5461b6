"""What every node's plan shares: its workers' specs from the config."""

from __future__ import annotations

import math
from typing import Any

from redistro.config.model import Config
from redistro.process.spec import WorkerSpec

# the session log's recorders (lowest priority: a starved one drops cycles)
RECORDERS = ("recorder", "logger")


def recorder_heartbeat_limit(cfg: Config, rate_hz: float) -> int:
    """A recorder's heartbeat limit in its node's cycles: ``log.heartbeat_limit_cycles``,
    and never less than ``log.heartbeat_limit_s`` of them (at 1 kHz, 200 cycles
    would be 200 ms, a fifth of what the log ring holds)."""
    return max(cfg.log.heartbeat_limit_cycles, math.ceil(cfg.log.heartbeat_limit_s * rate_hz))


def _off_cycle_rate(cfg: Config, role: str) -> float:
    return cfg.log.drain_hz if role in RECORDERS else cfg.ddm.rate_hz


def worker_specs(
    cfg: Config,
    roles: tuple[tuple[str, int], ...],
    params: dict[str, Any],
    rate_hz: float = 0.0,
) -> list[WorkerSpec]:
    """One WorkerSpec per (role, stage), at the role's configured priority; an
    off-cycle worker (negative stage) runs on its own timer: a recorder at
    ``log.drain_hz``, the ddm at ``ddm.rate_hz`` (0: on data); the recorders
    get the log's heartbeat limit."""
    prio = cfg.scheduling.priorities
    return [
        WorkerSpec(
            name=role,
            role=role,
            stage=stage,
            priority=prio.get(role, 16),
            params=params,
            rate_hz=0.0 if stage >= 0 else _off_cycle_rate(cfg, role),
            heartbeat_limit_cycles=(
                recorder_heartbeat_limit(cfg, rate_hz) if role in RECORDERS else 0
            ),
        )
        for role, stage in roles
    ]

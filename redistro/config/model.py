"""The config model: frozen dataclasses with constraints in field metadata.

Constraints understood by the validator (redistro.config.validate):
``gt``, ``ge``, ``lt``, ``le`` for numbers, ``min_len`` for lists, and
``keys`` (allowed keys) for dicts. Units are in the field names.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

# Paper Table 5.I: relative priorities of the controller processes
# (acquisition 19 > sender 18 = SSC worker > calibration 17 > pid 16 > manager 15).
# One deliberate change: the manager runs *above* its workers (20). It is the
# node's timer and watchdog; below its workers, their wake-ups preempt it while
# it dispatches the cycle and a spinning worker could starve the heartbeat check
# (docs/PERFORMANCE.md measures both orders).
PAPER_PRIORITIES: dict[str, int] = {
    "acquisition": 19,
    "sender": 18,
    "worker": 18,
    "calibration": 17,
    "pid": 16,
    "manager": 20,
    "ddm": 19,
    "logger": 15,
    "busy": 16,
}


@dataclass(frozen=True)
class SessionConfig:
    """Where runs go and how long the session owner waits for its nodes."""

    runs_dir: str = "runs"
    startup_timeout_s: float = field(default=10.0, metadata={"gt": 0, "le": 600})
    shutdown_timeout_s: float = field(default=3.0, metadata={"gt": 0, "le": 60})


@dataclass(frozen=True)
class SchedulingConfig:
    """How processes ask the OS for real-time service.

    policy: ``auto`` tries SCHED_RR and falls back to nice values; ``rr`` and
    ``nice`` ask for that one only (and report a refusal); ``none`` leaves the
    default scheduler alone.
    lock_memory: mlockall in every process. Off by default: a locked process
    takes 10-17 ms (instead of about 2 ms) to die on this machine, which delays
    the manager's detection of a dead worker (docs/PERFORMANCE.md).
    """

    policy: Literal["auto", "rr", "nice", "none"] = "auto"
    priorities: dict[str, int] = field(
        default_factory=lambda: dict(PAPER_PRIORITIES), metadata={"ge": 1, "le": 99}
    )
    lock_memory: bool = False


@dataclass(frozen=True)
class NodeConfig:
    """One node's runtime parameters.

    rate_hz: cycle rate of the node's interval timer [Hz].
    heartbeat_limit_cycles: a worker that has not signed its heartbeat for this
        many consecutive manager cycles is deemed hung (session ends abnormal).
    cpus: CPUs the node's processes may run on (empty: all).
    """

    rate_hz: float = field(default=200.0, metadata={"gt": 0, "le": 10000})
    heartbeat_limit_cycles: int = field(default=25, metadata={"ge": 2, "le": 100000})
    cpus: list[int] = field(default_factory=list, metadata={"ge": 0})


@dataclass(frozen=True)
class Config:
    """The whole config. Sections are added as capabilities land."""

    session: SessionConfig = field(default_factory=SessionConfig)
    scheduling: SchedulingConfig = field(default_factory=SchedulingConfig)
    # 100 cycles at 1 kHz: host stalls of one vCPU up to ~22 ms were measured here.
    bench: NodeConfig = field(
        default_factory=lambda: NodeConfig(rate_hz=1000.0, heartbeat_limit_cycles=100)
    )

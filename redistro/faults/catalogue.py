"""The fault scenarios: what is broken, and what the controller must do about it.

A process scenario breaks one process of a running strategy session
(tasks/fault_drill.yaml: both ESCs, the SSC, the DDMs and the plant) at a
random moment after r2 started moving: SIGKILL (a crash) or SIGSTOP (a hang).
Expected: the session ends with one of ``expect`` results, the first fault's
reason holds ``reason``, detected within ``limit`` (``"death"``: 2 cycles of
the detecting node; ``"heartbeat"``: its heartbeat limit; ``"starving"``: the
starving limit), every robot frozen, nothing left behind.
"""

from __future__ import annotations

from dataclasses import dataclass

# node -> its processes (as named in its Local Data), the ones a scenario breaks
ESC_PROCS = ("manager", "acquisition", "sender", "ddm")
SSC_PROCS = ("manager", "worker", "logger", "ddm")


@dataclass(frozen=True)
class Scenario:
    """name: unique, e.g. ``kill-esc.r2-sender``; node: ``esc.r2``, ``ssc`` or
    ``plant``; proc: the process of that node (``""`` for the plant);
    action: ``kill`` (SIGKILL) or ``stop`` (SIGSTOP); expect: accepted session
    results; reason: a piece of the first fault's reason; limit: ``death``,
    ``heartbeat``, ``starving`` or ``io`` (the I/O timeout)."""

    name: str
    node: str
    proc: str
    action: str
    expect: tuple[str, ...]
    reason: str
    limit: str


def _process_scenarios() -> list[Scenario]:
    out: list[Scenario] = []
    for node, procs in (("esc.r2", ESC_PROCS), ("ssc", SSC_PROCS)):
        for proc in procs:
            if proc == "manager":
                # the owner sees the manager's death; its workers follow it
                # (parent-death signal), the other nodes stop on the fault
                out.append(
                    Scenario(
                        f"kill-{node}-manager",
                        node,
                        proc,
                        "kill",
                        ("abnormal",),
                        f"manager of {node} died",
                        "death",
                    )
                )
                out.append(
                    Scenario(
                        f"stop-{node}-manager",
                        node,
                        proc,
                        "stop",
                        ("abnormal", "starving", "estop"),
                        "",
                        "starving",
                    )
                )
                continue
            out.append(
                Scenario(
                    f"kill-{node}-{proc}",
                    node,
                    proc,
                    "kill",
                    ("abnormal",),
                    f"worker {proc}",
                    "death",
                )
            )
            if node == "ssc" and proc == "ddm":
                # a hung SSC ddm sends nothing: the ESCs starve first
                out.append(
                    Scenario(
                        f"stop-{node}-{proc}",
                        node,
                        proc,
                        "stop",
                        ("starving", "abnormal"),
                        "starving index",
                        "starving",
                    )
                )
            else:
                out.append(
                    Scenario(
                        f"stop-{node}-{proc}",
                        node,
                        proc,
                        "stop",
                        ("abnormal", "starving", "estop"),
                        "",
                        "heartbeat",
                    )
                )
    out.append(Scenario("kill-plant", "plant", "", "kill", ("abnormal",), "", "io"))
    out.append(Scenario("stop-plant", "plant", "", "stop", ("abnormal",), "", "io"))
    return out


CATALOGUE: tuple[Scenario, ...] = tuple(_process_scenarios())


def by_name(name: str) -> Scenario:
    for s in CATALOGUE:
        if s.name == name:
            return s
    raise KeyError(name)

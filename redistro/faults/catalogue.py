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
    any_fault = ("abnormal", "starving", "estop")
    out: list[Scenario] = []
    for node, procs in (("esc.r2", ESC_PROCS), ("ssc", SSC_PROCS)):
        for proc in procs:
            if proc == "manager":
                # a dead or hung manager records nothing: the other nodes see
                # its robot's data go stale (starving), or the owner its death
                for action in ("kill", "stop"):
                    name = f"{action}-{node}-manager"
                    out.append(Scenario(name, node, proc, action, any_fault, "", "starving"))
                continue
            # a dead worker: its manager's pidfd, at once
            out.append(
                Scenario(f"kill-{node}-{proc}", node, proc, "kill", ("abnormal",),
                         f"worker {proc}", "death")
            )  # fmt: skip
            # a hung worker: its heartbeat grows old (a hung ddm also starves
            # the other nodes, later: 40 cycles)
            out.append(
                Scenario(f"stop-{node}-{proc}", node, proc, "stop", any_fault, "missed",
                         "heartbeat")
            )  # fmt: skip
    # the plant: the acquisitions see its boards go silent (the I/O timeout)
    out.append(Scenario("kill-plant", "plant", "", "kill", ("abnormal",), "", "io"))
    out.append(Scenario("stop-plant", "plant", "", "stop", ("abnormal",), "", "io"))
    return out


CATALOGUE: tuple[Scenario, ...] = tuple(_process_scenarios())


def by_name(name: str) -> Scenario:
    for s in CATALOGUE:
        if s.name == name:
            return s
    raise KeyError(name)

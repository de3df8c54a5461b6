"""The fault scenarios: what is broken, and what the controller must do about it.

Kinds:

- ``process``: one process of a running strategy session
  (tasks/fault_drill.yaml: both ESCs, the SSC, the DDMs and the plant) is
  killed (SIGKILL, a crash) or stopped (SIGSTOP, a hang) at a random moment
  after r2 started moving;
- ``inject``: an injection point (:mod:`redistro.faults.inject`) inside the
  same session fires at such a moment: a bad command, a bad sensor, a pushed
  peg, a broken or noisy DDM link (``action`` is the point);
- ``can-noise``: corrupt frames sent onto the CAN backplane's bus by the
  harness while the plant and r2's robot-level driver talk over it (whole
  group sessions over CAN do not fit two vCPUs);
- ``calibration``: a self-calibration with r2's home switches stuck;
- ``start``: what the next start finds: a crashed session's leftovers, a
  missing, corrupt or unclean positions file;
- ``input``: a bad task file, config or command line;
- ``hogs``: the short peg insertion (every segment of the main job)
  beside two processes spinning on both CPUs;
- ``limits``: the drill itself, with config that puts a joint limit in its
  way: nothing is injected, the guard must stop the joint inside the limit;
- ``rerun``: a session's records to r2, recorded, sent again in a later
  session with the same key file (:mod:`redistro.faults.rerun`);
- ``local-user``: another user squatting memory-card keys, or planting
  links in an ``--out`` folder (:mod:`redistro.faults.local_user`).

Expected: the session ends with one of ``expect``, the first fault's reason
holds ``reason``; detection within ``limit`` (``death``: 2 cycles of the
detecting node; ``guard``: 2 cycles, the check before a command; ``heartbeat``:
the heartbeat limit; ``starving``: the starving limit; ``io``: the I/O
timeout; ``""``: no bound, physics decides), every robot frozen, nothing left.
``count``: for a fault the controller must ride out, the counter (in the
summary) that must show it refused the bad data. A scenario whose verdict
is not a time (``Scenario.timed``) may run in lockstep
(``faults --clock lockstep``): its sessions then run paced by the plant,
and what froze after the fault is told by plant step. ``apart``: the plant's
truth (``summary.plant.arms``) must show that the arms never touched.
"""

from __future__ import annotations

from dataclasses import dataclass

# node -> its processes (as named in its Local Data), the ones a scenario breaks
ESC_PROCS = ("manager", "acquisition", "sender", "ddm")
SSC_PROCS = ("manager", "worker", "logger", "ddm")
ANY_FAULT = ("abnormal", "starving", "estop", "unsafe")


@dataclass(frozen=True)
class Scenario:
    """name: unique, e.g. ``kill-esc.r2-sender``; kind: see the module;
    node/proc: where the fault acts (``esc.r2``, ``ssc``, ``plant``); action:
    ``kill``/``stop``, the injection point, or the start/input case; expect:
    accepted session results (``refused``: exit code 2 before any process);
    reason: a piece of the first fault's reason (``a|b``: either); limit: the
    detection bound;
    arg: the injection's argument; sets: config overrides of the session;
    count: the counter that must be above zero."""

    name: str
    kind: str
    node: str
    proc: str
    action: str
    expect: tuple[str, ...]
    reason: str
    limit: str
    arg: float = 0.0
    sets: tuple[str, ...] = ()
    count: str = ""
    what: str = ""  # one line: the fault, for the table
    apart: bool = False  # the plant's truth must show the arms never touched

    @property
    def timed(self) -> bool:
        """Its verdict is a time: a detection within its bound, or a
        session that keeps time under load (the hogs, a flood of records).
        It runs in real time only; ``--clock lockstep`` leaves it out."""
        return bool(self.limit) or self.kind == "hogs" or self.action == "ddm.flood"


def _process_scenarios() -> list[Scenario]:
    out: list[Scenario] = []
    for node, procs in (("esc.r2", ESC_PROCS), ("ssc", SSC_PROCS)):
        for proc in procs:
            if proc == "manager":
                # a dead or hung manager records nothing: the other nodes see
                # its robot's data go stale (starving), or the owner its death
                for action in ("kill", "stop"):
                    out.append(
                        Scenario(f"{action}-{node}-manager", "process", node, proc, action,
                                 ANY_FAULT, "", "starving",
                                 what=f"{'SIGKILL' if action == 'kill' else 'SIGSTOP'} "
                                      f"of the {node} manager")
                    )  # fmt: skip
                continue
            # a dead worker: its manager's pidfd, at once
            out.append(
                Scenario(f"kill-{node}-{proc}", "process", node, proc, "kill", ("abnormal",),
                         f"worker {proc}", "death", what=f"SIGKILL of {node} {proc}")
            )  # fmt: skip
            # a hung worker: its heartbeat grows old (a hung ddm also starves
            # the other nodes, later: 40 cycles)
            out.append(
                Scenario(f"stop-{node}-{proc}", "process", node, proc, "stop", ANY_FAULT,
                         "missed", "heartbeat", what=f"SIGSTOP of {node} {proc}")
            )  # fmt: skip
    # the plant: the acquisitions see its boards go silent (the I/O timeout)
    out.append(Scenario("kill-plant", "process", "plant", "", "kill", ("abnormal",), "", "io",
                        what="SIGKILL of the plant"))  # fmt: skip
    out.append(Scenario("stop-plant", "process", "plant", "", "stop", ("abnormal",), "", "io",
                        what="SIGSTOP of the plant"))  # fmt: skip
    return out


def _inject_scenarios() -> list[Scenario]:
    nan, inf = float("nan"), float("inf")
    u = ("unsafe",)

    def s(
        name: str,
        node: str,
        point: str,
        expect: tuple[str, ...],
        reason: str,
        limit: str,
        what: str,
        arg: float = 0.0,
        sets: tuple[str, ...] = (),
        count: str = "",
    ) -> Scenario:
        proc = "ddm" if point.startswith("ddm.") else ""
        return Scenario(name, "inject", node, proc, point, expect, reason, limit, arg, sets,
                        count, what)  # fmt: skip

    return [
        # limits checked before every command (the sender's guard)
        s("command-nan", "esc.r2", "ddm.command", u, "not finite", "guard",
          "NaN as r2's joint 1 torque command", nan),
        s("command-inf", "esc.r2", "ddm.command", u, "not finite", "guard",
          "+inf as r2's joint 1 torque command", inf),
        s("torque-over-limit", "esc.r2", "ddm.command", u, "commanded torque", "guard",
          "r2's joint 1 commanded 300 N m (limit 200)", 300.0),
        s("velocity-over-limit", "esc.r2", "ddm.command", u, "velocity", "",
          "r2's joint 1 driven by a constant 80 N m (within the torque limit)", 80.0),
        # the push spins the wrist too: the guard may see the speed first
        s("wrist-force-over-limit", "plant", "plant.wrist-push", u, "force|velocity", "",
          "the peg pushed down with 300 N (limit 120 N)", 300.0),
        s("sensor-nan", "plant", "plant.sensor-nan", u, "not finite", "guard",
          "r2's wrist sensor reads NaN (its calibration memory corrupted)"),
        s("encoder-jump", "plant", "plant.encoder-jump", ("abnormal",), "encoder jump", "guard",
          "r2's joint 2 counter glitches by 40 000 counts (0.61 rad)", 40000.0),
        # the DDM links and records
        s("link-close", "esc.r2", "ddm.link-close", ANY_FAULT, "", "starving",
          "r2's DDM socket closed (the link cut)"),
        s("reflective-drop", "esc.r2", "ddm.drop", ANY_FAULT, "", "starving",
          "r2's reflective-memory updates dropped on the network",
          sets=("ddm.transport=reflective",)),
        s("records-delayed", "esc.r2", "ddm.delay", ANY_FAULT, "", "starving",
          "r2's DDM records delayed 0.5 s (past the starving limit)", 0.5),
        s("records-malformed", "ssc", "ddm.malformed", ("ok",), "", "",
          "50 commands with a flipped byte beside the genuine ones", 50.0, count="malformed"),
        s("records-replayed", "ssc", "ddm.replay", ("ok",), "", "",
          "50 commands replayed (sent 100 records earlier) beside the genuine ones", 50.0,
          count="out_of_order"),
        # attacks on the links: the records are signed with the link's key
        s("records-forged", "ssc", "ddm.forged", ("ok",), "", "",
          "50 forged 150 N m commands (checksum right, another key) beside the genuine ones",
          50.0, count="forged"),
        s("records-renamed", "ssc", "ddm.renamed", ("ok",), "", "",
          "50 old commands replayed under another source name beside the genuine ones", 50.0,
          count="forged"),
        s("records-forged-reflective", "ssc", "ddm.forged", ("ok",), "", "",
          "50 forged 150 N m commands on the reflective-memory network", 50.0,
          sets=("ddm.transport=reflective",), count="forged"),
        s("records-flood", "ssc", "ddm.flood", ("ok",), "", "",
          "5 000 forged commands at once on r2's link", 5000.0, count="forged"),
        s("foreign-connection", "ssc", "ddm.foreign", ("ok",), "", "",
          "a second connection to r2's ddm sends 50 forged commands", 50.0, count="foreign"),
        s("records-own-source-reflective", "ssc", "ddm.own-source", ("ok",), "", "",
          "50 forged commands on the reflective-memory network under r2's ESC's own name",
          50.0, sets=("ddm.transport=reflective",), count="forged"),
    ]  # fmt: skip


def _limit_scenarios() -> list[Scenario]:
    """The drill itself heading for a joint limit: nothing injected, the
    guard must stop the joint while it can still stop inside the limit."""
    return [
        # the drill's home move takes r2's joint 4 from about -1.64 up to -1.2
        # rad (peak 0.17 rad/s); its upper limit narrowed to -1.1 (-1.15 with
        # the margin) and a braking deceleration of 0.05 rad/s^2 put its
        # stopping point past the limit halfway, long before the joint is there
        Scenario("joint-limit-approach", "limits", "esc.r2", "", "limits", ("unsafe",),
                 "stopping position", "",
                 sets=("esc.safety.q_max_rad=[2.9, 2.0, 2.9, -1.1, 2.9, 2.0, 3.0]",
                       "esc.safety.decel_rad_s2=[5, 5, 5, 0.05, 5, 5, 5]"),
                 what="r2's joint 4 heading for its limit (narrowed to -1.1 rad) faster "
                      "than it could brake (0.05 rad/s^2)"),
    ]  # fmt: skip


def _other_scenarios() -> list[Scenario]:
    refused = ("refused",)
    out = [
        Scenario("can-corrupt-frames", "can-noise", "plant", "", "noise", ("ok",), "", "",
                 count="bad_frames",
                 what="1 s of corrupt CAN frames (writes and replies) on the backplane bus, "
                      "the plant and r2's driver on it"),
        Scenario("can-forged-writes", "can-noise", "plant", "", "forged", ("ok",), "", "",
                 count="forged_writes",
                 what="1 s of well-formed CAN writes (DAC at full scale, every brake "
                      "released) signed with another key, r2's driver holding the arm"),
        Scenario("can-replay-after-wrap", "can-noise", "plant", "", "replay", ("ok",), "", "",
                 count="forged_writes",
                 what="r2's joint-1 brake-release writes recorded on the CAN bus, sent again "
                      "for 1 s once the driver's sequence moved on 70 000 writes"),
        Scenario("arms-collide", "inject", "ssc", "worker", "ssc.collide", ("estop",),
                 "apart", "", apart=True,
                 what="a command override in the SSC steers the holding r1 into r2 (past "
                      "the task's load check): the group frozen with the arms apart"),
        Scenario("replay-earlier-run", "rerun", "esc.r2", "ddm", "rerun", ("ok",), "", "",
                 count="forged",
                 what="a session's hello and commands to r2, recorded, sent to r2's ddm in a "
                      "later session with the same key file, before that session's SSC comes"),
        Scenario("card-squat", "local-user", "", "", "card-squat", ("ok",), "", "",
                 what="another user holds 256 memory-card keys of the project's range while "
                      "a session runs over reflective memory"),
        Scenario("out-planted-links", "local-user", "", "", "out-planted-links", refused,
                 "", "",
                 what="session --out into another user's folder holding links to a private "
                      "file, named as the run folder's files"),
        Scenario("home-stuck-on", "calibration", "plant", "", "plant.home-stuck-on",
                 ("abnormal",), "no home switch", "",
                 what="r2's home switches stuck on during self-calibration"),
        Scenario("home-stuck-off", "calibration", "plant", "", "plant.home-stuck-off",
                 ("abnormal",), "no home switch", "",
                 what="r2's home switches stuck off during self-calibration"),
        Scenario("stale-ipc", "start", "", "", "stale-ipc", ("ok",), "", "",
                 what="every process of a session SIGKILLed, then a new session"),
        Scenario("positions-missing", "start", "", "", "positions-missing", refused,
                 "positions", "", what="r2's positions file deleted"),
        Scenario("positions-corrupt", "start", "", "", "positions-corrupt", refused,
                 "positions", "", what="r2's positions file not JSON"),
        Scenario("positions-unclean", "start", "", "", "positions-unclean", refused,
                 "positions", "", what="r2's positions file marked unclean (a crashed session)"),
    ]  # fmt: skip
    for case, what in INPUT_CASES.items():
        out.append(Scenario(f"input-{case}", "input", "", "", case, refused, "", "", what=what))
    out.append(
        Scenario("cpu-hogs-peg", "hogs", "", "", "hogs", ("ok",), "", "",
                 what="the short peg insertion (the main job's four segments) beside two "
                      "processes spinning on both CPUs")
    )  # fmt: skip
    return out


# invalid inputs: case -> what is wrong (the files are written by the runner)
INPUT_CASES = {
    "wrong-type": "a segment's duration_s is a string",
    "unknown-key": "a segment has an unknown key",
    "unreachable-goal": "a goal 3 m from the robot's base",
    "zero-duration": "a segment's duration_s is 0",
    "negative-duration": "a goal's move_s is negative",
    "unknown-robot": "the task names robot r9",
    "bad-config": "--set esc.rate_hz=-5",
    "config-unknown-key": "a config file with an unknown section key",
}

CATALOGUE: tuple[Scenario, ...] = tuple(
    _process_scenarios() + _inject_scenarios() + _limit_scenarios() + _other_scenarios()
)


def by_name(name: str) -> Scenario:
    for s in CATALOGUE:
        if s.name == name:
            return s
    raise KeyError(name)

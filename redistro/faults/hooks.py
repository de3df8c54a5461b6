"""The fault harness's hooks, installed into a session's processes from outside.

The runner arms one injection point for a session (:mod:`redistro.faults.inject`)
and names this module as the session's hooks (:mod:`redistro.process.hooks`);
the plant and the ddms then ask it for their part:

- :func:`plant_disturbance`: the plant's faults (a
  :class:`~redistro.plant.disturbance.Disturbance`):
  ``plant.wrist-push`` (pressed down hard on the peg, every step),
  ``plant.encoder-jump`` (one counter glitch on joint 1),
  ``plant.home-stuck-on`` / ``-off`` (every home switch of the robot stuck),
  ``plant.sensor-nan`` (the wrist receiver's calibration memory corrupted);
- :func:`ddm_hooks`: a ddm's faults: its transport wrapped
  (:mod:`redistro.faults.wire`), ``ddm.command``, a bad command written
  into an ESC's Local Data, and ``ddm.hold``: the ddm opens its link only
  once the trigger exists (at most ``HOLD_MAX_S``; a node that comes late,
  for a scenario that needs something to reach a peer before it);
- :func:`ssc_hooks`: ``ssc.collide``, a command override in the SSC: from
  the trigger on, the holding robot (r1) is steered at ``COLLIDE_RAD_S``
  toward ``INTO_R2``, a posture that swings it into r2 (past the task's
  load check: nothing in the task asks for it).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from redistro.faults import inject
from redistro.faults.wire import POINTS, InjectedTransport, Relay
from redistro.localdata.layout import COMMAND

STUCK = {"home-stuck-on": True, "home-stuck-off": False}
HOLD_MAX_S = 5.0  # (within the node's start-up timeout)


class PlantFaults:
    """One armed plant point, acting on the robot it concerns."""

    def __init__(self, injection: inject.Injection) -> None:
        self.injection = injection
        injection.defer_record = True  # recorded once the faulty step is on the boards
        self.robot = -1  # the rig it concerns (found at the first step)
        self.glitched = False

    def _live(self, chassis: Any) -> str:
        if self.robot < 0:
            names = [r.name for r in chassis.rigs]
            self.robot = next((i for i, n in enumerate(names) if self.injection.concerns(n)), 0)
        if not self.injection.live():
            return ""
        return self.injection.point.split(".", 1)[1]

    def before_physics(self, chassis: Any) -> None:
        what = self._live(chassis)
        arg = self.injection.arg
        if what == "wrist-push":
            chassis.push_wrist(self.robot, np.array([0.0, 0.0, -(arg or 300.0)]))
        elif what == "encoder-jump" and not self.glitched:
            self.glitched = True
            chassis.glitch_encoder(self.robot, 1, int(arg or 5000))
        chassis.force_home_switches(self.robot, STUCK.get(what))

    def after_sample(self, chassis: Any) -> None:
        if self._live(chassis) == "sensor-nan":
            chassis.corrupt_wrist_calibration(self.robot)

    def on_boards(self, now_ns: int) -> None:
        inj = self.injection
        if inj.fired_ns and not inj.recorded:
            inj.record(now_ns)  # the fault is on the boards from this step


def plant_disturbance() -> PlantFaults | None:
    """The plant's armed point, or None."""
    inj = inject.injection("plant.")
    return None if inj is None else PlantFaults(inj)


class DdmFaults:
    """A ddm's armed points: its transport wrapped, its commands corrupted."""

    def __init__(self, node: str, kind: str) -> None:
        self.node = node
        self.command_injection = inject.injection("ddm.command", node) if kind == "esc" else None
        self.wire = [inj for p in POINTS if (inj := inject.injection(p, node)) is not None]
        self.hold = inject.injection("ddm.hold", node)

    def before_open(self) -> None:
        """Called before the ddm opens its link: with ``ddm.hold`` armed,
        wait for the trigger (polled, to a deadline of ``HOLD_MAX_S``)."""
        if self.hold is None:
            return
        deadline = time.monotonic() + HOLD_MAX_S
        while not self.hold.live() and time.monotonic() < deadline:
            time.sleep(inject.CHECK_EVERY_NS / 1e9)  # polling the trigger file

    def transport(self, transport: Any, names: dict[int, str]) -> Any:
        """The transport with the armed link and record faults around it
        (and, for a command fault, a relay: every command then comes to the
        ddm's step, where the corruption is applied after admission)."""
        for inj in self.wire:
            transport = InjectedTransport(transport, inj, names)
        if self.command_injection is not None and not self.wire:
            transport = Relay(transport)
        return transport

    @property
    def corrupts_commands(self) -> bool:
        return self.command_injection is not None

    def command(self, payload: Any) -> Any:
        """The command to write: from the trigger on, ``arg`` (NaN, inf or a
        torque) on joint 1 of every command, the joint under control."""
        inj = self.command_injection
        if inj is None or not inj.live():
            return payload
        bad = np.frombuffer(bytes(payload), dtype=COMMAND).copy().reshape(())
        bad["tau_nm"][0] = inj.arg
        bad["joint_on"][0] = 1
        return bad


def ddm_hooks(node: str, kind: str) -> DdmFaults | None:
    """The ddm's armed points, or None."""
    hooks = DdmFaults(node, kind)
    armed = hooks.command_injection is not None or hooks.wire or hooks.hold is not None
    return hooks if armed else None


COLLIDE_RAD_S = 0.4  # the override's joint speed (under the guard's limits)
INTO_R2 = np.array([-1.5708, 1.3, 0.0, -0.4, 0.0, 0.3, 0.0])  # r1 reaching into r2


class SscFaults:
    """The SSC's armed point: a holding robot steered into the other."""

    def __init__(self, injection: inject.Injection) -> None:
        self.injection = injection

    def steer(self, states: list[Any], dt: float) -> None:
        """Before the cycle's laws: move the holding robot's hold posture
        toward INTO_R2, at most COLLIDE_RAD_S per joint."""
        if not self.injection.live():
            return
        step = COLLIDE_RAD_S * dt
        for st in states:
            if st.name == "r1":
                st.hold_q[...] += np.clip(INTO_R2 - st.hold_q, -step, step)


def ssc_hooks(node: str) -> SscFaults | None:
    """The SSC's armed point, or None."""
    inj = inject.injection("ssc.collide", node)
    return None if inj is None else SscFaults(inj)

"""The live view's operator panel: pause, resume, stop, e-stop and jog buttons.

Shown only when the viewer can read the session's key (it runs as the
session's user, beside its 0700 runtime folder): each click is a command
signed with that key (``ssc/ctl.py``), sent from a thread of its own so the
page stays responsive; the manager's answer is shown under the buttons.
"""

from __future__ import annotations

import math
import threading
from typing import Any

from redistro.errors import ConfigError
from redistro.ssc.ctl import Client, Command, Order

JOG_AXES = ("+x", "-x", "+y", "-y", "+z", "-z")
JOG_STEPS_MM = ("1", "2", "5")


def client_for(session_id: str) -> Client | None:
    """A signing client of the session, or None (its key is not ours to read)."""
    from redistro.ipc import names

    try:
        return Client(session_id, names.runtime_dir() / session_id)
    except ConfigError:
        return None


def jog_step(axis: str, mm: float) -> tuple[float, float, float, float, float, float]:
    """The world-frame step of a jog button: ``+z`` by ``mm`` millimetres."""
    sign = 1.0 if axis[0] == "+" else -1.0
    v = [0.0] * 6
    v["xyz".index(axis[1])] = sign * mm / 1000.0
    return (v[0], v[1], v[2], v[3], v[4], v[5])


class OperatorPanel:
    """The buttons on a viser GUI (the server's, or one client's)."""

    def __init__(self, gui: Any, client: Client, robots: list[str]) -> None:
        self.client, self.robots = client, robots
        self.lock = threading.Lock()
        with gui.add_folder("operator"):
            self.pause = gui.add_button("Pause")
            self.resume = gui.add_button("Resume")
            self.stop = gui.add_button("Stop")
            self.estop = gui.add_button("E-stop", color="red")
            self.robot = gui.add_dropdown("jog robot", options=robots, initial_value=robots[0])
            self.step = gui.add_dropdown("jog mm", options=JOG_STEPS_MM, initial_value="5")
            self.jog = gui.add_button_group("jog", options=JOG_AXES)
            self.answer = gui.add_markdown("operator: ready")
        for button, command in (
            (self.pause, Command.PAUSE),
            (self.resume, Command.RESUME),
            (self.stop, Command.STOP),
            (self.estop, Command.ESTOP),
        ):
            button.on_click(lambda _e, c=command: self._send(Order(c)))
        self.jog.on_click(self._jog)

    def _jog(self, event: Any) -> None:
        axis = str(event.target.value)
        mm = float(self.step.value)
        if axis not in JOG_AXES or not (math.isfinite(mm) and 0 < mm <= 5):
            return
        robot = self.robots.index(str(self.robot.value))
        self._send(Order(Command.JOG, robot, jog_step(axis, mm)))

    def _send(self, order: Order) -> None:
        """The command, from a thread of its own (the answer may take a second)."""
        if not self.lock.acquire(blocking=False):
            self.answer.content = "operator: busy, the last command is under way"
            return
        self.answer.content = f"operator: {order.command.name.lower()} sent"

        def run() -> None:
            try:
                reply = self.client.send(order)
                ok = "done" if reply.get("ok") else "not done"
                self.answer.content = f"operator: {reply.get('text', '')} ({ok})"
            finally:
                self.lock.release()

        threading.Thread(target=run, name="view-operator", daemon=True).start()

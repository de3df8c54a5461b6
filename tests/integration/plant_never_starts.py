"""Hooks (REDISTRO_HOOKS) for a session whose plant dies in its start-up,
after the nodes started beside it have begun waiting for it."""

from __future__ import annotations

import time


def plant_disturbance() -> None:
    time.sleep(1.5)  # the ESC managers are up and waiting by then
    raise RuntimeError("this plant never starts (a test's hook)")

"""Hooks installed into a session's processes from outside.

A tool that composes a session with behaviour of its own (the fault harness
breaking it on purpose) names a module in the environment every process of
the session inherits::

    REDISTRO_HOOKS=redistro.faults.hooks

A process that offers a hook point asks :func:`factory` for that module's
function of the point's name once, at its Initialization (the plant for
``plant_disturbance``, a ddm for ``ddm_hooks``), and calls it. The layers
that offer the points never import the tool; in a normal run nothing is
imported and nothing is paid in a cycle.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

ENV = "REDISTRO_HOOKS"
# a developer's profile of one process: "NODE/WORKER" (tools/profile.py)
PROFILE_ENV = "REDISTRO_PROFILE"
PROFILE_OUT_ENV = "REDISTRO_PROFILE_OUT"  # the folder its statistics go to


def factory(name: str) -> Callable[..., Any] | None:
    """The hooks module's function ``name``, or None (no module named, or no
    such function in it). A named module that cannot be imported is an
    error of the tool that named it: ImportError."""
    module = os.environ.get(ENV)
    if not module:
        return None
    fn = getattr(importlib.import_module(module), name, None)
    return fn if callable(fn) else None


class Profile:
    """cProfile around one process's routine, its statistics written at the
    end to ``<REDISTRO_PROFILE_OUT>/profile-<node>-<worker>.pstats``. Only
    the process named in ``REDISTRO_PROFILE`` pays for it (cProfile slows it
    about twofold); every other process pays one lookup at start."""

    def __init__(self, name: str) -> None:
        import cProfile

        self.path = Path(os.environ.get(PROFILE_OUT_ENV) or ".") / (
            "profile-" + name.replace("/", "-") + ".pstats"
        )
        self.profiler = cProfile.Profile()

    def __enter__(self) -> Profile:
        self.profiler.enable()
        return self

    def __exit__(self, *exc: object) -> None:
        self.profiler.disable()
        self.profiler.dump_stats(str(self.path))


def profile(name: str) -> Profile | None:
    """A profile of this process when it is the one named (``node/worker``)."""
    return Profile(name) if os.environ.get(PROFILE_ENV) == name else None

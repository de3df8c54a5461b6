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
from typing import Any

ENV = "REDISTRO_HOOKS"


def factory(name: str) -> Callable[..., Any] | None:
    """The hooks module's function ``name``, or None (no module named, or no
    such function in it). A named module that cannot be imported is an
    error of the tool that named it: ImportError."""
    module = os.environ.get(ENV)
    if not module:
        return None
    fn = getattr(importlib.import_module(module), name, None)
    return fn if callable(fn) else None

"""Registries of backends imported only when used, as python-can's ``BACKENDS``.

A registry is a dict from a config key to ``"module:Name"``; :func:`load`
imports that module and returns the name. Adding a backend (a worker role,
a transport, a backplane) is one line in its table.
"""

from __future__ import annotations

import importlib
from typing import Any


def load(table: dict[str, str], key: str, what: str) -> Any:
    """The object ``table[key]`` names; KeyError naming the known keys."""
    try:
        target = table[key]
    except KeyError:
        raise KeyError(f"unknown {what} {key!r} (known: {', '.join(table)})") from None
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)

"""Worker roles: a key in a NodeSpec maps to a class, imported only when used."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from redistro.process.worker import Worker

ROLES: dict[str, str] = {
    "busy": "redistro.process.busy:BusyWorker",
}


def worker_class(role: str) -> type[Worker]:
    try:
        target = ROLES[role]
    except KeyError:
        raise KeyError(f"unknown worker role {role!r} (known: {', '.join(ROLES)})") from None
    module, _, name = target.partition(":")
    cls: type[Worker] = getattr(importlib.import_module(module), name)
    return cls

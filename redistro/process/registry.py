"""Worker roles: a key in a NodeSpec maps to a class, imported only when used."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from redistro.process.manager import Manager
    from redistro.process.worker import Worker

ROLES: dict[str, str] = {
    "busy": "redistro.process.busy:BusyWorker",
    "acquisition": "redistro.esc.acquisition:Acquisition",
    "calibration": "redistro.esc.calibration:Calibration",
    "pid": "redistro.esc.pid:Pid",
    "sender": "redistro.esc.sender:Sender",
    "ddm": "redistro.ddm.worker:Ddm",
    "worker": "redistro.ssc.worker:SscWorker",
    "logger": "redistro.ssc.logger:SscLogger",
    "recorder": "redistro.log.worker:EscRecorder",
}

# node kind -> its manager class ("bench" nodes use the base Manager)
MANAGERS: dict[str, str] = {
    "esc": "redistro.esc.manager:EscManager",
    "ssc": "redistro.ssc.manager:SscManager",
}


def manager_class(kind: str) -> type[Manager]:
    target = MANAGERS.get(kind, "redistro.process.manager:Manager")
    module, _, name = target.partition(":")
    cls: type[Manager] = getattr(importlib.import_module(module), name)
    return cls


def worker_class(role: str) -> type[Worker]:
    try:
        target = ROLES[role]
    except KeyError:
        raise KeyError(f"unknown worker role {role!r} (known: {', '.join(ROLES)})") from None
    module, _, name = target.partition(":")
    cls: type[Worker] = getattr(importlib.import_module(module), name)
    return cls

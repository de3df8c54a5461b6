"""Worker roles: a key in a NodeSpec maps to a class, imported only when used."""

from __future__ import annotations

from typing import TYPE_CHECKING

from redistro.registries import load

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
    cls: type[Manager] = load(
        {kind: MANAGERS.get(kind, "redistro.process.manager:Manager")}, kind, "node kind"
    )
    return cls


def worker_class(role: str) -> type[Worker]:
    cls: type[Worker] = load(ROLES, role, "worker role")
    return cls

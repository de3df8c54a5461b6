"""Backplanes: how I/O module drivers reach the board registers.

Controller side, :class:`Backplane`: ``inventory()`` lists the chassis,
``read(addresses)`` takes a snapshot of each board's ``in`` bank,
``write(address, record)`` sets a board's ``out`` bank. Board side (inside the
plant), :class:`BoardPort`: ``outputs(address)`` and ``publish(address, record)``.

Every operation is bounded by the I/O timeout: a board that has not updated
(shm) or answered (CAN) within it raises :class:`~redistro.errors.IOFault`.
Implementations are chosen by ``plant.backplane`` through the registry
:data:`BACKPLANES` (:func:`open_backplane`) and imported only when used: the
shared-memory bank in :mod:`redistro.drivers.io.shm`, CAN in
:mod:`redistro.drivers.io.can`.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any

import numpy as np

from redistro.drivers.io.registers import BoardType
from redistro.registries import load

if TYPE_CHECKING:
    from redistro.config.model import PlantConfig


class Backplane(ABC):
    """The controller's end of the chassis bus."""

    timeout_s: float

    @classmethod
    def from_config(cls, plant: PlantConfig, session_id: str) -> Backplane:
        """This backplane to the plant of ``session_id``, set up from the
        plant's config (the I/O timeout; a backplane with a bus of its own
        reads its section)."""
        return cls(session_id, plant.io_timeout_ms / 1e3)  # type: ignore[call-arg]

    @abstractmethod
    def inventory(self) -> dict[int, BoardType]:
        """address -> board type, as the chassis reports it."""

    @abstractmethod
    def read(self, addresses: list[int]) -> dict[int, np.ndarray[Any, Any]]:
        """A fresh snapshot of each board's ``in`` bank (a 0-d record each)."""

    @abstractmethod
    def write(self, address: int, record: np.ndarray[Any, Any]) -> None:
        """Set a board's whole ``out`` bank."""

    def reader(
        self, views: dict[int, np.ndarray[Any, Any]], image: np.ndarray[Any, Any] | None = None
    ) -> Any:
        """A callable that takes a fresh snapshot of every listed board's ``in``
        bank into ``views`` (address -> its bytes; views of ``image``, the
        caller's register memory, when given): :meth:`read`, in one go."""
        addrs = list(views)
        pairs = [(a, views[a]) for a in addrs]

        def read_all() -> None:
            recs = self.read(addrs)
            for a, dst in pairs:
                dst[...] = _bytes_array(recs[a])

        return read_all

    def writer(
        self, records: dict[int, np.ndarray[Any, Any]], image: np.ndarray[Any, Any] | None = None
    ) -> Any:
        """A callable that writes every listed board's ``out`` bank from
        ``records`` (address -> the bank, kept and updated in place by the
        caller; views of ``image`` when given): :meth:`write`, in one go."""
        pairs = list(records.items())

        def write_all() -> None:
            for a, rec in pairs:
                self.write(a, rec)

        return write_all

    @abstractmethod
    def close(self) -> None: ...


def _bytes_array(rec: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    raw: np.ndarray[Any, Any] = rec.reshape(1).view(np.uint8)
    return raw


class BoardPort(ABC):
    """The boards' end of the chassis bus (the plant)."""

    @abstractmethod
    def outputs(self, address: int) -> np.ndarray[Any, Any]:
        """The latest ``out`` bank the controller wrote (a 0-d record)."""

    def outputs_into(self, address: int, dst: memoryview) -> None:
        """Copy the latest ``out`` bank into ``dst`` (its raw bytes)."""
        dst[:] = _bytes(self.outputs(address))

    @abstractmethod
    def publish(self, address: int, record: np.ndarray[Any, Any]) -> None:
        """Make a board's ``in`` bank visible to the controller."""

    def publisher(
        self, records: dict[int, np.ndarray[Any, Any]], image: np.ndarray[Any, Any] | None = None
    ) -> Any:
        """A callable that publishes every board's ``in`` bank from ``records``
        (address -> a record the board side keeps and updates in place; each a
        view of ``image``, the board side's register memory, when given)."""
        pairs = list(records.items())

        def publish_all() -> None:
            for a, rec in pairs:
                self.publish(a, rec)

        return publish_all

    def outputs_reader(
        self, views: dict[int, np.ndarray[Any, Any]], image: np.ndarray[Any, Any] | None = None
    ) -> Any:
        """A callable that takes every listed board's latest ``out`` bank into
        ``views`` (address -> its bytes; views of ``image`` when given)."""
        pairs = [(a, memoryview(v)) for a, v in views.items()]  # type: ignore[arg-type]

        def read_all() -> None:
            for a, dst in pairs:
                self.outputs_into(a, dst)

        return read_all

    def service(self, until_ns: int) -> None:
        """Serve requests until ``until_ns`` (CLOCK_MONOTONIC); default: sleep."""
        delay = (until_ns - time.monotonic_ns()) / 1e9
        if delay > 0:
            time.sleep(delay)

    @abstractmethod
    def close(self) -> None: ...


def _bytes(record: np.ndarray[Any, Any]) -> memoryview:
    return memoryview(record.reshape(1).view(np.uint8))  # type: ignore[arg-type]


BACKPLANES: dict[str, str] = {
    "shm": "redistro.drivers.io.shm:ShmBackplane",
    "can": "redistro.drivers.io.can:CanBackplane",
}


def backplane_class(kind: str) -> type[Backplane]:
    cls: type[Backplane] = load(BACKPLANES, kind, "backplane")
    return cls


def open_backplane(plant: PlantConfig, session_id: str) -> Backplane:
    """The controller's backplane ``plant.backplane`` names, to the plant of
    ``session_id`` (not opened yet; each backplane reads its part of the
    plant's config)."""
    return backplane_class(plant.backplane).from_config(plant, session_id)

"""Backplanes: how I/O module drivers reach the board registers.

Controller side, :class:`Backplane`: ``inventory()`` lists the chassis,
``read(addresses)`` takes a snapshot of each board's ``in`` bank,
``write(address, record)`` sets a board's ``out`` bank. Board side (inside the
plant), :class:`BoardPort`: ``outputs(address)`` and ``publish(address, record)``.

Every operation is bounded by the I/O timeout: a board that has not updated
(shm) or answered (CAN) within it raises :class:`~redistro.errors.IOFault`.
Implementations are chosen by ``plant.backplane`` in :func:`open_backplane`
and imported only when used.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from typing import Any

import numpy as np

from redistro.drivers.io.registers import BANKS, BoardType
from redistro.errors import IOFault, TornReadTimeout


class Backplane(ABC):
    """The controller's end of the chassis bus."""

    timeout_s: float

    @abstractmethod
    def inventory(self) -> dict[int, BoardType]:
        """address -> board type, as the chassis reports it."""

    @abstractmethod
    def read(self, addresses: list[int]) -> dict[int, np.ndarray[Any, Any]]:
        """A fresh snapshot of each board's ``in`` bank (a 0-d record each)."""

    @abstractmethod
    def write(self, address: int, record: np.ndarray[Any, Any]) -> None:
        """Set a board's whole ``out`` bank."""

    @abstractmethod
    def close(self) -> None: ...


class BoardPort(ABC):
    """The boards' end of the chassis bus (the plant)."""

    @abstractmethod
    def outputs(self, address: int) -> np.ndarray[Any, Any]:
        """The latest ``out`` bank the controller wrote (a 0-d record)."""

    @abstractmethod
    def publish(self, address: int, record: np.ndarray[Any, Any]) -> None:
        """Make a board's ``in`` bank visible to the controller."""

    def service(self, until_ns: int) -> None:
        """Serve requests until ``until_ns`` (CLOCK_MONOTONIC); default: sleep."""
        delay = (until_ns - time.monotonic_ns()) / 1e9
        if delay > 0:
            time.sleep(delay)

    @abstractmethod
    def close(self) -> None: ...


# -- shared-memory register bank --


class ShmBackplane(Backplane):
    """Registers in the plant's shared-memory bank (:mod:`bank`)."""

    def __init__(self, session_id: str, timeout_s: float) -> None:
        from redistro.drivers.io.bank import RegisterBank

        self.timeout_s = timeout_s
        self.bank = RegisterBank.attach(session_id)
        self._in: dict[int, Any] = {}
        self._out: dict[int, Any] = {}
        self._recs: dict[int, np.ndarray[Any, Any]] = {}
        self._views: dict[int, memoryview] = {}  # byte views of _recs (no per-read allocation)
        self._last: dict[int, tuple[int, int]] = {}  # address -> (step, monotonic ns seen)

    def inventory(self) -> dict[int, BoardType]:
        return dict(zip(self.bank.addresses, self.bank.types, strict=True))

    def _in_block(self, address: int) -> Any:
        block = self._in.get(address)
        if block is None:
            if address not in self.bank.index:
                raise IOFault(f"no board at address {address} in the chassis")
            block = self._in[address] = self.bank.board_in(address)
            rec = np.zeros((), BANKS[self.bank.types[self.bank.index[address]]][0])
            self._recs[address] = rec
            self._views[address] = memoryview(rec.reshape(1).view(np.uint8))  # type: ignore[arg-type]
        return block

    def read(self, addresses: list[int]) -> dict[int, np.ndarray[Any, Any]]:
        from redistro.errors import TornReadTimeout

        now = time.monotonic_ns()
        out = {}
        for a in addresses:
            block = self._in.get(a) or self._in_block(a)
            rec = self._recs[a]
            try:
                block.read_into(self._views[a], budget_s=self.timeout_s)
            except TornReadTimeout:
                raise IOFault(f"board {a}: register bank stuck mid-update") from None
            step = int(rec["step"])
            last = self._last.get(a)
            if last is None or step != last[0]:
                self._last[a] = (step, now)
            elif now - last[1] > self.timeout_s * 1e9:
                raise IOFault(
                    f"board {a}: no update for {(now - last[1]) / 1e6:.0f} ms "
                    f"(step {step}): the plant is stopped or gone"
                )
            out[a] = rec
        return out

    def write(self, address: int, record: np.ndarray[Any, Any]) -> None:
        block = self._out.get(address)
        if block is None:
            if address not in self.bank.index:
                raise IOFault(f"no board at address {address} in the chassis")
            block = self._out[address] = self.bank.board_out(address)
        block.publish(record)

    def close(self) -> None:
        self.bank.close()


class ShmPort(BoardPort):
    def __init__(self, bank: Any) -> None:
        self.bank = bank
        self._in = {a: bank.board_in(a) for a in bank.addresses}
        self._out = {a: bank.board_out(a) for a in bank.addresses}
        self._recs = {
            a: np.zeros((), BANKS[t][1]) for a, t in zip(bank.addresses, bank.types, strict=True)
        }
        self._rec_bytes = {a: _bytes(r) for a, r in self._recs.items()}
        self._scratch = {a: np.zeros((), r.dtype) for a, r in self._recs.items()}
        self._scratch_bytes = {a: _bytes(r) for a, r in self._scratch.items()}
        self._published: dict[int, tuple[np.ndarray[Any, Any], memoryview]] = {}
        self.torn_outputs = 0  # steps that kept a board's previous outputs

    def outputs(self, address: int) -> np.ndarray[Any, Any]:
        """The latest consistent outputs. A writer held off inside its write
        (preempted on a loaded host) leaves no consistent copy for a while:
        the board then keeps its previous outputs for this step, as a real
        board keeps its registers until the next complete write."""
        try:
            self._out[address].read_into(self._scratch_bytes[address])
        except TornReadTimeout:
            self.torn_outputs += 1
            return self._recs[address]
        self._rec_bytes[address][:] = self._scratch_bytes[address]
        return self._recs[address]

    def publish(self, address: int, record: np.ndarray[Any, Any]) -> None:
        cached = self._published.get(address)
        if cached is None or cached[0] is not record:  # the chassis keeps its records
            cached = self._published[address] = (record, _bytes(record))
        self._in[address].publish(cached[1])

    def close(self) -> None:
        pass  # the bank is the plant's; it closes it


def _bytes(record: np.ndarray[Any, Any]) -> memoryview:
    return memoryview(record.reshape(1).view(np.uint8))  # type: ignore[arg-type]


def open_backplane(kind: str, session_id: str, timeout_s: float, **can: Any) -> Backplane:
    """The controller's backplane of ``kind`` (``plant.backplane``)."""
    if kind == "shm":
        return ShmBackplane(session_id, timeout_s)
    if kind == "can":
        from redistro.drivers.io.can import CanBackplane

        return CanBackplane(session_id, timeout_s, **can)
    raise ValueError(f"unknown backplane {kind!r}")

"""The shared-memory backplane: board registers in the plant's register bank
(:mod:`redistro.drivers.io.bank`), read and written with sequence counters
and the I/O timeout, the controller's end (:class:`ShmBackplane`) and the
plant's (:class:`ShmPort`)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from redistro.drivers.io.backplane import Backplane, BoardPort, _bytes
from redistro.drivers.io.registers import BANKS, BoardType
from redistro.errors import IOFault, TornReadTimeout


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
        # address -> (its publishes, monotonic ns they last moved)
        self._last: dict[int, tuple[int, int]] = {}

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
            self._fresh(a, block.seq, now, int(rec["step"]))
            out[a] = rec
        return out

    def reader(
        self, views: dict[int, np.ndarray[Any, Any]], image: np.ndarray[Any, Any] | None = None
    ) -> Any:
        from redistro import kernels

        if image is None or not kernels.AVAILABLE:
            return super().reader(views, image)
        addrs = list(views)
        for a in addrs:
            self._in_block(a)  # checks the address
        bank = self.bank
        table = kernels.table(
            "seq_read",
            "table",
            [
                (
                    *bank.board_offsets(a, "in")[:2],
                    views[a].nbytes,
                    kernels.address_in(image, views[a]),
                )
                for a in addrs
            ],
        )
        torn = np.zeros(len(addrs), dtype=np.int64)
        p = kernels.plan("seq_read", src=bank.raw, dst=image, table=table, torn=torn)
        read = kernels.KERNELS.seq_read
        # the first board's step (the bank's common header), read from the
        # snapshot: the plant publishes every board at each step, so a plant
        # that stopped stops them all
        at = int(BANKS[BoardType.ENCODER][0].fields["step"][1])  # type: ignore[index]
        first = addrs[0]
        step = views[first][at : at + 8].view("<u8")
        seq_at = bank.board_offsets(first, "in")[0]  # (its publishes: see _fresh)
        seq = bank.raw[seq_at : seq_at + 8].view("<u8")
        fallback = super().reader(views, image)
        fresh = self._fresh
        monotonic_ns = time.monotonic_ns

        def read_kernel() -> None:
            if read(p):  # a board mid-update: its snapshot the patient way (or an IOFault)
                fallback()
                return
            fresh(first, int(seq[0]), monotonic_ns(), int(step[0]))

        return read_kernel

    def _fresh(self, a: int, published: int, now: int, step: int) -> None:
        """A board the plant has not published for the I/O timeout is an
        IOFault. Its publishes (the seqlock's count), not its physics step:
        in lockstep the plant serves the boards without stepping until the
        group's first tick (a node slow to start on a loaded host once read
        the same step 0 over 514 ms apart, inside its encoder preset)."""
        last = self._last.get(a)
        if last is None or published != last[0]:
            self._last[a] = (published, now)
        elif now - last[1] > self.timeout_s * 1e9:
            raise IOFault(
                f"board {a}: no update for {(now - last[1]) / 1e6:.0f} ms "
                f"(step {step}): the plant is stopped or gone"
            )

    def writer(
        self, records: dict[int, np.ndarray[Any, Any]], image: np.ndarray[Any, Any] | None = None
    ) -> Any:
        from redistro import kernels

        if image is None or not kernels.AVAILABLE:
            return super().writer(records, image)
        bank = self.bank
        for a in records:
            if a not in bank.index:
                raise IOFault(f"no board at address {a} in the chassis")
        table = kernels.table(
            "seq_write",
            "table",
            [
                (*bank.board_offsets(a, "out")[:2], rec.nbytes, kernels.address_in(image, rec))
                for a, rec in records.items()
            ],
        )
        p = kernels.plan("seq_write", dst=bank.raw, src=image, table=table)
        write = kernels.KERNELS.seq_write
        return lambda: write(p)

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
        self._torn = 0
        self._kernel_torn = np.zeros(0, dtype=np.int64)

    @property
    def torn_outputs(self) -> int:
        """Steps that kept a board's previous outputs (its writer was mid-write)."""
        return self._torn + int(self._kernel_torn.sum())

    def outputs(self, address: int) -> np.ndarray[Any, Any]:
        """The latest consistent outputs. A writer held off inside its write
        (preempted on a loaded host) leaves no consistent copy for a while:
        the board then keeps its previous outputs for this step, as a real
        board keeps its registers until the next complete write."""
        try:
            self._out[address].read_into(self._scratch_bytes[address])
        except TornReadTimeout:
            self._torn += 1
            return self._recs[address]
        self._rec_bytes[address][:] = self._scratch_bytes[address]
        return self._recs[address]

    def outputs_into(self, address: int, dst: memoryview) -> None:
        """As :meth:`outputs`, straight into ``dst``: a torn read leaves ``dst``
        (the board's registers) as they were."""
        scratch = self._scratch_bytes[address]
        try:
            self._out[address].read_into(scratch)
        except TornReadTimeout:
            self._torn += 1
            return
        dst[:] = scratch

    def publish(self, address: int, record: np.ndarray[Any, Any]) -> None:
        cached = self._published.get(address)
        if cached is None or cached[0] is not record:  # the chassis keeps its records
            cached = self._published[address] = (record, _bytes(record))
        self._in[address].publish(cached[1])

    def publisher(
        self, records: dict[int, np.ndarray[Any, Any]], image: np.ndarray[Any, Any] | None = None
    ) -> Any:
        from redistro import kernels

        if image is not None and kernels.AVAILABLE:  # every board in one call
            bank = self.bank
            table = kernels.table(
                "seq_write",
                "table",
                [
                    (*bank.board_offsets(a, "in")[:2], rec.nbytes, kernels.address_in(image, rec))
                    for a, rec in records.items()
                ],
            )
            p = kernels.plan("seq_write", dst=bank.raw, src=image, table=table)
            write = kernels.KERNELS.seq_write

            def publish_kernel() -> None:
                write(p)

            return publish_kernel
        pairs = [(self._in[a].publish, _bytes(rec)) for a, rec in records.items()]

        def publish_all() -> None:
            for publish, raw in pairs:
                publish(raw)

        return publish_all

    def outputs_reader(
        self, views: dict[int, np.ndarray[Any, Any]], image: np.ndarray[Any, Any] | None = None
    ) -> Any:
        from redistro import kernels

        if image is not None and kernels.AVAILABLE:  # every board in one call
            bank = self.bank
            table = kernels.table(
                "seq_read",
                "table",
                [
                    (*bank.board_offsets(a, "out")[:2], v.nbytes, kernels.address_in(image, v))
                    for a, v in views.items()
                ],
            )
            torn = np.zeros(len(views), dtype=np.int64)
            self._kernel_torn = torn
            p = kernels.plan("seq_read", src=bank.raw, dst=image, table=table, torn=torn)
            read = kernels.KERNELS.seq_read

            def read_kernel() -> None:
                # a board whose outputs are mid-write keeps its previous ones
                read(p)

            return read_kernel
        return super().outputs_reader(views, image)

    def close(self) -> None:
        pass  # the bank is the plant's; it closes it

"""The shared-memory register bank: the chassis as one POSIX shared-memory segment.

The plant creates it; drivers attach. Layout (numpy dtypes, built from the
board table so that creator and attachers agree; the header carries a hash):

- ``header``: magic, version, layout hash, plant pid, physics rate, board count;
- ``status`` (seqlocked, plant writes): state, step, simulated time, real-time
  factor, late steps;
- ``table``: per board slot its address and type;
- per board: ``in`` (seqlocked, the board writes) and ``out`` (seqlocked, the
  controller writes) register banks as declared in :mod:`registers`;
- ``truth`` per robot (seqlocked, plant writes): the simulation's ground truth,
  for tests and reports only; no driver reads it.
"""

from __future__ import annotations

import contextlib
import enum
import functools
import hashlib
import os
from typing import Any

import numpy as np

from redistro.drivers.io.registers import BANKS, BoardType
from redistro.errors import IPCError, LayoutError, NodeFault
from redistro.ipc import names
from redistro.ipc.session import Manifest
from redistro.ipc.shm import SharedMemory
from redistro.localdata.block import Block
from redistro.localdata.layout import seqlocked

MAGIC = b"RDSTBANK"
VERSION = 1
NODE = "plant"
OBJECT = "bank"
MAX_BOARDS = 32
MAX_ROBOTS = 4


class PlantState(enum.IntEnum):
    STARTING = 0
    RUNNING = 1
    STOPPED = 2
    FAILED = 3


HEADER = np.dtype(
    [
        ("magic", "S8"),
        ("version", "<u4"),
        ("n_boards", "<u4"),
        ("layout_hash", "<u8"),
        ("plant_pid", "<i8"),
        ("physics_hz", "<f8"),
        ("n_robots", "<u4"),
        ("robot_names", "S16", MAX_ROBOTS),
    ]
)
STATUS = np.dtype(
    [
        ("state", "<u4"),
        ("step", "<u8"),
        ("sim_time_ns", "<u8"),
        ("wall_ns", "<u8"),  # CLOCK_MONOTONIC of the last step
        ("rtf", "<f8"),  # simulated time / wall time since start
        ("late_steps", "<u8"),  # steps taken more than one step late
        ("skipped_steps", "<u8"),  # steps dropped to catch up with the wall clock
    ]
)
TRUTH = np.dtype(
    [
        ("step", "<u8"),
        ("q_rad", "<f8", 7),
        ("qd_rad_s", "<f8", 7),
        ("tau_nm", "<f8", 7),  # applied at the joint (motor or brake)
        ("braked", "u1", 7),
        ("home", "u1", 7),
        ("wrench_sensor", "<f8", 6),  # noise-free wrist wrench, sensor frame
        ("contact_world", "<f8", 6),  # PyBullet's contact forces on the tool, world frame
        ("tool_xyz_m", "<f8", 3),
        ("tool_rot", "<f8", (3, 3)),  # world from sensor frame
        ("encoder_offset_counts", "<i8", 7),  # counter reading at q = 0 (before wrap)
    ]
)


def bank_dtype(board_types: list[BoardType], n_robots: int) -> np.dtype[Any]:
    fields: list[tuple[Any, ...]] = [
        ("header", HEADER),
        ("status", seqlocked(STATUS)),
        ("table", np.dtype([("address", "<u2"), ("type", "<u2")]), (MAX_BOARDS,)),
    ]
    for i, t in enumerate(board_types):
        din, dout = BANKS[t]
        fields.append((f"in{i}", seqlocked(din)))
        fields.append((f"out{i}", seqlocked(dout)))
    fields.append(("truth", seqlocked(TRUTH), (max(n_robots, 1),)))
    return np.dtype([(n, *rest) for n, *rest in fields], align=True)


@functools.cache
def _hash(dt: np.dtype[Any]) -> int:
    return int.from_bytes(hashlib.sha256(repr(dt.descr).encode()).digest()[:8], "little")


class RegisterBank:
    """A mapped register bank. Board access by chassis address."""

    def __init__(self, shm: SharedMemory, dtype: np.dtype[Any], owner: bool) -> None:
        self.shm = shm
        self.owner = owner
        self.view: np.ndarray[Any, Any] = np.ndarray((), dtype=dtype, buffer=shm.buffer)
        n = int(self.view["header"]["n_boards"])
        table = self.view["table"][:n]
        self.addresses = [int(a) for a in table["address"]]
        self.types = [BoardType(int(t)) for t in table["type"]]
        self.index = {a: i for i, a in enumerate(self.addresses)}
        self._blocks: list[Block] = []
        self.status = self._block(self.view["status"], "status")
        n_robots = int(self.view["header"]["n_robots"])
        self.robot_names = [
            bytes(x).decode() for x in self.view["header"]["robot_names"][:n_robots]
        ]

    @property
    def raw(self) -> np.ndarray[Any, Any]:
        """The whole mapping as bytes (for kernels that publish or read many
        blocks in one call: see :meth:`block_offsets`)."""
        return np.frombuffer(self.shm.buffer, dtype=np.uint8)

    def _offsets(self, field: str, index: int | None = None) -> tuple[int, int, int]:
        dt = self.view.dtype
        assert dt.fields is not None
        spec = dt.fields[field]
        block_dt, at = spec[0], int(spec[1])
        if index is not None:  # an array of blocks
            block_dt = block_dt.base
            at += index * block_dt.itemsize
        f = block_dt.fields
        data = f["data"][0]
        return at + int(f["seq"][1]), at + int(f["data"][1]), int(data.itemsize)

    def board_offsets(self, address: int, side: str) -> tuple[int, int, int]:
        """(seq, payload, size) byte offsets in :attr:`raw` of a board's ``in`` or
        ``out`` bank."""
        return self._offsets(f"{side}{self.index[address]}")

    def truth_offsets(self, robot: int) -> tuple[int, int, int]:
        return self._offsets("truth", robot)

    def _block(self, view: np.ndarray[Any, Any], name: str) -> Block:
        b = Block(name, view)
        self._blocks.append(b)
        return b

    @classmethod
    def create(
        cls,
        session_id: str,
        boards: dict[int, BoardType],
        robot_names: list[str],
        physics_hz: float,
        manifest: Manifest | None,
    ) -> RegisterBank:
        if len(boards) > MAX_BOARDS:
            raise LayoutError(f"a chassis holds at most {MAX_BOARDS} boards, got {len(boards)}")
        addresses = sorted(boards)
        types = [boards[a] for a in addresses]
        dt = bank_dtype(types, len(robot_names))
        name = names.object_name(session_id, NODE, OBJECT)
        shm = SharedMemory.create(name, dt.itemsize, manifest)
        view: np.ndarray[Any, Any] = np.ndarray((), dtype=dt, buffer=shm.buffer)
        h = view["header"]
        h["magic"] = MAGIC
        h["version"] = VERSION
        h["n_boards"] = len(addresses)
        h["plant_pid"] = os.getpid()
        h["physics_hz"] = physics_hz
        h["n_robots"] = len(robot_names)
        for i, r in enumerate(robot_names):
            h["robot_names"][i] = r.encode()
        for i, (a, t) in enumerate(zip(addresses, types, strict=True)):
            view["table"][i] = (a, int(t))
            view[f"in{i}"]["data"]["board_type"] = int(t)
        h["layout_hash"] = _hash(dt)  # last: an attacher that sees it sees the rest
        del view, h
        return cls(shm, dt, owner=True)

    @classmethod
    def attach(cls, session_id: str) -> RegisterBank:
        name = names.object_name(session_id, NODE, OBJECT)
        shm = SharedMemory.attach(name)
        try:
            head = np.ndarray((), dtype=HEADER, buffer=shm.buffer)
            if bytes(head["magic"]) != MAGIC or int(head["version"]) != VERSION:
                raise LayoutError(f"{name}: not a register bank of this version")
            if int(head["layout_hash"]) == 0:  # written last: the plant is still making it
                raise LayoutError(f"{name}: not made yet")
            n = int(head["n_boards"])
            table = np.ndarray(
                (MAX_BOARDS,),
                dtype=np.dtype([("address", "<u2"), ("type", "<u2")]),
                buffer=shm.buffer,
                offset=bank_dtype([], 1).fields["table"][1],  # type: ignore[index]
            )
            types = [BoardType(int(t)) for t in table["type"][:n]]
            dt = bank_dtype(types, int(head["n_robots"]))
            if int(head["layout_hash"]) != _hash(dt):
                raise LayoutError(f"{name}: layout hash differs (another version?)")
            del head, table
            return cls(shm, dt, owner=False)
        except Exception:
            shm.close()
            raise

    # -- access --

    def board_in(self, address: int) -> Block:
        return self._block(self.view[f"in{self.index[address]}"], f"in@{address}")

    def board_out(self, address: int) -> Block:
        return self._block(self.view[f"out{self.index[address]}"], f"out@{address}")

    def truth(self, robot: int) -> Block:
        return self._block(self.view["truth"][robot : robot + 1].reshape(()), f"truth{robot}")

    def close(self) -> None:
        for b in self._blocks:
            b.detach()
        self._blocks.clear()
        self.view = np.empty((), dtype=np.uint8)
        with contextlib.suppress(IPCError):
            self.shm.close()

    def unlink(self) -> None:
        self.shm.unlink()


class PlantWatch:
    """Whether the plant of a session is up (its bank says RUNNING): what a
    node started beside a plant still starting waits for."""

    def __init__(self, session_id: str) -> None:
        self.session_id = session_id
        self.bank: RegisterBank | None = None

    def running(self) -> bool:
        """True once RUNNING; NodeFault when the plant ended before that."""
        if self.bank is None:
            try:
                self.bank = RegisterBank.attach(self.session_id)
            except (IPCError, LayoutError):
                return False  # not created yet
        state = int(self.bank.status.read()["state"])
        if state in (PlantState.STOPPED, PlantState.FAILED):
            raise NodeFault("abnormal", "the plant ended before the node started")
        return state == PlantState.RUNNING

    def close(self) -> None:
        if self.bank is not None:
            self.bank.close()
            self.bank = None

"""A node's Local Data segment: create (manager), attach (everyone else), blocks."""

from __future__ import annotations

import contextlib
import os
import time
from typing import Any, cast

import numpy as np

from redistro.errors import IPCError, LayoutError
from redistro.ipc import names
from redistro.ipc.session import Manifest
from redistro.ipc.shm import MemorySegment, SharedMemory
from redistro.localdata.block import Block, MessageBox
from redistro.localdata.layout import (
    BLOCKS,
    HEADER,
    MAGIC,
    SELF,
    VERSION,
    WRITERS,
    layout_hash,
    segment_dtype,
)

OBJECT = "localdata"


def writer_of(block: str, node_kind: str) -> str:
    """The role declared as the one writer of ``block`` in a node of ``node_kind``."""
    table = WRITERS[block]
    role = table.get(node_kind, table.get("*"))
    if role is None:
        raise LayoutError(f"block {block} has no declared writer in a {node_kind} node")
    return role


class LocalData:
    """A node's Local Data: POSIX shared memory, or with ``memory=True`` an
    in-process stand-in (:class:`~redistro.ipc.shm.MemorySegment`) for unit
    tests that run a manager's bookkeeping, a worker or a ddm in one process."""

    def __init__(self, shm: SharedMemory | MemorySegment, n_procs: int, n_robots: int) -> None:
        self.shm = shm
        self.n_procs = n_procs
        self.n_robots = n_robots
        self.dtype = segment_dtype(n_procs, n_robots)
        if shm.size < self.dtype.itemsize:
            raise LayoutError(f"{shm.name}: segment is {shm.size} bytes, layout needs more")
        self.view: np.ndarray[Any, Any] = np.ndarray((), dtype=self.dtype, buffer=shm.buffer)
        self._handles: list[Block | MessageBox] = []

    # -- lifecycle --

    @classmethod
    def create(
        cls,
        session_id: str,
        node: str,
        *,
        node_kind: str,
        proc_names: list[str],
        proc_roles: list[str],
        proc_stages: list[int],
        robot_names: list[str],
        rate_hz: float,
        period_ns: int,
        heartbeat_limit_cycles: int,
        manifest: Manifest | None,
        memory: bool = False,
    ) -> LocalData:
        n_procs, n_robots = len(proc_names), len(robot_names)
        dtype = segment_dtype(n_procs, n_robots)
        name = names.object_name(session_id, node, OBJECT)
        kind = MemorySegment if memory else SharedMemory
        shm = kind.create(name, dtype.itemsize, manifest)
        ld = cls(shm, n_procs, n_robots)
        st = ld.view["static"]
        st["rate_hz"] = rate_hz
        st["period_ns"] = period_ns
        st["heartbeat_limit_cycles"] = heartbeat_limit_cycles
        st["node_kind"] = node_kind.encode()
        st["proc_names"] = [n.encode() for n in proc_names]
        st["proc_roles"] = [r.encode() for r in proc_roles]
        st["proc_stage"] = proc_stages
        st["robot_names"] = [r.encode() for r in robot_names]
        hd = ld.view["header"]
        hd["layout_hash"] = layout_hash(n_procs, n_robots)
        hd["version"] = VERSION
        hd["n_procs"] = n_procs
        hd["n_robots"] = n_robots
        hd["creator_pid"] = os.getpid()
        hd["created_unix_ns"] = time.time_ns()
        hd["session_id"] = session_id.encode()
        hd["node"] = node.encode()
        hd["magic"] = MAGIC  # last: an attacher that sees the magic sees a whole header
        return ld

    @classmethod
    def attach(cls, session_id: str, node: str, memory: bool = False) -> LocalData:
        name = names.object_name(session_id, node, OBJECT)
        shm = (MemorySegment if memory else SharedMemory).attach(name)
        if shm.size < HEADER.itemsize:
            shm.close()
            raise LayoutError(f"{name}: too small for a Local Data header")
        header = np.ndarray((), dtype=HEADER, buffer=shm.buffer).copy()[()]
        if bytes(header["magic"]) != MAGIC:
            shm.close()
            raise LayoutError(f"{name}: bad magic {bytes(header['magic'])!r}")
        n_procs, n_robots = int(header["n_procs"]), int(header["n_robots"])
        problems = []
        if int(header["version"]) != VERSION:
            problems.append(f"version {int(header['version'])} != {VERSION}")
        if int(header["layout_hash"]) != layout_hash(n_procs, n_robots):
            problems.append("layout hash differs from this build's layout")
        if bytes(header["session_id"]).decode() != session_id:
            problems.append("session id differs")
        if problems:
            shm.close()
            raise LayoutError(f"{name}: " + "; ".join(problems))
        return cls(shm, n_procs, n_robots)

    def close(self) -> None:
        for handle in self._handles:
            handle.detach()
        self._handles.clear()
        self.view = np.empty((), dtype=np.uint8)
        # A caller may still hold a view; the mapping then goes with the last
        # view. The name can be unlinked regardless.
        with contextlib.suppress(IPCError):
            self.shm.close()

    def unlink(self) -> None:
        self.shm.unlink()

    @property
    def memory(self) -> bool:
        """In-process (the stand-in for tests), not POSIX shared memory."""
        return isinstance(self.shm, MemorySegment)

    def torn_reads(self) -> int:
        """Snapshot retries needed so far by every read handle of this attachment."""
        return sum(h.torn for h in self._handles if isinstance(h, Block))

    # -- static data --

    @property
    def node_kind(self) -> str:
        return bytes(self.view["static"]["node_kind"][()]).decode()

    @property
    def header(self) -> np.void:
        return cast(np.void, self.view["header"].copy()[()])

    @property
    def static(self) -> np.void:
        return cast(np.void, self.view["static"].copy()[()])

    def proc_names(self) -> list[str]:
        return [bytes(n).decode() for n in self.view["static"]["proc_names"]]

    def proc_roles(self) -> list[str]:
        return [bytes(n).decode() for n in self.view["static"]["proc_roles"]]

    # -- blocks --

    def _block_view(self, name: str, index: int | None) -> np.ndarray[Any, Any]:
        if name not in BLOCKS:
            raise LayoutError(f"no block named {name!r}")
        view = self.view[name]
        if view.ndim:
            if index is None or not 0 <= index < view.shape[0]:
                raise LayoutError(f"block {name} needs an index in 0..{view.shape[0] - 1}")
            return view[index : index + 1].reshape(())  # a 0-d view, not a copy
        if index is not None:
            raise LayoutError(f"block {name} takes no index")
        return view

    def block(self, name: str, index: int | None = None) -> Block:
        """A read handle (``read()``) onto a block."""
        label = f"{name}[{index}]" if index is not None else name
        block = Block(label, self._block_view(name, index))
        self._handles.append(block)
        return block

    def writer(
        self, name: str, index: int | None = None, *, role: str, proc_index: int | None = None
    ) -> Block:
        """A write handle, granted only to the block's declared writer.

        For per-process blocks (``proc``) the writer is the process owning the
        row: pass ``proc_index`` equal to ``index``.
        """
        declared = writer_of(name, self.node_kind)
        if declared == SELF:
            if proc_index is None or proc_index != index:
                raise LayoutError(f"{name}[{index}] is written only by process {index}")
        elif declared != role:
            raise LayoutError(
                f"{name} in a {self.node_kind} node is written by {declared}, not {role}"
            )
        return self.block(name, index)

    @property
    def raw(self) -> np.ndarray[Any, Any]:
        """The whole segment as bytes, for kernels that copy many blocks in one
        call (read-only use; a block is written through its writer handle)."""
        return np.frombuffer(self.shm.buffer, dtype=np.uint8)

    def block_offsets(self, name: str, index: int | None = None) -> tuple[int, int, int]:
        """(seq, payload, payload size) byte offsets of a block in :attr:`raw`."""
        view = self._block_view(name, index)
        base = np.frombuffer(self.shm.buffer, dtype=np.uint8).__array_interface__["data"][0]
        at = view.__array_interface__["data"][0] - base
        fields = view.dtype.fields
        assert fields is not None
        payload = fields["data"][0]
        return at + int(fields["seq"][1]), at + int(fields["data"][1]), int(payload.itemsize)

    def msgbox(self, proc_index: int) -> MessageBox:
        if not 0 <= proc_index < self.n_procs:
            raise LayoutError(f"no process {proc_index}")
        box = MessageBox(self.view["msgbox"][proc_index : proc_index + 1].reshape(()))
        self._handles.append(box)
        return box

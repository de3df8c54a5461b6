"""A read-only view of a running node's Local Data, for the processes that
watch a node from outside it: the session's progress line, the owner's
e-stop relay, the start-up datum, ``redistro top`` and the fault runner.

It attaches once, keeps the blocks it was asked for, and only reads
(seqlocked snapshots). ``NodeView.open`` returns None while the node's
segment is not there (not yet created, or already removed), so a watcher
polls it like any other condition with a deadline.
"""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np

from redistro.errors import IPCError, LayoutError
from redistro.localdata.block import Block
from redistro.localdata.segment import LocalData


class NodeView:
    def __init__(self, ld: LocalData, node: str) -> None:
        self.ld = ld
        self.node = node
        self._blocks: dict[tuple[str, int | None], Block] = {}

    @classmethod
    def attach(cls, session_id: str, node: str) -> NodeView:
        """The view of ``node`` in ``session_id``; LayoutError for a segment of
        another layout, IPCError or OSError when there is none."""
        return cls(LocalData.attach(session_id, node), node)

    @classmethod
    def open(cls, session_id: str, node: str) -> NodeView | None:
        """The view of ``node`` in ``session_id``; None while it has no Local Data."""
        try:
            return cls.attach(session_id, node)
        except (IPCError, LayoutError, OSError, ValueError):
            return None

    def close(self) -> None:
        self._blocks.clear()
        with contextlib.suppress(Exception):
            self.ld.close()

    def __enter__(self) -> NodeView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- what the node is --

    @property
    def kind(self) -> str:
        return self.ld.node_kind

    @property
    def static(self) -> np.void:
        return self.ld.static

    def procs(self) -> list[tuple[str, str]]:
        """(name, role) of each worker process, in row order."""
        return list(zip(self.ld.proc_names(), self.ld.proc_roles(), strict=True))

    # -- snapshots --

    def block(self, name: str, index: int | None = None) -> Block:
        key = (name, index)
        b = self._blocks.get(key)
        if b is None:
            b = self._blocks[key] = self.ld.block(name, index)
        return b

    def read(self, name: str, index: int | None = None) -> Any:
        """A consistent copy of one block (a numpy record)."""
        return self.block(name, index).read()

    def manager(self) -> Any:
        return self.read("manager")

    def cycle(self) -> int:
        return int(self.manager()["cycle"])

    def estop(self) -> bool:
        return bool(self.manager()["estop"])

    def proc(self, who: str) -> Any:
        """The status row of the process named (or, failing that, with the role) ``who``."""
        names, roles = self.ld.proc_names(), self.ld.proc_roles()
        j = names.index(who) if who in names else roles.index(who)
        return self.read("proc", j)

    def pid(self, who: str) -> int:
        """The pid of the manager (``"manager"``) or of a worker process."""
        return int((self.manager() if who == "manager" else self.proc(who))["pid"])


class SessionViews:
    """The views of a running session's nodes, each opened once it exists
    and kept (a watcher polling several nodes: the ROS 2 bridge, the live
    view)."""

    def __init__(self, session_id: str) -> None:
        self.session_id = session_id
        self.views: dict[str, NodeView] = {}

    def get(self, node: str) -> NodeView | None:
        """The node's view; None while it has no Local Data."""
        view = self.views.get(node)
        if view is None:
            view = NodeView.open(self.session_id, node)
            if view is not None:
                self.views[node] = view
        return view

    def close(self) -> None:
        for v in self.views.values():
            v.close()
        self.views.clear()

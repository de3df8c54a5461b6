"""A ddm's answer in its transport's thread.

A transport whose records arrive on a thread of its own (zenoh's) lets the
ddm make its usual step for each record there, as it arrives
(``Accelerator.answer_with``): the record admitted by the kernel; in an
ESC, the newest feedback emitted and sent back as the reply; in the SSC,
the exchange published (its manager watches every robot's updates).
Anything else (the ddm stepping now, an ESC's first command, an e-stop, a
record to refuse, a lost link) is the ddm's own step's: the record goes to
its queue untouched. The step's state is shared under one lock.

The answer is made in one compiled call when the kernels are built (the
``CompiledAnswer``, ddm/answer_kernel.c, over the ddm's plans); :meth:`answer`
is its Python reference, and the path taken otherwise.
"""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING, Any

import numpy as np

from redistro.ddm import wire_layout
from redistro.ddm.transport import ANSWERED, NOT_TAKEN, REPLY_OWED
from redistro.errors import TransportError
from redistro.kernels import KERNELS
from redistro.localdata.layout import MANAGER

if TYPE_CHECKING:
    from redistro.ddm.worker import Ddm


class ThreadAnswer:
    """One ddm's answer in its transport's thread (see the module's text)."""

    def __init__(self, ddm: Ddm) -> None:
        self.ddm = ddm
        self.lock = threading.Lock()  # the ddm's step lock
        self.on = False  # the transport hands records over to be answered
        self.owed = False  # an answer's feedback the ddm's own step is to send
        self.taken_here = 0  # records the Python answer took whole
        # the compiled answer's state and counts (ANSWER_STATE, ddm/wire_layout.py),
        # the e-stop byte it reads, and what runs before each record (a
        # bench's stand-in for the acquisition; None in a node)
        self.state: Any = None
        self.estop_at = 0
        self.before: Any = None

    def offer(self, ld: Any) -> None:
        """Ask the transport to hand its records over as they arrive (the
        compiled answer when the kernels have it)."""
        compiled = None
        if hasattr(KERNELS, "CompiledAnswer"):
            self.state = np.zeros((), wire_layout.ANSWER_STATE)
            _, manager_at, _ = ld.block_offsets("manager")
            self.estop_at = manager_at + int(MANAGER.fields["estop"][1])  # type: ignore[index]
            compiled = self.compiled
        self.on = self.ddm.accel.answer_with(self.answer, compiled)
        self.open_state()

    @property
    def taken(self) -> int:
        """Records taken whole in the transport's thread (by either answer)."""
        return self.taken_here + (0 if self.state is None else int(self.state["answered"]))

    def open_state(self) -> None:
        """The compiled answer's state: answering while this ddm answers,
        was commanded and has its link (the e-stop it reads itself)."""
        if self.state is not None:
            d = self.ddm
            commanded = d.commanded or d.kind != "esc"
            self.state["answering"] = int(self.on and commanded and not d.lost)

    def take_owed(self) -> bool:
        """Whether an answer left the reply to the ddm's step (and no more)."""
        owed, self.owed = self.owed, False
        if self.state is not None and self.state["reply_owed"]:
            owed, self.state["reply_owed"] = True, 0
        return owed

    def compiled(self, put: Any, inbox: Any, fallback: Any, wake: Any) -> Any:
        """The answer in one compiled call (``_kernels.CompiledAnswer``), for the
        transport to hand each record to in its thread: what :meth:`answer`
        does, over the same kernels, state and step lock. ``put`` sends an
        ESC's reply (None: the SSC's side); a record it does not take goes
        to ``fallback(raw)`` (the transport's Python path); ``wake()`` when
        the ddm's own step owes the reply."""
        kpath = self.ddm.kernel_path
        assert kpath is not None and KERNELS is not None
        return KERNELS.CompiledAnswer(
            kpath.admit_plan, kpath.emit_plan, kpath.publish_plan, self.state, self.estop_at,
            self.lock, put, inbox, fallback, wake, self.before,
        )  # fmt: skip

    def answer(self, raw: bytes) -> int:
        """The ddm's usual step for one record (see the module's text):
        NOT_TAKEN, ANSWERED or REPLY_OWED (taken; the ddm's step sends the reply)."""
        if not self.lock.acquire(blocking=False):
            return NOT_TAKEN
        try:
            d = self.ddm
            kpath = d.kernel_path
            if not self.on or d.lost or d.estop_flag[0]:
                return NOT_TAKEN
            esc = d.kind == "esc"
            if esc and not d.commanded:
                return NOT_TAKEN
            assert kpath is not None
            if kpath.admit_call(kpath.admit_plan, raw) < 0:
                return NOT_TAKEN
            d.dirty = True
            self.taken_here += 1
            if not esc:
                d._publish()
                return ANSWERED
            return self._reply()
        finally:
            self.lock.release()

    def _reply(self) -> int:
        """An ESC's reply: the newest feedback, emitted and sent back."""
        d = self.ddm
        kpath = d.kernel_path
        assert kpath is not None
        d.steps += 1
        mask = kpath.emit_call(kpath.emit_plan)
        if mask < 0:  # a torn read of the feedback: the ddm reads it again
            self.owed = True
            return REPLY_OWED
        if mask:
            d.sends += 1
            try:
                d.transport.send(bytes(kpath.wire_views[0]), d.answer_gid)
            except TransportError:
                return REPLY_OWED  # (closed: the ddm's receive says so)
        if not d.steps & 63:
            d._publish()
        return ANSWERED

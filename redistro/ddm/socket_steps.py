"""A ddm's steps over stream sockets in kernel calls: the records sent by
``ddm_send`` on each robot's socket, and an ESC's usual step (the command
received and admitted, the new feedback emitted and sent back as the reply)
in one ``ddm_reply`` call. What a call does not take whole goes to the
ddm's general path."""

from __future__ import annotations

import errno
from typing import TYPE_CHECKING, Any

from redistro.ddm.transport import Accelerator

if TYPE_CHECKING:
    from redistro.ddm.kernel_path import KernelPath
    from redistro.ddm.worker import Ddm

REPLIED = 1 << 40  # ddm_reply: the usual step done whole
NOTHING = -errno.EAGAIN  # ... nothing had come


class SocketSteps:
    """One ddm's kernel calls on its transport's sockets. (An ESC's usual
    step is the hot path: its call is bound once, with its plans and the
    receive buffer, and the object keeps its few fields in slots.)"""

    __slots__ = ("admit", "d", "emit", "generation", "kernel", "reply_fd", "rx", "send_plan")

    def __init__(self, ddm: Ddm) -> None:
        self.d = ddm
        self.generation = -1  # the transport's peers the send fds are for
        # (bind: ddm_reply, its plans and the receive buffer; the
        # accelerator's reply_fd)
        self.kernel: Any = None
        self.admit: Any = None
        self.emit: Any = None
        self.send_plan: Any = None
        self.rx: Any = None
        self.reply_fd: Any = None

    def bind(self, kpath: KernelPath, accel: Accelerator) -> None:
        """ddm_reply, its plans (made once) and the socket's receive buffer,
        for :meth:`reply`."""
        self.reply_fd = accel.reply_fd
        self.kernel = kpath.reply_call
        self.admit, self.emit, self.send_plan = kpath.admit_plan, kpath.emit_plan, kpath.send_plan
        self.rx = accel.rx

    def reply(self) -> bool:
        """An ESC's usual step in one kernel call. True when that was the
        whole step: nothing came, or whole records, every one admitted (the
        exchange counted, the starving index paid back, the latency taken by
        the kernel). Else the general path takes the step on, with what the
        call received."""
        # (each callable read into a local first: called straight from its
        # slot, the interpreter looks it up as a method, the slow way; and
        # ddm_reply called with its arguments, not through a partial)
        reply_fd = self.reply_fd
        fd = reply_fd(self.d.ready_fds)
        if fd < 0:
            return False
        kernel = self.kernel
        got = kernel(self.admit, self.emit, self.send_plan, self.rx, fd)
        if got == REPLIED:
            self.d.dirty = True
            return True
        if got == NOTHING:
            return True
        return self._replied(got)

    def _replied(self, got: int) -> bool:
        """What ddm_reply did not take whole: the reply's trouble (a torn
        read of the feedback, a send not made whole), or a receive the
        general path takes on."""
        d = self.d
        kpath = d.kernel_path
        assert kpath is not None
        if not d.accel.received(got):
            return False
        d.dirty = True
        if kpath.reply["trouble"]:
            d.accel.send_result(d.gid[d.robots[0]], int(kpath.send_status[0]))
        elif kpath.reply["emitted"] == -1:  # a torn read of the feedback: read it again
            d._send(False)
        return True

    def refresh_fds(self) -> None:
        """Each robot's socket for the send kernels (a peer came or went)."""
        d = self.d
        kpath = d.kernel_path
        assert kpath is not None
        self.generation = d.accel.generation
        for i, robot in enumerate(d.gid[r] for r in d.robots):
            kpath.send_fds[i] = d.accel.send_fd(robot)

    def send(self, mask: int) -> None:
        """The records emitted (mask) sent on their sockets by ddm_send, the
        robots in turn; what it could not send whole goes to the transport."""
        d = self.d
        kpath = d.kernel_path
        assert kpath is not None
        if d.accel.generation != self.generation:  # a peer came or went
            self.refresh_fds()
        trouble = kpath.send_call(kpath.send_plan, mask, d.sends & 1)
        if not trouble:
            return
        for i, robot in d.send_orders[0]:
            if trouble >> i & 1:
                result = int(kpath.send_status[i])
                if result == 0:  # no socket: the transport's own send counts it
                    d.transport.send(bytes(kpath.wire_views[i]), robot)
                else:
                    d.accel.send_result(robot, result)

"""The lockstep bell: a node's word to the plant that a tick's work moved on.

In lockstep the plant waits, phase by phase, for the nodes' cycles and
records (``plant/lockstep.py``). It sleeps on one named POSIX semaphore of
the session, the bell, and the nodes post it where a phase may have ended:
the last stage of a node's cycle once it signed, a ddm once it admitted
records. Each post is a hint, never the verdict: the plant looks at Local
Data again, and a wait with no post still looks every ``LOOK_S``.

Cost per cycle, in lockstep only: one ``sem_post`` in each last-stage
worker, one in a ddm per step that admitted records (about 1 µs each),
and a plant that sleeps until then instead of looking every 20 µs.
"""

from __future__ import annotations

import posix_ipc

from redistro.ipc import names
from redistro.ipc.sem import Semaphore
from redistro.ipc.session import Manifest

# the longest the plant sleeps on the bell before it looks anyway (a phase
# that no node rings for: a log draining, a node that left the group)
LOOK_S = 0.002


def bell_name(session_id: str) -> str:
    return names.object_name(session_id, "plant", "bell")


def create(session_id: str) -> Semaphore:
    """The plant's bell, in the session's manifest (the plant unlinks it)."""
    return Semaphore.create(bell_name(session_id), Manifest.for_session(session_id))


class Ringer:
    """A node's side: :meth:`ring` posts the bell. It is opened at the first
    ring (the plant made it before any node could ring: a node rings only
    in the tick the plant gave it, or on a record such a tick produced);
    while none exists a ring does nothing."""

    __slots__ = ("name", "sem")

    def __init__(self, session_id: str) -> None:
        self.name = bell_name(session_id)
        self.sem: posix_ipc.Semaphore | None = None

    def ring(self) -> None:
        sem = self.sem
        if sem is None:
            try:
                sem = self.sem = posix_ipc.Semaphore(self.name)
            except posix_ipc.ExistentialError:
                return
        sem.release()

    def close(self) -> None:
        if self.sem is not None:
            self.sem.close()
            self.sem = None

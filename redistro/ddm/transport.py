"""The DDM transport interface: move whole wire records between nodes.

Every call is non-blocking (a ddm waits on the transport's ``fds()`` for
records to come): ``send`` queues one record for the peer that
handles ``robot`` (the SSC's ddm talks to one ESC per robot; an ESC's ddm to
the SSC); ``receive`` returns the records that have arrived since the last
call (whole records, not yet validated: the DDM decodes and admits them). A
lost link raises :class:`~redistro.errors.TransportError`. Transports are
chosen by ``ddm.transport`` and imported only when used.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Collection
from typing import TYPE_CHECKING, Any

from redistro.registries import load

if TYPE_CHECKING:
    from redistro.config import Config


# what an answer (``Transport.answer_with``) did with a record
NOT_TAKEN, ANSWERED, REPLY_OWED = 0, 1, 2


class Links:
    """What a transport's links do beside carrying records. These defaults
    are a medium without connections (every record goes out; nothing is
    lost alone, stored or held back); a transport with connections, a card
    or a status channel gives its own (``Transport.links``)."""

    status_every = 0  # ddm steps between two status reports (0: never asked)

    def can_send(self, robot: int) -> bool:
        """Whether a record for ``robot`` would go out now (a connecting
        side: its link is made)."""
        return True

    def lost_links(self) -> dict[int, str]:
        """Robots whose own link was lost while the others' still work
        (robot -> why); a transport without per-robot links has none."""
        return {}

    def authenticated(self, robot: int | None = None) -> None:
        """The records just received (from ``robot``'s link, on a connecting
        side) were signed with this run's key: their connection is the
        peer's, and no new connection displaces it."""

    def drop_unauthenticated(self) -> None:
        """A record just received was not signed with the link's key: drop
        its connection unless it has authenticated before."""

    def refused(self) -> int:
        """Connections refused so far (the link already had its peer)."""
        return 0

    def verify_with(self, check: Callable[[bytes], bool]) -> bool:
        """A transport that stores what it receives (reflective memory's
        card): ``check(record)`` says whether a record is authentic before
        it is stored. False: this transport stores nothing."""
        return False

    def flush(self) -> None:
        """Send what ``send`` held back (a transport that carries a step's
        records together: reflective memory); the ddm calls it after each
        step's sends."""

    def status(self, doc: dict[str, object]) -> None:
        """Publish the node's status (a small JSON document) where viewers
        (``redistro top --zenoh``) see it."""


NO_LINKS = Links()


class Accelerator:
    """A transport's offer to the ddm's compiled path (``Transport.accelerator``;
    None: the ddm hands records over one by one). Stream sockets let the
    kernels make the system calls (``admit_with``, ``send_fd``,
    ``reply_fd``); a transport whose records arrive on a thread of its own
    lets the ddm answer there (``answer_with``)."""

    taken = 0  # records the last receive handed to the admitting kernel, admitted

    @property
    def generation(self) -> int:
        """Changes whenever a robot's peer (and so its send_fd) changes."""
        return 0

    @property
    def rx(self) -> Any:
        """The receive buffer of reply_fd's socket."""
        return None

    def admit_with(self, call: Any, plan: Any, state: Any) -> bool:
        """Hand each whole record, as it arrives, to ``call(plan, rx, fd)``
        (the ``ddm_recv`` kernel: one recv and the records' admission; the
        admitted ones are not returned by ``receive``, ``taken`` counts
        them). False: this transport cannot."""
        return False

    def send_fd(self, robot: int) -> int:
        """The stream socket a record for ``robot`` is sent on (-1: none)."""
        return -1

    def send_result(self, robot: int, result: int) -> None:
        """What a send on ``send_fd(robot)`` made elsewhere returned (the
        bytes sent or -errno), counted or raised as ``send`` would."""

    def reply_fd(self, ready: Collection[int] | None) -> int:
        """A replying side (an ESC) on a stream socket: the peer's socket
        when this receive is the usual one, which the ddm may make in one
        kernel call with its reply (``ddm_reply``, into ``rx``); else -1."""
        return -1

    def received(self, got: int) -> bool:
        """What that call's recv returned: True when the receive is done
        with; False: the next ``receive`` takes it on as its own."""
        return False

    def answer_with(
        self,
        answer: Callable[[bytes], int],
        compiled: Callable[[Any, Any, Any, Any], Callable[[Any], None]] | None = None,
    ) -> bool:
        """Records that arrive on a thread of the transport's own (zenoh's):
        hand each there, as it arrives, to ``answer(raw)``, which makes the
        ddm's usual step for it whole without waking the ddm (admitted; an
        ESC's reply sent back). It returns ``NOT_TAKEN`` (the record is
        queued for the ddm's ``receive`` as usual, and wakes it),
        ``ANSWERED``, or ``REPLY_OWED`` (taken; the ddm is woken for the rest of
        its step). While records wait in the queue, the later ones queue
        behind them. ``compiled``: the same answer in one compiled call,
        made for the transport by ``compiled(put, inbox, fallback, wake)``
        (``put(reply)`` sends an ESC's reply to the record's sender, None
        on the SSC's side; ``fallback(raw)``, the transport's own path for
        a record it does not take; ``wake()`` wakes the ddm), which the
        transport may hand each record or sample to instead. False: this
        transport cannot."""
        return False


NO_ACCELERATOR = Accelerator()  # (what a ddm uses for a transport without one)


class Transport(ABC):
    """What every transport does: send, receive, its fds, close. What some
    do beside is in ``links`` (connections, a card, a status channel) and
    ``accelerator`` (the ddm's compiled path), as python-can's bus keeps
    its required surface small."""

    # the receiving side answers each record it gets with its own (the paper's
    # send/receive/reply): an ESC's ddm then sends its feedback as the reply
    # to each command, not on its own
    replies = False
    # a memory, not a stream (reflective memory): a receive hands over the
    # latest record of each slot written since the last
    latest_only = False
    # a stream that drops records rather than block when its link is
    # congested (zenoh's publishers, congestion control DROP): what arrives
    # is in order, the starving index sees what does not
    drops_when_congested = False
    links: Links = NO_LINKS
    accelerator: Accelerator | None = None

    @abstractmethod
    def send(self, record: bytes, robot: int) -> None: ...

    @abstractmethod
    def receive(self, ready: Collection[int] | None = None) -> list[bytes]:
        """ready: the fds (of ``fds()``) the ddm's poll found readable; a
        transport may skip the others (nothing waits there: the poll is
        level-triggered). None: look everywhere."""

    @abstractmethod
    def close(self) -> None: ...

    def fds(self) -> list[int]:
        """File descriptors that become readable when records arrive (or a
        link breaks): what a ddm waits on, beside its wake event."""
        return []

    @classmethod
    def for_node(
        cls,
        cfg: Config,
        session_id: str,
        link: str,
        node: str,
        kind: str,
        robots: list[str],
        key: bytes,
    ) -> Transport:
        """This transport set up for one node's side from the config:
        session_id names the node's own objects; link derives where the
        nodes of one group meet; kind (esc, ssc) and robots say which side;
        key signs what the transport itself sends (a connecting side's
        hello)."""
        raise NotImplementedError(f"{cls.__name__} cannot be set up from the config")

    def __enter__(self) -> Transport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


TRANSPORTS: dict[str, str] = {
    "socket": "redistro.ddm.sockets:SocketTransport",
    "reflective": "redistro.ddm.reflective:ReflectiveTransport",
    "zenoh": "redistro.ddm.zenoh_transport:ZenohTransport",
}


def transport_class(key: str) -> type[Transport]:
    cls: type[Transport] = load(TRANSPORTS, key, "transport")
    return cls

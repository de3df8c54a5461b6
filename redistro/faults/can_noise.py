"""Corrupt frames on the CAN backplane's bus, sent by an outsider (the harness)."""

from __future__ import annotations

import random
import time

from redistro.config.model import Config
from redistro.drivers.io.can import FRAME, READ, REPLY, WRITE, _message, open_bus


def send_noise(cfg: Config, session_id: str, seconds: float, rate_hz: float = 2000.0) -> int:
    """Frames with the identifiers of real traffic (writes to the boards,
    replies from them) and corrupt contents, for ``seconds``; how many went out."""
    c = cfg.plant.can
    bus = open_bus(c.interface, c.channel, c.port, session_id)
    rng = random.Random(7)
    from redistro.config.hardware import load_hardware

    addresses = sorted(
        {b.address for hw in load_hardware(cfg).values() for b in hw.io.boards.values()}
    )
    sent = 0
    try:
        end = time.monotonic() + seconds
        period = 1.0 / rate_hz
        nxt = time.monotonic()
        while time.monotonic() < end:
            kind = rng.choice((WRITE, REPLY, READ))
            data = bytearray(rng.randbytes(FRAME))
            bus.send(_message(kind | rng.choice(addresses), bytes(data)))
            sent += 1
            nxt += period
            delay = nxt - time.monotonic()
            if delay > 0:
                time.sleep(delay)  # pacing the noise, not synchronizing
    finally:
        bus.shutdown()
    return sent

"""Corrupt frames on the CAN backplane's bus, sent by an outsider (the harness)."""

from __future__ import annotations

import dataclasses
import os
import random
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from redistro.config.model import Config
from redistro.drivers.io.can import FRAME, REPLY, WRITE, _message, open_bus


def send_noise(
    cfg: Config, session_id: str, seconds: float, rate_hz: float = 2000.0, forged: bool = False
) -> int:
    """Frames with the identifiers of real traffic (writes to the boards,
    replies from them) and corrupt contents, for ``seconds``; how many went
    out. forged: well-formed writes instead (full-scale DAC codes, every
    brake released), signed with a key that is not the plant's."""
    c = cfg.plant.can
    bus = open_bus(c.interface, c.channel, c.port, session_id, c.loopback_only)
    rng = random.Random(7)
    from redistro.config.hardware import load_hardware

    types = {b.address: b.type for hw in load_hardware(cfg).values() for b in hw.io.boards.values()}
    addresses = sorted(types)
    sent = 0
    try:
        end = time.monotonic() + seconds
        period = 1.0 / rate_hz
        nxt = time.monotonic()
        while time.monotonic() < end:
            if forged:
                sent += _forged_write(bus, types, rng.choice(addresses), sent)
            else:
                kind = rng.choice((WRITE, REPLY))
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


def _forged_write(bus: Any, types: Mapping[int, str], address: int, seq: int) -> int:
    """One well-formed write to ``address`` (every output at full scale), its
    tag made with a key that is not the plant's; the frames sent."""
    import numpy as np

    from redistro.drivers.io.can import frames_for, write_tag
    from redistro.drivers.io.registers import BANKS, BoardType

    kind = {"dac": BoardType.DAC, "dio": BoardType.DIO}.get(types.get(address, ""))
    if kind is None:
        return 0
    out = np.zeros((), BANKS[kind][1])
    raw = out.reshape(1).view(np.uint8)
    raw[:] = 0xFF if kind == BoardType.DIO else 0
    if kind == BoardType.DAC:
        out["code"][:] = 2047
    bank = out.tobytes()
    n = 0
    for frame in frames_for(seq, bank + write_tag(b"not the plant's key" * 2, address, seq, bank)):
        bus.send(_message(WRITE | address, frame))
        n += 1
    return n


def run_can_noise(out_dir: Path, cfg: Config, forged: bool = False) -> dict[str, Any]:
    """The plant on the CAN backplane, r2's robot-level driver reading it at
    200 Hz (holding its DAC at zero, the brakes on) for 3 s, corrupt frames on
    the bus for the middle second. Whole robot-group sessions over CAN do not
    fit two vCPUs (the plant runs at ~0.07 of real time), so the bus is driven
    by one driver, as the I/O integration tests do.

    Passed when every read came back (no I/O fault), every position agreed with
    the simulation's truth within 2 counts (nothing corrupt was taken), and
    the bad frames were counted."""
    import threading

    import numpy as np

    from redistro.config.hardware import load_hardware
    from redistro.drivers.io.backplane import open_backplane
    from redistro.drivers.robot import RobotDriver
    from redistro.errors import IOFault
    from redistro.ipc.session import Session
    from redistro.plant.launch import PlantProcess

    cfg = dataclasses.replace(cfg, plant=dataclasses.replace(cfg.plant, backplane="can"))
    hw = load_hardware(cfg)["r2"]
    row: dict[str, Any] = {}
    reads = worst = 0
    worst_counts = 0.0
    fault = ""
    with Session.create() as session:
        plant = PlantProcess.start(session, out_dir / "run", cfg)
        sid = session.id
        try:
            assert plant.bank is not None
            bp = open_backplane(cfg.plant, sid)  # plant.backplane=can above
            d = RobotDriver(hw, bp, cfg.plant.physics_hz)
            d.open()
            truth = plant.bank.truth(plant.bank.robot_names.index("r2"))
            d.preset_encoders(truth.read()["q_rad"])
            q_start = np.array(truth.read()["q_rad"], dtype=np.float64)
            sent: list[int] = []
            noise = threading.Thread(
                target=lambda: sent.append(send_noise(cfg, sid, 1.0, forged=forged))
            )
            t0 = time.monotonic()
            nxt = t0
            try:
                while time.monotonic() - t0 < 3.0:
                    if not noise.is_alive() and not sent and time.monotonic() - t0 > 1.0:
                        noise.start()
                    fb = d.read_feedback()
                    d.send_torques(np.zeros(7))  # the amplifiers' watchdog
                    tr = truth.read()
                    if int(tr["step"]) == fb.step:  # the same sample: they must agree
                        err = float(np.max(np.abs(fb.q_rad - tr["q_rad"]) * d.counts_per_rad))
                        worst_counts = max(worst_counts, err)
                        worst += 1
                    reads += 1
                    nxt += 0.005
                    time.sleep(max(0.0, nxt - time.monotonic()))  # a 200 Hz loop
            except IOFault as exc:
                fault = str(exc)
            noise.join()
            row["controller_bad_frames"] = int(getattr(bp, "bad_frames", 0))
            moved = np.abs(np.asarray(truth.read()["q_rad"], dtype=np.float64) - q_start)
            row["moved_rad"] = round(float(moved.max()), 5)
            d.freeze()
            d.close()
        finally:
            plant.stop()
        result = plant.result()
    row["frames_sent"] = sent[0] if sent else 0
    row["reads"] = reads
    row["compared"] = worst
    row["worst_position_error_counts"] = round(worst_counts, 2)
    row["plant_bad_frames"] = int(result.get("bad_frames", 0))
    row["plant_forged_writes"] = int(result.get("forged_writes", 0))
    row["count"] = {"bad_frames": row["plant_bad_frames"] + row["controller_bad_frames"]}
    if forged:
        row["count"] = {"forged_writes": row["plant_forged_writes"]}
    row["got"] = "abnormal" if fault else "ok"
    row["cause"] = fault
    row["processes_left"] = 0
    row["ipc_left"] = sorted(e for e in os.listdir("/dev/shm") if sid in e)
    row["passed"] = bool(
        not fault
        and reads > 300
        and worst > 0
        and worst_counts <= 2
        and next(iter(row["count"].values())) > 0
        and (not forged or row.get("moved_rad", 1.0) < 0.002)  # braked, DAC at 0: held
        and not row["ipc_left"]
    )
    return row

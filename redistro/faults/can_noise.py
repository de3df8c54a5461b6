"""Frames on the CAN backplane's bus sent by an outsider (the harness):
corrupt ones, writes signed with another key, and genuine writes captured
and sent again much later."""

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

    from redistro.drivers.io.can import frames_for, signed, write_tag
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
    seq = time.monotonic_ns()  # as fresh as the driver's: only the key is wrong
    tag = write_tag(b"not the plant's key" * 2, address, seq, bank)
    for frame in frames_for(seq, signed(seq, bank, tag)):
        bus.send(_message(WRITE | address, frame))
        n += 1
    return n


def _listen(cfg: Config, session_id: str, seconds: float, into: list[Any]) -> None:
    """The writes seen on the bus for ``seconds`` (an eavesdropper on loopback)."""
    c = cfg.plant.can
    bus = open_bus(c.interface, c.channel, c.port, session_id, c.loopback_only)
    try:
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            msg = bus.recv(timeout=left)
            if msg is not None and msg.arbitration_id & 0x700 == WRITE:
                into.append(msg)
    finally:
        bus.shutdown()


def _replay(cfg: Config, session_id: str, frames: list[Any], seconds: float) -> int:
    """The captured frames sent again at the pace they were recorded, the
    recording over and over, for ``seconds``; the writes replayed (banks)."""
    c = cfg.plant.can
    bus = open_bus(c.interface, c.channel, c.port, session_id, c.loopback_only)
    writes = 0
    try:
        end = time.monotonic() + seconds
        first = frames[0].timestamp
        while time.monotonic() < end:
            t0 = time.monotonic()
            for msg in frames:
                delay = t0 + (msg.timestamp - first) - time.monotonic()
                if delay > 0:
                    time.sleep(delay)  # the recording's own pace
                bus.send(msg)
                if msg.data[2] == msg.data[3] - 1:  # a bank's last segment
                    writes += 1
                if time.monotonic() >= end:
                    break
    finally:
        bus.shutdown()
    return writes


def _ended(row: dict[str, Any], fault: str, sid: str) -> None:
    """How the driver's run ended (an I/O fault or not), what it left."""
    row["got"] = "abnormal" if fault else "ok"
    row["cause"] = fault
    row["processes_left"] = 0
    row["ipc_left"] = sorted(e for e in os.listdir("/dev/shm") if sid in e)


class _CanRig:
    """The plant on the CAN backplane and r2's robot-level driver open on
    it (its encoders preset from the simulation's truth), for one drill:
    ``with _CanRig(out_dir, cfg) as rig: ...``; the plant's result after.
    No node runs: the plant steps on the wall clock, whatever the clock
    of the campaign's sessions."""

    def __init__(self, out_dir: Path, cfg: Config) -> None:
        self.out_dir = out_dir
        self.cfg = dataclasses.replace(
            cfg,
            plant=dataclasses.replace(cfg.plant, backplane="can"),
            session=dataclasses.replace(cfg.session, clock="realtime"),
        )
        self.result: dict[str, Any] = {}

    def __enter__(self) -> _CanRig:
        from redistro.config.hardware import load_hardware
        from redistro.drivers.io.backplane import open_backplane
        from redistro.drivers.robot import RobotDriver
        from redistro.ipc.session import Session
        from redistro.plant.launch import PlantProcess

        cfg = self.cfg
        self.session = Session.create()
        self.session.__enter__()
        self.sid = self.session.id
        self.plant = PlantProcess.start(self.session, self.out_dir / "run", cfg)
        try:
            assert self.plant.bank is not None
            self.bp = open_backplane(cfg.plant, self.sid)
            self.d = RobotDriver(load_hardware(cfg)["r2"], self.bp, cfg.plant.physics_hz)
            self.d.open()
            self.truth = self.plant.bank.truth(self.plant.bank.robot_names.index("r2"))
            self.d.preset_encoders(self.truth.read()["q_rad"])
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.plant.stop()
            self.result = self.plant.result()
        finally:
            self.session.__exit__(None, None, None)


def run_can_noise(out_dir: Path, cfg: Config, forged: bool = False) -> dict[str, Any]:
    """The plant on the CAN backplane, r2's robot-level driver reading it at
    200 Hz (holding its DAC at zero, the brakes on) for 3 s, corrupt frames on
    the bus for the middle second. Whole robot-group sessions over CAN do not
    fit two vCPUs (the plant runs at ~0.07 of real time), so the bus is driven
    by one driver, as the I/O integration tests do.

    Passed when every read came back (no I/O fault), every position agreed with
    the simulation's truth within 2 counts (nothing corrupt was taken), and
    the bad frames were counted."""
    import numpy as np

    row: dict[str, Any] = {}
    with _CanRig(out_dir, cfg) as rig:
        q_start = np.array(rig.truth.read()["q_rad"], dtype=np.float64)
        fault, reads, worst, worst_counts, sent = _read_through_noise(rig, forged)
        row["controller_bad_frames"] = int(getattr(rig.bp, "bad_frames", 0))
        moved = np.abs(np.asarray(rig.truth.read()["q_rad"], dtype=np.float64) - q_start)
        row["moved_rad"] = round(float(moved.max()), 5)
        rig.d.freeze()
        rig.d.close()
    result = rig.result
    row["frames_sent"] = sent
    row["reads"] = reads
    row["compared"] = worst
    row["worst_position_error_counts"] = round(worst_counts, 2)
    row["plant_bad_frames"] = int(result.get("bad_frames", 0))
    row["plant_forged_writes"] = int(result.get("forged_writes", 0))
    row["count"] = {"bad_frames": row["plant_bad_frames"] + row["controller_bad_frames"]}
    if forged:
        row["count"] = {"forged_writes": row["plant_forged_writes"]}
    _ended(row, fault, rig.sid)
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


def _read_through_noise(rig: _CanRig, forged: bool) -> tuple[str, int, int, float, int]:
    """The driver's 200 Hz loop for 3 s, the noise on the bus in the middle
    second: (the I/O fault, reads, reads compared with the truth, the worst
    position error [counts], frames of noise sent)."""
    import threading

    import numpy as np

    from redistro.errors import IOFault

    d, truth = rig.d, rig.truth
    reads = compared = 0
    worst = 0.0
    sent: list[int] = []
    noise = threading.Thread(
        target=lambda: sent.append(send_noise(rig.cfg, rig.sid, 1.0, forged=forged))
    )
    fault = ""
    t0 = nxt = time.monotonic()
    try:
        while time.monotonic() - t0 < 3.0:
            if not noise.is_alive() and not sent and time.monotonic() - t0 > 1.0:
                noise.start()
            fb = d.read_feedback()
            d.send_torques(np.zeros(7))  # the amplifiers' watchdog
            tr = truth.read()
            if int(tr["step"]) == fb.step:  # the same sample: they must agree
                err = float(np.max(np.abs(fb.q_rad - tr["q_rad"]) * d.counts_per_rad))
                worst = max(worst, err)
                compared += 1
            reads += 1
            nxt += 0.005
            time.sleep(max(0.0, nxt - time.monotonic()))  # a 200 Hz loop
    except IOFault as exc:
        fault = str(exc)
    if noise.is_alive() or sent:
        noise.join()
    return fault, reads, compared, worst, sent[0] if sent else 0


def run_can_replay(out_dir: Path, cfg: Config) -> dict[str, Any]:
    """The plant on the CAN backplane and r2's driver at 200 Hz. For its
    first 0.3 s the driver releases joint 1's brake and drives it with
    4 N m while an eavesdropper records every write on the bus; then it
    holds (brakes on, DAC at zero). Its sequence number is then moved on
    by 70 000 writes (the minutes of running after which a 16-bit number
    has wrapped), and for 1 s the recording is sent again and again, at
    its own pace, beside the driver's writes.

    Passed when no replayed write reached a register (the plant took no
    more writes than the driver made; the replayed ones counted forged),
    joint 1 did not move while they came, the amplifiers' watchdog never
    tripped (the genuine writes were taken all along) and no read failed."""
    row: dict[str, Any] = {}
    with _CanRig(out_dir, cfg) as rig:
        fault, captured, replayed, moved = _drive_and_replay(rig)
        row["captured_frames"] = captured
        row["replayed_writes"] = replayed
        row["moved_while_replayed_rad"] = round(moved, 5)
        rig.d.freeze()
        rig.d.close()
        row["driver_writes"] = int(rig.bp.writes)  # type: ignore[attr-defined]
    result = rig.result
    row["plant_forged_writes"] = int(result.get("forged_writes", 0))
    row["plant_taken_writes"] = int(result.get("taken_writes", 0))
    row["watchdog_trips"] = [t.get("robot") for t in result.get("watchdog_trips") or []]
    row["count"] = {"forged_writes": row["plant_forged_writes"]}
    _ended(row, fault, rig.sid)
    row["passed"] = bool(
        not fault
        and row["captured_frames"] > 0
        and row["replayed_writes"] > 0
        # every replayed write refused: none taken beyond the driver's own
        # (loopback UDP may lose a datagram: then a write is neither taken
        # nor counted)
        and row["plant_taken_writes"] <= row.get("driver_writes", 0)
        and row["plant_forged_writes"] >= 0.9 * row["replayed_writes"]
        and row["moved_while_replayed_rad"] < 0.002
        and not row["watchdog_trips"]
        and not row["ipc_left"]
    )
    return row


def _drive_and_replay(rig: _CanRig) -> tuple[str, int, int, float]:
    """The driver's 200 Hz loop for 2.5 s: joint 1 driven for 0.3 s while
    recorded, then held; from 0.8 s the recording replayed. (the I/O fault,
    frames captured, writes replayed, joint 1's move while replayed [rad])."""
    import threading

    import numpy as np

    from redistro.errors import IOFault

    d, truth, cfg, sid = rig.d, rig.truth, rig.cfg, rig.sid
    captured: list[Any] = []
    spy = threading.Thread(target=_listen, args=(cfg, sid, 0.3, captured))
    replayed: list[int] = []
    drive = np.zeros(7)
    drive[0] = 4.0
    fault = ""
    q_hold = q_end = None
    try:
        spy.start()
        time.sleep(0.05)  # the eavesdropper joins the group (pacing, not a sync)
        t0 = nxt = time.monotonic()
        replay: threading.Thread | None = None
        while time.monotonic() - t0 < 2.5:
            d.read_feedback()
            t = time.monotonic() - t0
            if t < 0.3:
                d.release_brakes([0])
                d.send_torques(drive)
            else:
                d.freeze()
            if replay is None and t >= 0.8:
                spy.join()
                _whole_banks(captured)
                rig.bp._seq += 70_000  # type: ignore[attr-defined]  # minutes of running
                q_hold = float(truth.read()["q_rad"][0])
                replay = threading.Thread(
                    target=lambda: replayed.append(_replay(cfg, sid, captured, 1.0))
                )
                replay.start()
            if replay is not None and not replay.is_alive() and q_end is None:
                q_end = float(truth.read()["q_rad"][0])
            nxt += 0.005
            time.sleep(max(0.0, nxt - time.monotonic()))  # a 200 Hz loop
        if replay is not None:
            replay.join()
    except IOFault as exc:
        fault = str(exc)
    moved = abs((q_end if q_end is not None else float(truth.read()["q_rad"][0]))
                - (q_hold if q_hold is not None else 0.0))  # fmt: skip
    return fault, len(captured), replayed[0] if replayed else 0, moved


def _whole_banks(captured: list[Any]) -> None:
    """Whole banks only: from a first segment to a last one."""
    while captured and captured[0].data[2] != 0:
        captured.pop(0)
    while captured and captured[-1].data[2] != captured[-1].data[3] - 1:
        captured.pop()

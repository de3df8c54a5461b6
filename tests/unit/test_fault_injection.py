"""The harness's injection points and the faulty DDM transport (no processes)."""

from __future__ import annotations

import time
from collections.abc import Collection
from pathlib import Path

import pytest

from redistro.ddm import record as wire
from redistro.ddm.transport import Transport
from redistro.errors import TransportError, WireError
from redistro.faults import inject
from redistro.faults.wire import REPLAY_BACK, InjectedTransport


class Loop(Transport):
    """A transport that hands back what was sent (the contract's simplest peer)."""

    def __init__(self) -> None:
        self.queue: list[bytes] = []
        self.closed = False

    def send(self, record: bytes, robot: int) -> None:
        self.queue.append(record)

    def receive(self, ready: Collection[int] | None = None) -> list[bytes]:
        out, self.queue = self.queue, []
        return out

    def close(self) -> None:
        self.closed = True


def _record(seq: int) -> bytes:
    return wire.encode(wire.KIND_COMMAND, 1, "ssc", seq, time.monotonic_ns() + seq, bytes(
        wire.PAYLOADS[wire.KIND_COMMAND].itemsize))  # fmt: skip


def _armed(tmp_path: Path, point: str, arg: float = 0.0) -> inject.Injection:
    trigger = tmp_path / f"trigger-{point}"
    inj = inject.Injection(point=point, robot="r2", trigger=str(trigger), arg=arg)
    assert not inj.live()  # no trigger yet
    trigger.touch()
    inj._next_ns = 0  # look again now (it looks at most every 2 ms)
    assert inj.live()
    return inj


def test_an_injection_is_armed_through_the_environment(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert inject.injection("plant.") is None  # nothing armed: nothing to pay
    trigger = tmp_path / "t"
    env = inject.arm("plant.encoder-jump", str(trigger), robot="r2", arg=5.0)
    monkeypatch.setenv(inject.ENV, env)
    assert inject.injection("ddm.drop") is None
    inj = inject.injection("plant.")
    assert inj is not None and inj.point == "plant.encoder-jump" and inj.arg == 5.0
    assert inj.concerns("r2") and not inj.concerns("r1")
    assert not inj.live()
    trigger.touch()
    inj._next_ns = 0
    assert inj.live() and inj.fired_ns > 0
    assert Path(f"{trigger}.fired").exists()  # when it fired, for the latencies


def test_malformed_copies_are_refused_and_the_genuine_records_pass(tmp_path: Path) -> None:
    inner = Loop()
    t = InjectedTransport(inner, _armed(tmp_path, "ddm.malformed", 3), {1: "r2"})
    for seq in range(1, 6):
        t.send(_record(seq), 1)
    got = inner.receive()
    assert len(got) == 8  # 3 corrupt copies + 5 genuine records
    refused = 0
    for raw in got:
        try:
            wire.decode(raw)
        except WireError:
            refused += 1
    assert refused == 3


def test_replayed_records_are_dropped_by_admission(tmp_path: Path) -> None:
    inner = Loop()
    inj = inject.Injection(point="ddm.replay", trigger=str(tmp_path / "t"), arg=5)
    t = InjectedTransport(inner, inj, {1: "r2"})
    seq = 0
    for _ in range(REPLAY_BACK):  # history before the trigger
        seq += 1
        t.send(_record(seq), 1)
    (tmp_path / "t").touch()
    inj._next_ns = 0
    for _ in range(10):
        seq += 1
        t.send(_record(seq), 1)
    admission = wire.Admission()
    accepted = sum(admission.admit(wire.decode(raw)) for raw in inner.receive())
    assert accepted == seq  # every genuine record, once
    assert admission.dropped["out_of_order"] == 5


def test_drop_delay_and_close(tmp_path: Path) -> None:
    inner = Loop()
    t = InjectedTransport(inner, _armed(tmp_path, "ddm.drop"), {1: "r2"})
    t.send(_record(1), 1)
    assert inner.receive() == []

    inner = Loop()
    t = InjectedTransport(inner, _armed(tmp_path, "ddm.delay", 0.05), {1: "r2"})
    t.send(_record(1), 1)
    assert inner.queue == []
    deadline = time.monotonic() + 2.0
    came: list[bytes] = []
    while not came and time.monotonic() < deadline:
        came += t.receive()  # the delayed record leaves once due (the loop hands it back)
    assert len(came) == 1

    inner = Loop()
    t = InjectedTransport(inner, _armed(tmp_path, "ddm.link-close"), {1: "r2"})
    with pytest.raises(TransportError):
        t.send(_record(1), 1)
    assert inner.closed
    with pytest.raises(TransportError):
        t.receive()


def test_records_of_another_robot_are_left_alone(tmp_path: Path) -> None:
    inner = Loop()
    t = InjectedTransport(inner, _armed(tmp_path, "ddm.drop"), {0: "r1", 1: "r2"})
    t.send(_record(1), 0)
    assert len(inner.receive()) == 1


def test_the_harness_hooks_are_found_only_when_a_session_names_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from redistro.process import hooks

    monkeypatch.delenv(hooks.ENV, raising=False)
    assert hooks.factory("plant_disturbance") is None  # a normal run: nothing imported
    monkeypatch.setenv(hooks.ENV, "redistro.faults.hooks")
    make = hooks.factory("plant_disturbance")
    assert make is not None and make() is None  # named, but no point armed
    assert hooks.factory("no_such_hook") is None
    monkeypatch.setenv(inject.ENV, inject.arm("ddm.drop", str(tmp_path / "t"), node="ssc"))
    ddm = hooks.factory("ddm_hooks")
    assert ddm is not None
    assert ddm("esc.r1", "esc") is None  # armed for another node
    faults = ddm("ssc", "ssc")
    assert faults is not None and isinstance(faults.transport(Loop(), {1: "r2"}), InjectedTransport)
    monkeypatch.setenv(hooks.ENV, "redistro.no_such_module")
    with pytest.raises(ImportError):
        hooks.factory("plant_disturbance")


def test_the_plants_faults_act_through_the_chassis_points(tmp_path: Path) -> None:
    """The harness's plant faults on a real chassis and PyBullet world: a
    counter glitch once, a stuck switch while live, the receiver corrupted."""
    import numpy as np

    from redistro.config.hardware import load_hardware
    from redistro.config.loader import load_config
    from redistro.faults.hooks import PlantFaults
    from redistro.plant.chassis import HOME_AS_SWITCH, HOME_STUCK_ON, Chassis
    from redistro.plant.world import World

    root = Path(__file__).parents[2]
    cfg = load_config(root / "config" / "redistro.yaml")
    world = World(cfg)
    try:
        glitch = PlantFaults(_armed(tmp_path, "plant.encoder-jump", 700))
        chassis = Chassis(cfg, world, load_hardware(cfg), disturbance=glitch)
        r2 = [r.name for r in chassis.rigs].index("r2")
        before = chassis.rigs[r2].encoder_offset.copy()
        for _ in range(3):
            chassis.step()
        jumped = chassis.rigs[r2].encoder_offset - before
        assert jumped[1] == 700 and not jumped[[0, 2, 3, 4, 5, 6]].any()  # once, joint 1
        chassis.disturbance = PlantFaults(_armed(tmp_path, "plant.home-stuck-on"))
        chassis.step()
        assert (chassis._home_force[chassis.rigs[r2].sl] == HOME_STUCK_ON).all()
        assert (chassis._home_force[chassis.rigs[1 - r2].sl] == HOME_AS_SWITCH).all()
        chassis.disturbance = PlantFaults(_armed(tmp_path, "plant.sensor-nan"))
        chassis.step()
        assert np.isnan(chassis.reg.ft_calibration[chassis.rigs[r2].ft_row, 0, 0])
        assert (chassis._home_force == HOME_AS_SWITCH).all()  # the switch works again
    finally:
        world.close()


def test_detection_counts_from_the_cycle_the_fault_took_effect_in() -> None:
    """The trigger is read at the node's cycle 100 (tick due at t = 1 s);
    the armed point acts when its process next looks: 4.9 ms later is
    still cycle 100, 5.1 ms later cycle 101 (5 ms ticks); with no tick time
    known, the cycle read stands."""
    from redistro.faults.runner import cycle_at

    due = 1_000_000_000
    assert cycle_at(100, due, due + 4_900_000, 5.0) == 100
    assert cycle_at(100, due, due + 5_100_000, 5.0) == 101
    assert cycle_at(100, due, due + 12_000_000, 5.0) == 102
    assert cycle_at(100, 0, due + 12_000_000, 5.0) == 100
    assert cycle_at(100, due, due - 1, 5.0) == 100


def test_the_campaign_parks_arms_left_off_their_park_pose(tmp_path: Path) -> None:
    """A scenario starts with the arms parked: a calibration's sweep reaches
    the home switches only near the park pose, and a switch out of reach
    would pass home-stuck-off for the wrong reason."""
    import json

    from redistro.config.loader import load_config
    from redistro.faults.runner import _away_from_park

    cfg = load_config(Path(__file__).parents[2] / "config" / "redistro.yaml")
    assert _away_from_park(tmp_path, cfg) == ""  # no pose kept: the arms power up parked
    park = {r: list(cfg.robots[r].initial_q_rad) for r in cfg.robots}
    pose = tmp_path / cfg.session.plant_pose_file
    pose.write_text(json.dumps({"q_rad": park}))
    assert _away_from_park(tmp_path, cfg) == ""
    park["r2"][3] += 0.17  # about 10 degrees on joint 4
    pose.write_text(json.dumps({"q_rad": park}))
    assert _away_from_park(tmp_path, cfg) == "r2 stands 10 deg off its park pose"

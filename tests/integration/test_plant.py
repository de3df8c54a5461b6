"""The plant process and the two-layer driver, over both backplanes.

Real plant process, real PyBullet, real shared memory or real python-can
(udp_multicast) frames between processes.
"""

from __future__ import annotations

import math
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from redistro.drivers.io.registers import ENC_MODULO
from redistro.errors import ConfigError, IOFault
from tests.integration.plant_rig import Model, above_the_load, plant_rig

BACKPLANES = ["shm", "can"]


def one_count(d) -> np.ndarray:  # type: ignore[no-untyped-def]
    return 1.0 / d.counts_per_rad


@pytest.mark.parametrize("backplane", BACKPLANES)
def test_torque_moves_arm_and_encoders_agree(backplane: str, tmp_path: Path) -> None:
    with plant_rig(backplane, tmp_path) as rig:
        d = rig.drivers["r1"]
        q0 = rig.truth("r1")["q_rad"].copy()
        d.send_torques(np.zeros(7))  # (the amplifiers on: their watchdog ran out at start-up)
        d.release_brakes([0])  # the vertical axis: no gravity on it
        rig.wait_released("r1", [0])
        errors = []

        def push() -> None:
            d.send_torques(np.array([8.0, 0, 0, 0, 0, 0, 0]))
            fb, tr = rig.synced("r1")
            errors.append(np.abs(fb.q_rad - tr["q_rad"]) / one_count(d))

        with above_the_load():  # (a reader stalled by the load took 7 samples in 0.5 s)
            rig.run_for(0.5, push)
        d.freeze()
        moved = rig.truth("r1")["q_rad"][0] - q0[0]
        assert moved > 0.05, f"joint 1 moved only {moved} rad"
        err = np.max(errors, axis=0)
        assert len(errors) >= 20
        assert np.all(err <= 1.0), f"encoder error in counts: {err}"


@pytest.mark.parametrize("backplane", BACKPLANES)
def test_counter_wrap(backplane: str, tmp_path: Path) -> None:
    with plant_rig(backplane, tmp_path) as rig:
        d = rig.drivers["r1"]
        tr = rig.truth("r1")
        counts = np.zeros(7, dtype=np.int64)
        counts[0] = ENC_MODULO - 300  # 300 counts below the wrap
        d.preset_encoders(tr["q_rad"], counts=counts)
        d.release_brakes([0])
        raws = []

        def push() -> None:
            d.send_torques(np.array([8.0, 0, 0, 0, 0, 0, 0]))
            raws.append(int(d.read_raw()[d.hw.joints[0].encoder.address]["counter"][0]))

        with above_the_load():  # (its reads in time, beside a loaded host)
            rig.run_for(0.4, push)
        d.freeze()
        fb, tr = rig.synced("r1")
        assert max(raws) > ENC_MODULO - 300 and raws[-1] < ENC_MODULO // 2, "counter did not wrap"
        assert abs(fb.q_rad[0] - tr["q_rad"][0]) <= one_count(d)[0]


@pytest.mark.parametrize("backplane", BACKPLANES)
def test_brakes_hold_against_gravity(backplane: str, tmp_path: Path) -> None:
    with plant_rig(backplane, tmp_path) as rig:
        start = {r: rig.truth(r)["q_rad"].copy() for r in rig.drivers}
        taus = {r: np.abs(rig.truth(r)["tau_nm"]).max() for r in rig.drivers}
        rig.run_for(5.0)
        for r, q0 in start.items():
            drift = np.degrees(np.abs(rig.truth(r)["q_rad"] - q0)).max()
            assert drift < 0.1, f"{r} drifted {drift} deg under its brakes"
            assert taus[r] > 5.0, "the brakes were not carrying any gravity load"


@pytest.mark.parametrize("backplane", BACKPLANES)
def test_home_switches_toggle_at_their_angles(backplane: str, tmp_path: Path) -> None:
    # start 0.1 rad below every home mark (the park pose) and sweep up through them
    start = [round(a - 0.1, 3) for a in [0.0, 0.5, 0.0, -1.2, 0.0, 1.0, 0.0]]
    # (the amplifiers' watchdog at 2 s: on a loaded host the test process,
    # which writes the torques, may stall past 100 ms and the arm would
    # freeze mid-sweep; twice a fresh run found no edge on joint 2)
    sets = [f"robots.r1.initial_q_rad={start}", "plant.output_watchdog_ms=2000"]
    with plant_rig(backplane, tmp_path, sets) as rig:
        model = Model(rig.cfg)
        d = rig.drivers["r1"]
        s = d.hw.sensors
        kp = np.array([400, 400, 200, 200, 80, 50, 30.0])
        kd = np.array([30, 30, 15, 15, 4, 2, 1.0])
        t0 = rig.sim_time_s()
        seen: list[tuple[np.ndarray, np.ndarray]] = []
        d.release_brakes()
        rig.wait_released("r1", list(range(7)))

        def sweep() -> None:
            t = rig.sim_time_s() - t0
            target = np.asarray(s.home_angle_rad) - 0.1 + 0.2 * min(1.0, t / 1.5)
            fb, tr = rig.synced("r1")
            tau = model.gravity("r1", fb.q_rad) + kp * (target - fb.q_rad) - kd * fb.qd_rad_s
            d.send_torques(tau)
            seen.append((tr["q_rad"].copy(), fb.home.copy()))
            time.sleep(0.0002)  # (real time: the rest of the host gets its turn)

        with above_the_load():  # (its torques written in time, beside a loaded host)
            rig.run_for(1.8, sweep)
        d.freeze()
        model.close()
        q = np.array([a for a, _ in seen])
        home = np.array([b for _, b in seen])
        for j in range(7):
            half, hyst = s.home_window_rad[j] / 2, s.home_hysteresis_rad[j] / 2
            centre = s.home_angle_rad[j]
            on = np.flatnonzero(~home[:-1, j] & home[1:, j]) + 1
            off = np.flatnonzero(home[:-1, j] & ~home[1:, j]) + 1
            assert len(on) >= 1 and len(off) >= 1, f"joint {j + 1}: no edges as it swept through"
            tol = max(2e-3, 2 * np.abs(np.diff(q[:, j])).max())
            # on a little inside the window's edge, off a little outside (hysteresis)
            d_on = np.abs(q[on, j] - centre) - (half - hyst)
            d_off = np.abs(q[off, j] - centre) - (half + hyst)
            assert np.all(np.abs(d_on) <= tol), f"joint {j + 1} switched on at {q[on, j]}"
            assert np.all(np.abs(d_off) <= tol), f"joint {j + 1} switched off at {q[off, j]}"


@pytest.mark.parametrize("backplane", BACKPLANES)
def test_wrist_sensor_reads_the_contact_force(backplane: str, tmp_path: Path) -> None:
    from redistro.config.loader import load_config

    cfg = load_config(None, [])
    hx, hy, top = cfg.workcell.hole.xyz_m
    peg = cfg.workcell.peg
    model = Model(cfg)
    # the peg's tip 3 mm above the fixture's top face, beside the hole, pointing down
    above = [hx, hy + 0.025, top + peg.length_m + 0.003]
    q_start = model.ik("r2", above, [np.pi, 0.0, 0.0])
    sets = [f"robots.r2.initial_q_rad=[{', '.join(f'{v:.6f}' for v in q_start)}]"]
    press = np.array([0.0, 0.0, -20.0])  # N, world frame, on the environment
    with plant_rig(backplane, tmp_path, sets) as rig:
        d = rig.drivers["r2"]
        d.release_brakes()
        kp, kd = 30.0, np.array([8, 8, 4, 4, 1, 0.5, 0.2])
        samples: list[tuple[np.ndarray, np.ndarray]] = []

        def push() -> None:
            fb, tr = rig.synced("r2")
            jac = model.jacobian("r2", fb.q_rad, [0.0, 0.0, peg.length_m])
            tau = model.gravity("r2", fb.q_rad) + jac.T @ press
            tau += kp * (q_start - fb.q_rad) - kd * fb.qd_rad_s
            d.send_torques(tau)
            rot = tr["tool_rot"]
            samples.append((rot @ fb.wrench[:3], tr["contact_world"][:3].copy()))

        with above_the_load():  # (its torques written in time, beside a loaded host)
            rig.run_for(1.5, push)
        d.freeze()
    model.close()
    late = samples[len(samples) * 2 // 3 :]
    sensed = np.mean([a for a, _ in late], axis=0)
    contact = np.mean([b for _, b in late], axis=0)
    assert contact[2] > 10.0, f"the peg did not press on the fixture: {contact}"
    assert sensed[2] > 0, "the sensed force must push the peg up (external force on the tool)"
    err = np.linalg.norm(sensed - contact) / np.linalg.norm(contact)
    assert err < 0.10, f"sensed {sensed} vs contact {contact}: {err:.1%}"


@pytest.mark.parametrize("backplane", BACKPLANES)
def test_freeze_stops_a_moving_arm(backplane: str, tmp_path: Path) -> None:
    with plant_rig(backplane, tmp_path) as rig:
        d = rig.drivers["r1"]
        d.send_torques(np.zeros(7))  # (the amplifiers on: their watchdog ran out at start-up)
        d.release_brakes([0])
        rig.wait_released("r1", [0])
        rig.run_for(0.3, lambda: d.send_torques(np.array([15.0, 0, 0, 0, 0, 0, 0])))
        speed = rig.truth("r1")["qd_rad_s"][0]
        assert speed > 0.3, f"joint 1 only reached {speed} rad/s"
        t0 = time.monotonic()
        d.freeze()
        braked_at = stopped_at = None
        deadline = time.monotonic() + 5
        with above_the_load():  # (a stall of this watcher would make the stop look late)
            while stopped_at is None and time.monotonic() < deadline:
                tr = rig.truth("r1")
                if braked_at is None and tr["braked"][0]:
                    braked_at = int(tr["step"])
                if braked_at is not None and abs(tr["qd_rad_s"][0]) < 1e-3:
                    stopped_at = int(tr["step"])
                time.sleep(0.0002)  # (5 looks a step)
        wall_ms = (time.monotonic() - t0) * 1e3
        assert braked_at is not None and stopped_at is not None
        stop_ms = (stopped_at - braked_at) * 1e3 / rig.cfg.plant.physics_hz
        print(
            f"freeze[{backplane}]: {speed:.2f} rad/s stopped in {stop_ms} ms, {wall_ms:.1f} ms wall"
        )
        assert stop_ms <= 20.0, f"stopped {stop_ms} ms after the brake engaged"
        assert wall_ms < 500, f"freeze took {wall_ms} ms of wall time"


@pytest.mark.parametrize("backplane", BACKPLANES)
def test_a_killed_plant_is_an_io_fault(backplane: str, tmp_path: Path) -> None:
    # above the load from the rig's start: its drivers' opening reads have
    # the 30 ms budget too (stalled by the load, one found no CAN answer)
    with above_the_load(), plant_rig(backplane, tmp_path, ["plant.io_timeout_ms=30"]) as rig:
        d = rig.drivers["r1"]
        d.read_feedback()
        os.kill(rig.plant.pid, signal.SIGKILL)
        t0 = time.monotonic()
        with pytest.raises(IOFault):
            deadline = time.monotonic() + 2
            while time.monotonic() < deadline:
                d.read_feedback()
        detected_ms = (time.monotonic() - t0) * 1e3
        print(f"plant killed[{backplane}]: I/O fault after {detected_ms:.1f} ms")
        # target 50 ms (io_timeout 30 ms + one read); the bound leaves room for host stalls
        assert detected_ms < 80, f"I/O fault seen {detected_ms:.0f} ms after the kill"
        rig.plant.proc.wait(5)


def test_driver_config_must_match_the_chassis(tmp_path: Path) -> None:
    from redistro.config.hardware import load_hardware
    from redistro.config.loader import load_config
    from redistro.drivers.io.shm import ShmBackplane
    from redistro.drivers.robot import RobotDriver

    with plant_rig("shm", tmp_path) as rig:
        other = tmp_path / "r1.io.yaml"
        text = (Path("config/robots/r1.io.yaml")).read_text().replace("address: 32", "address: 99")
        other.write_text(text)
        cfg = load_config(None, [f"robots.r1.io={other}"])
        hw = load_hardware(cfg)["r1"]
        bp = ShmBackplane(rig.session.id, 0.02)
        drv = RobotDriver(hw, bp, 1000.0)
        with pytest.raises(
            ConfigError, match=r"r1.io.yaml: boards.dac.address: no board at address 99"
        ):
            drv.open()
        drv.close()


def test_positions_file_presets_the_next_start(tmp_path: Path) -> None:
    from redistro.drivers import positions

    path = tmp_path / "positions.json"
    with plant_rig("shm", tmp_path / "a") as rig:
        finals = {r: rig.synced(r)[0].q_rad for r in rig.drivers}
        positions.write(path, rig.session.id, finals, clean=True)
    with plant_rig("shm", tmp_path / "b") as rig:
        pos = positions.read(path, list(rig.drivers))
        for r, d in rig.drivers.items():
            d.preset_encoders(np.asarray(pos.q_rad[r]))
            fb, tr = rig.synced(r)
            err = np.abs(fb.q_rad - tr["q_rad"]) * d.counts_per_rad
            assert np.all(err <= 2.0), f"{r}: {err} counts after a preset from the file"


def test_the_amplifiers_watchdog_brakes_an_arm_nobody_commands(tmp_path: Path) -> None:
    """Outputs written once and then left alone (a dead controller): the
    chassis cuts the DAC and engages the brakes after plant.output_watchdog_ms."""
    with plant_rig("shm", tmp_path, ["plant.output_watchdog_ms=50"]) as rig:
        d = rig.drivers["r1"]
        d.send_torques(np.array([8.0, 0, 0, 0, 0, 0, 0]))
        d.release_brakes([0])
        d.send_torques(np.array([8.0, 0, 0, 0, 0, 0, 0]))
        released_at = time.monotonic()
        seen_released = False
        deadline = released_at + 10.0
        while time.monotonic() < deadline:
            braked = rig.truth("r1")["braked"]
            seen_released = seen_released or not braked[0]
            if seen_released and braked.all():
                break
            time.sleep(0.002)  # polling the plant's truth with a deadline
        assert seen_released, "the brake of joint 1 never came off"
        assert rig.truth("r1")["braked"].all(), "the arm was never braked again"
        # written again: the watchdog lets go
        d.send_torques(np.zeros(7))
        d.release_brakes([0])
        rig.run_for(0.01, lambda: d.send_torques(np.zeros(7)))
        assert not rig.truth("r1")["braked"][0]
        d.freeze()
    trips = rig.plant.result()["watchdog_trips"]
    assert any(t["robot"] == "r1" for t in trips), trips


def test_the_plant_refuses_a_world_whose_bodies_overlap() -> None:
    """Built from a config that bypassed the load checks (the plant judges
    its own world): two bases in one another, then a base in the table, are
    refused, naming which body; the shipped work-cell is built."""
    import dataclasses

    from redistro.config import load_config
    from redistro.plant.world import World

    cfg = load_config("config/redistro.yaml")
    World(cfg).close()
    for base, what in (([0.0, -0.4, 0.0], "inside robot r2"), ([0.45, 0.0, 0.0], "table")):
        r1 = dataclasses.replace(cfg.robots["r1"], base_xyz_m=base)
        bad = dataclasses.replace(cfg, robots={**cfg.robots, "r1": r1})
        with pytest.raises(ConfigError, match=what):
            World(bad)
    # an object where an arm stands (an arm starts where the last session left it)
    from redistro.config.model import ObjectConfig

    crate = ObjectConfig(size_xyz_m=[0.2, 0.2, 0.3], xy_m=[0.0, 0.45])
    bad = dataclasses.replace(
        cfg, workcell=dataclasses.replace(cfg.workcell, objects={"crate": crate})
    )
    with pytest.raises(ConfigError, match=r"robot r1 stands \d+ mm inside the object crate"):
        World(bad)


def test_an_object_with_a_hole_is_built_with_its_hole() -> None:
    """A block with a square hole in its top face: a ray down the hole's
    centre meets its floor at the hole's depth, a ray beside the hole the
    top face; a hole without walls around it is refused at load."""
    import dataclasses

    from redistro.config import load_config
    from redistro.config.loader import load_config as load
    from redistro.config.model import ObjectConfig
    from redistro.plant.truth import object_pose
    from redistro.plant.world import World

    cfg = load_config("config/redistro.yaml")
    block = ObjectConfig(
        size_xyz_m=[0.16, 0.08, 0.06], xy_m=[0.45, 0.3], yaw_deg=30.0,
        hole_side_m=0.031, hole_depth_m=0.04, hole_at_xy_m=[0.04, 0.0],
    )  # fmt: skip
    cfg = dataclasses.replace(
        cfg, workcell=dataclasses.replace(cfg.workcell, objects={"block": block})
    )
    world = World(cfg)
    try:
        (x, y, z), yaw = object_pose(cfg, "block")
        c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
        top = z + 0.03
        for local, depth in (((0.04, 0.0), 0.04), ((-0.04, 0.0), 0.0), ((0.04, 0.03), 0.0)):
            px, py = x + c * local[0] - s * local[1], y + s * local[0] + c * local[1]
            hit = world.pb.rayTest(
                [px, py, top + 0.1], [px, py, top - 0.2], physicsClientId=world.client
            )[0]
            assert hit[0] == world.objects["block"], (local, hit)
            assert abs(hit[3][2] - (top - depth)) < 1e-4, (local, hit[3])
    finally:
        world.close()
    bad = "block: {size_xyz_m: [0.16, 0.08, 0.06], xy_m: [0.45, 0.3], hole_side_m: 0.078}"
    with pytest.raises(ConfigError, match=r"the hole's wall along y is 1.0 mm, at least 3 mm"):
        load(None, [f"workcell.objects={{{bad}}}"])


def test_the_plant_sees_how_deep_an_object_went_into_another_objects_hole() -> None:
    """The plant's truth for an insertion of one object into another:
    a peg dropped into a turned block's hole comes to rest on its floor,
    and ObjectsInHoles reports the hole's depth; a peg standing beside the
    hole, on the block's top face, counts nothing."""
    import dataclasses

    from redistro.config import load_config
    from redistro.config.model import ObjectConfig
    from redistro.plant.truth import ObjectsInHoles, object_pose
    from redistro.plant.world import World

    cfg = load_config("config/redistro.yaml")
    block = ObjectConfig(
        size_xyz_m=[0.16, 0.08, 0.06], xy_m=[0.45, 0.3], yaw_deg=30.0, mass_kg=2.0,
        hole_side_m=0.031, hole_depth_m=0.04, hole_at_xy_m=[0.04, 0.0],
    )  # fmt: skip
    peg = ObjectConfig(size_xyz_m=[0.02, 0.02, 0.1], xy_m=[0.45, 0.1], mass_kg=0.1)
    objects = {"block": block, "peg": peg}
    cfg = dataclasses.replace(cfg, workcell=dataclasses.replace(cfg.workcell, objects=objects))
    for local, depth in (((0.04, 0.0), 0.04), ((-0.04, 0.0), None)):
        world = World(cfg)
        try:
            pb, cid = world.pb, world.client
            (x, y, z), yaw = object_pose(cfg, "block")
            c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
            px, py = x + c * local[0] - s * local[1], y + s * local[0] + c * local[1]
            q = pb.getQuaternionFromEuler([0, 0, math.radians(yaw)])
            pb.resetBasePositionAndOrientation(
                world.objects["peg"], [px, py, z + 0.03 + 0.051], q, physicsClientId=cid
            )
            truth = ObjectsInHoles(world)
            for step in range(1, 1500):  # (1.5 s: dropped, at rest)
                pb.stepSimulation(physicsClientId=cid)
                truth.sample(step)
            got = truth.report()["peg"]
            assert got["hole_of"] == "block"
            if depth is None:
                assert got["depth_m"] == 0.0, got
            else:
                assert abs(got["depth_m"] - depth) < 0.002, got
        finally:
            world.close()

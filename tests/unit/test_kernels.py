"""The compiled kernels against their numpy references, on the same inputs.

The chassis and the robot-level driver each keep the arithmetic of their
kernels in numpy (``use_kernels=False``). Here both run side by side, step
by step, on real PyBullet worlds and the real register layouts, and must
agree byte for byte: every board register, every truth record, every
decoded figure.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from redistro import kernels
from redistro.config.hardware import load_hardware
from redistro.config.loader import load_config
from redistro.drivers.io.registers import BoardType
from redistro.drivers.robot import RobotDriver
from redistro.errors import IOFault
from redistro.kernel_layouts import elements
from redistro.plant.chassis import Chassis
from redistro.plant.loopback import ChassisLoopback as Loopback
from redistro.plant.world import World

pytestmark = pytest.mark.skipif(not kernels.AVAILABLE, reason="redistro._kernels not built")
ROOT = Path(__file__).parents[2]
CFG = load_config(ROOT / "config" / "redistro.yaml")
HW = load_hardware(CFG)


@pytest.fixture
def twins() -> Any:
    worlds = [World(CFG), World(CFG)]
    pair = [Chassis(CFG, w, HW, use_kernels=k) for w, k in zip(worlds, (True, False), strict=True)]
    yield pair
    for w in worlds:
        w.close()


def _drive(c: Chassis, k: int) -> None:
    """The same controller outputs on both: brakes, DAC codes, a preset, latches."""
    dio, dac = c.banks.out[BoardType.DIO], c.banks.out[BoardType.DAC]
    enc = c.banks.out[BoardType.ENCODER]
    if k == 10:
        dio["outputs"] = 0x7F  # every brake released
    if k == 600:
        dio["outputs"] = 0x3F  # joint 7 braked again
    if k % 5 == 0:
        dac["code"] = (np.sin(k / 50 + np.arange(16)) * 400).astype(np.int16) if k > 10 else 0
        dac["watchdog"] = k + 1
    if k == 200:
        enc["preset_value"][0, 1] = 12345
        enc["preset_req"][0, 1] += 1
    if k == 300:
        enc["latch_mode"] = 1  # latch on home edges
    if k == 400:
        enc["latch_mode"][1, 0] = 0
        enc["latch_req"][1, 0] += 1  # a software latch


def test_the_chassis_kernels_match_the_numpy_chassis(twins: list[Chassis]) -> None:
    fast, ref = twins
    assert np.array_equal(fast.image, ref.image)
    for k in range(800):
        for c in twins:
            _drive(c, k)
            c.apply_outputs(None, 1_000_000 * k)
            c.step()
            c.fill_truth()
        # the gauges' counts may differ by one where a sum rounds differently
        diff = np.flatnonzero(fast.image != ref.image)
        strain = {
            off
            for row in fast.ft_rows
            for off in range(
                fast.banks.offset(BoardType.FORCE, "in", int(row), "strain"),
                fast.banks.offset(BoardType.FORCE, "in", int(row), "strain") + 24,
            )
        }
        assert set(diff.tolist()) <= strain, f"step {k}: registers differ at {diff[:8]}"
        assert np.array_equal(fast.truth_image, ref.truth_image), f"step {k}: truth differs"
    moved = np.abs(fast.q - np.concatenate([CFG.robots[r].initial_q_rad for r in HW])).max()
    assert moved > 0.05  # the arms really moved
    assert fast.reg.enc_latch_count.sum() > 0  # and latched on their home switches


def test_the_driver_kernels_match_the_numpy_driver() -> None:
    world = World(CFG)
    try:
        chassis = Chassis(CFG, world, HW)
        bp = Loopback(chassis)
        fast = RobotDriver(HW["r2"], bp, 1000.0, use_kernels=True)
        ref = RobotDriver(HW["r2"], bp, 1000.0, use_kernels=False)
        for d in (fast, ref):
            d.open(owner=False)
            d.jump_limit_rad_s = 20.0
        tau = np.array([5.0, -8.0, 3.0, 2.0, 0.5, -0.5, 0.2])
        fast.release_brakes()
        for k in range(600):
            fast.send_torques(tau * np.sin(k / 100))
            staged = fast.regs.rec_out[33]["code"].copy()
            ref.tau_cmd[...] = tau * np.sin(k / 100)
            assert ref._dac_numpy() == 0
            assert np.array_equal(ref.regs.rec_out[33]["code"], staged), f"cycle {k}: DAC codes"
            for _ in range(5):
                chassis.apply_outputs(None, 1_000_000 * k)
                chassis.step()
            for d in (fast, ref):
                d.sample()
            for name in ("q", "qd", "tau", "wrench", "home_levels", "brakes", "latch_q"):
                a, b = getattr(fast, name), getattr(ref, name)
                assert np.array_equal(a, b), f"cycle {k}: {name} {a} != {b}"
            assert np.array_equal(fast.latch_count, ref.latch_count)
            assert np.array_equal(fast._state, ref._state)
        assert np.abs(fast.qd).max() > 0.01  # it moved
        # a counter glitch: both refuse it, naming the joint
        chassis.rigs[1].encoder_offset[2] += 40000
        chassis.step()
        for d in (fast, ref):
            with pytest.raises(IOFault, match="joint 3: encoder jump"):
                d.sample()
    finally:
        world.close()


def test_a_non_finite_torque_is_refused_before_anything_is_written() -> None:
    world = World(CFG)
    try:
        chassis = Chassis(CFG, world, HW)
        for use in (True, False):
            d = RobotDriver(HW["r1"], Loopback(chassis), 1000.0, use_kernels=use)
            d.open(owner=False)
            before = chassis.image.copy()
            with pytest.raises(ValueError, match="finite"):
                d.send_torques(np.array([0, 0, np.nan, 0, 0, 0, 0.0]))
            assert np.array_equal(chassis.image, before)
    finally:
        world.close()


def test_the_dac_kernel_carries_its_rounding_as_the_numpy_driver_does() -> None:
    """Random torques, small, large and past the converter's range: the
    kernel and the numpy driver write the same codes and carry the same
    rounding errors, cycle after cycle. On a joint that carries (r1's
    joints 1-6 in the config), a torque under one code's worth comes out on
    average (error feedback); on joint 7 it is rounded to nothing; a
    saturated code carries nothing; a freeze forgets what was carried."""
    world = World(CFG)
    rng = np.random.default_rng(7)
    try:
        chassis = Chassis(CFG, world, HW)
        fast, ref = (
            RobotDriver(HW["r1"], Loopback(chassis), 1000.0, use_kernels=use)
            for use in (True, False)
        )
        for d in (fast, ref):
            d.open(owner=False)
        scale = rng.choice([0.01, 1.0, 100.0, 1000.0], size=(2000, 1))
        for k, tau in enumerate(rng.standard_normal((2000, 7)) * scale):
            fast.send_torques(tau)
            staged = fast.regs.rec_out[32]["code"].copy()
            ref.tau_cmd[...] = tau
            assert ref._dac_numpy() == 0
            assert np.array_equal(ref.regs.rec_out[32]["code"], staged), f"cycle {k}: DAC codes"
            assert np.array_equal(fast.dac_residual, ref.dac_residual), f"cycle {k}: carried"
            assert np.abs(fast.dac_residual).max() <= 0.5
        small = 0.3 * fast.dac_scale  # (a third of a code's torque, on every joint)
        codes = []
        for _ in range(1000):
            fast.send_torques(small)
            codes.append(fast.regs.rec_out[32]["code"][:7].astype(np.float64))
        mean = np.mean(codes, axis=0) * fast.dac_scale
        assert HW["r1"].sensors.dac_error_feedback == [True] * 6 + [False]
        assert np.allclose(mean[:6], small[:6], rtol=0.01) and mean[6] == 0.0, (mean, small)
        fast.send_torques(np.full(7, 1e6))  # (saturated: nothing carried)
        assert not fast.dac_residual.any()
        fast.send_torques(small)
        assert fast.dac_residual[:6].all() and fast.dac_residual[6] == 0.0
        fast.freeze()
        assert not fast.dac_residual.any() and not fast.regs.rec_out[32]["code"][:7].any()
    finally:
        world.close()


def test_seqlocks_copy_whole_blocks_or_none() -> None:
    from redistro.localdata.block import Block
    from redistro.localdata.layout import seqlocked

    dt = seqlocked(np.dtype([("v", "<u8", 20)]))
    shm = np.zeros(2 * dt.itemsize, dtype=np.uint8)
    blocks = [
        Block(f"b{i}", shm[i * dt.itemsize : (i + 1) * dt.itemsize].view(dt)[0:1].reshape(()))
        for i in range(2)
    ]
    image = np.zeros(400, dtype=np.uint8)
    seq_off = [i * dt.itemsize + dt.fields["seq"][1] for i in range(2)]  # type: ignore[index]
    data_off = [i * dt.itemsize + dt.fields["data"][1] for i in range(2)]  # type: ignore[index]
    rows = [(seq_off[i], data_off[i], 160, 200 * i) for i in range(2)]
    torn = np.zeros(2, dtype=np.int64)
    read_rows = kernels.table("seq_read", "table", rows)
    read = kernels.plan("seq_read", src=shm, dst=image, table=read_rows, torn=torn)
    write_rows = kernels.table("seq_write", "table", rows)
    write = kernels.plan("seq_write", dst=shm, src=image, table=write_rows)
    image[:160] = 7
    image[200:360] = 9
    kernels.KERNELS.seq_write(write)
    assert blocks[0].seq == 2 and bytes(blocks[1].read()["v"].tobytes()) == bytes([9]) * 160
    image[:] = 0
    assert kernels.KERNELS.seq_read(read) == 0
    assert (image[:160] == 7).all() and (image[200:360] == 9).all()
    # a writer stopped mid-write (odd sequence): no copy, counted, the old bytes stay
    blocks[1]._seq[0] += 1
    image[200:360] = 1
    assert kernels.KERNELS.seq_read(read) == 1
    assert torn.tolist() == [0, 1] and (image[200:360] == 1).all()


def test_plans_refuse_wrong_buffers() -> None:
    with pytest.raises(KeyError, match="table"):
        kernels.plan("copy", src=np.zeros(4, np.uint8), dst=np.zeros(4, np.uint8))
    with pytest.raises(ValueError, match="buffer table: elements of float64, expected int64"):
        kernels.plan(
            "copy", src=np.zeros(4, np.uint8), dst=np.zeros(4, np.uint8), table=np.zeros(3)
        )
    with pytest.raises(ValueError, match="no kernel"):
        kernels.plan("nothing")
    names = [a[0] for a in kernels.KERNELS.signature("driver_dac")]
    assert names == ["image", "tau", "volts_per_nm", "code_off", "residual", "carry"]


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
def test_the_guard_screen_flags_whatever_the_guard_refuses() -> None:
    """guard_prepare must flag every command that check() refuses (it only
    screens: check() names the limit), and prepare the command as the sender
    would: no torque on a joint off, NaN or not."""
    from redistro.esc.sender import TRACE_CYCLES, Violation, check
    from redistro.localdata.block import Record
    from redistro.localdata.layout import COMMAND, FEEDBACK, HOME

    fb, cmd, home = Record(FEEDBACK), Record(COMMAND), Record(HOME)
    qd_max, tau_max = np.full(7, 1.0), np.array([200, 200, 120, 120, 60, 60, 30.0])
    q_lo, q_hi = np.full(7, -2.0), np.full(7, 2.0)
    stop_k = np.full(7, 0.1)  # 1 / (2 * 5 rad/s^2)
    limits = np.concatenate([qd_max, tau_max, [120.0, 15.0], q_lo, q_hi, stop_k])
    on, released, tau = np.zeros(7, bool), np.zeros(7, bool), np.zeros(7)
    trace, at = np.zeros((TRACE_CYCLES, 30)), np.zeros(2, np.int64)
    f, c, h = FEEDBACK.fields, COMMAND.fields, HOME.fields
    plan = kernels.plan(
        "guard_prepare",
        fb=fb.array.reshape(1).view(np.uint8),
        fb_off=np.array([f[n][1] for n in ("q_rad", "qd_rad_s", "tau_nm", "wrench")], np.int64),
        src=cmd.array.reshape(1).view(np.uint8),
        src_off=np.array([c[n][1] for n in ("tau_nm", "joint_on", "session_status")], np.int64),
        home=home.array.reshape(1).view(np.uint8),
        home_off=np.array([h["step"][1]], np.int64),
        limits=limits,
        on=on,
        released=released,
        tau=tau,
        trace=trace,
        trace_at=at,
    )
    rng = np.random.default_rng(7)
    specials = [np.nan, np.inf, -np.inf, 1e308]
    refused = 0
    for k in range(20000):
        a, cm = fb.array, cmd.array
        a["q_rad"] = rng.normal(size=7) * 0.8
        a["qd_rad_s"] = rng.normal(size=7) * 0.3
        a["tau_nm"] = rng.normal(size=7) * tau_max * 0.25
        a["wrench"] = rng.normal(size=6) * [25, 25, 25, 3, 3, 3]
        cm["tau_nm"] = rng.normal(size=7) * tau_max * 0.25
        cm["joint_on"] = rng.random(7) < 0.9
        cm["session_status"] = 2 if rng.random() < 0.05 else 1
        if rng.random() < 0.2:  # a special value somewhere
            field = rng.choice(["q_rad", "qd_rad_s", "tau_nm", "wrench"])
            vec = a[field] if rng.random() < 0.7 else cm["tau_nm"]
            vec[rng.integers(len(vec))] = rng.choice(specials)
        home["step"] = k
        at[1] = k
        flags = kernels.KERNELS.guard_prepare(plan)
        want_on = (cm["joint_on"] != 0) & (int(cm["session_status"]) != 2)
        assert np.array_equal(on, want_on)
        assert np.array_equal(tau, np.where(want_on, cm["tau_nm"], 0.0), equal_nan=True)
        try:
            check(
                a["q_rad"],
                a["qd_rad_s"],
                a["tau_nm"],
                a["wrench"],
                tau,
                qd_max,
                tau_max,
                120.0,
                15.0,
                q_lo,
                q_hi,
                stop_k,
            )
        except Violation:
            refused += 1
            assert flags & 1, f"case {k}: check() refuses, the screen passed it"
        row = trace[k % TRACE_CYCLES]
        assert row[0] == k and row[1] == k and np.array_equal(row[23:], tau, equal_nan=True)
    assert 2000 < refused < 18000  # both kinds of case were tried


def test_the_cartesian_law_kernel_matches_its_numpy_composition() -> None:
    from redistro.control.cartesian import (
        ForceParams,
        ImpedanceGains,
        TaskFrameCommand,
        rotvec_to_matrix,
    )
    from redistro.control.cartesian_law import CartesianLaw
    from redistro.control.dynamics import ArmModel
    from redistro.robotmodel import Peg

    imp = CFG.ssc.impedance
    gains = ImpedanceGains(
        *(
            np.asarray(v, dtype=float)
            for v in (imp.k, imp.d, imp.ki, imp.i_max, imp.k_null, imp.d_joint)
        ),
        zeta=imp.zeta,
    )
    fc = CFG.ssc.force
    force = ForceParams(
        fc.k_adm, fc.k_adm_rot, fc.v_max, fc.w_max, fc.a_max, fc.alpha_max, fc.contact_n, fc.ramp_s
    )
    peg = CFG.workcell.peg
    model = ArmModel(Peg(peg.side_m, peg.length_m, peg.mass_kg), [0.0, -0.45, 0.0])
    base = np.array([0.0, -0.45, 0.0])
    laws = [CartesianLaw(gains, force, peg.length_m, base, use_kernel=k) for k in (True, False)]
    rng = np.random.default_rng(11)
    for case in range(40):
        q0 = np.array([0, 0.5, 0, -1.2, 0, 1.0, 0]) + rng.normal(size=7) * 0.3
        frame = "tool" if case % 3 == 0 else "world"
        sel = [
            np.zeros(6),
            np.array([0, 0, 1.0, 0, 0, 0]),
            np.array([1.0, 1, 0, 0, 0, 0]),
            np.array([0, 0, 1.0, 1, 1, 0]),
        ][case % 4]
        goal = np.concatenate(
            [rng.normal(size=3) * 0.1 + [0.5, -0.3, 0.2], rng.normal(size=3) * 0.3 + [0, 3.1, 0]]
        )
        cmd = TaskFrameCommand(goal, rng.normal(size=6) * [5, 5, 20, 0.5, 0.5, 0.5], sel, frame)
        start_R = rotvec_to_matrix(rng.normal(size=3) * 0.4 + [0, 3.0, 0])
        start_p = rng.normal(size=3) * 0.05 + [0.5, -0.3, 0.3]
        integral = rng.normal(size=6) * 0.01
        for law in laws:
            law.start(cmd, start_p, start_R, 2.0 + case % 3, q0, integral)
        for k in range(30):
            q = q0 + rng.normal(size=7) * 0.05
            qd = rng.normal(size=7) * 0.2
            w = rng.normal(size=6) * [5, 5, 15, 0.5, 0.5, 0.5]
            for law in laws:
                model.terms_into(q, law.J, law.R, law.t, law.M, law.g)
                law.q[...], law.qd[...], law.wrench[...] = q, qd, w
                law.update(0.1 * k * (case % 5), 0.005, 0.1 * k, integrate=bool(k % 2))
            (a_out, a_st), (b_out, b_st) = ((elements(x.out), elements(x.state)) for x in laws)
            assert np.allclose(a_out, b_out, rtol=1e-7, atol=1e-8), (
                f"case {case} cycle {k}: {a_out - b_out}"
            )
            assert np.allclose(a_st, b_st, rtol=1e-9, atol=1e-10), f"case {case} cycle {k}"
    assert laws[0].contact  # the force axes met their contact threshold somewhere


def test_the_joint_kernels_match_their_numpy_references() -> None:
    from redistro.control.pid import PidGains, PidLoop, PidState
    from redistro.control.trajectory import QuinticRef

    rng = np.random.default_rng(2)
    gains = PidGains(*(np.abs(rng.normal(size=7)) * 20 for _ in range(4)))
    arrays = [np.zeros(7) for _ in range(5)]
    on = np.zeros(7, dtype=bool)
    loops = []
    for use in (True, False):
        tau = np.zeros(7)
        loops.append((PidLoop(gains, PidState(), *arrays, on, tau, use_kernel=use), tau))
    refs = [QuinticRef(np.zeros(7), np.zeros(7), np.zeros(7), use_kernel=u) for u in (True, False)]
    for r in refs:
        r.start(rng.normal(size=7), rng.normal(size=7), 2.5)
        r.q0[...] = refs[0].q0
        r.d[...] = refs[0].d
    for k in range(300):
        for a in arrays:
            a[...] = rng.normal(size=7)
        on[...] = rng.random(7) < 0.8
        for loop, _tau in loops:
            loop.update(0.001 * (1 + k % 3))
        (_, a), (_, b) = loops
        assert np.allclose(a, b, rtol=1e-13, atol=1e-13)
        assert np.array_equal(loops[0][0].state.integral, loops[1][0].state.integral)
        for r in refs:
            r.at(-0.2 + 0.01 * k)
        assert np.allclose(
            np.array([refs[0].q, refs[0].qd, refs[0].qdd]),
            np.array([refs[1].q, refs[1].qd, refs[1].qdd]),
            rtol=1e-13,
            atol=1e-13,
        )

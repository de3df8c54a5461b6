"""Every compiled kernel against its Python reference, on random inputs.

Each test draws inputs with hypothesis (500 examples at least), runs the
kernel and the reference beside it on the same buffers, and compares what
both wrote. The DDM's kernels have theirs in test_ddm_equivalence.py, the
record codec in test_ddm_kernel_path.py.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from redistro import kernels
from redistro.config.hardware import load_hardware
from redistro.config.loader import load_config
from redistro.drivers.io.registers import BoardType
from redistro.errors import IOFault
from redistro.kernel_layouts import elements

pytestmark = pytest.mark.skipif(not kernels.AVAILABLE, reason="the kernels are not built")
ROOT = Path(__file__).parents[2]
CFG = load_config(ROOT / "config" / "redistro.yaml")
HW = load_hardware(CFG)
EXAMPLES = settings(
    max_examples=500, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)

finite = st.floats(-1e3, 1e3, allow_nan=False)
anything = st.floats(allow_nan=True, allow_infinity=True, width=64)


def vec(n: int, elems: Any = finite) -> Any:
    return hnp.arrays(np.float64, n, elements=elems)


# -- copies and seqlocks --


@EXAMPLES
@given(
    src=hnp.arrays(np.uint8, 256),
    spans=st.lists(
        st.tuples(st.integers(0, 240), st.integers(0, 240), st.integers(0, 16)), max_size=12
    ),
)
def test_copy(src: np.ndarray[Any, Any], spans: list[tuple[int, int, int]]) -> None:
    rows = kernels.copy_table(spans)
    a, b = np.zeros(256, np.uint8), np.zeros(256, np.uint8)
    kernels.KERNELS.copy(kernels.plan("copy", src=src, dst=a, table=rows))
    kernels.copy_rows(src, b, rows)
    assert np.array_equal(a, b)


@EXAMPLES
@given(
    payloads=st.lists(st.binary(min_size=1, max_size=64), min_size=1, max_size=6),
    odd=st.lists(st.booleans(), min_size=6, max_size=6),
)
def test_seqlocked_blocks_read_and_write_as_the_blocks_do(
    payloads: list[bytes], odd: list[bool]
) -> None:
    """seq_write publishes as Block.publish does; seq_read copies what
    Block.read_into reads, and leaves (and counts) a block mid-write."""
    from redistro.errors import TornReadTimeout
    from redistro.localdata.block import Block
    from redistro.localdata.layout import seqlocked

    n = len(payloads)
    dt = seqlocked(np.dtype([("v", "u1", 64)]))
    shm, ref_shm = np.zeros(n * dt.itemsize, np.uint8), np.zeros(n * dt.itemsize, np.uint8)
    blocks = [
        Block(f"b{i}", ref_shm[i * dt.itemsize : (i + 1) * dt.itemsize].view(dt)[0])
        for i in range(n)
    ]
    image = np.zeros(64 * n, np.uint8)
    spans = []
    for i, p in enumerate(payloads):
        image[64 * i : 64 * i + len(p)] = np.frombuffer(p, np.uint8)
        seq_at = i * dt.itemsize + dt.fields["seq"][1]  # type: ignore[index]
        data_at = i * dt.itemsize + dt.fields["data"][1]  # type: ignore[index]
        spans.append((seq_at, data_at, len(p), 64 * i))
    write = kernels.plan(
        "seq_write", dst=shm, src=image, table=kernels.table("seq_write", "table", spans)
    )
    kernels.KERNELS.seq_write(write)
    for i, p in enumerate(payloads):
        full = bytearray(64)
        full[: len(p)] = p
        blocks[i].publish(np.frombuffer(bytes(full), np.uint8))
    for i, p in enumerate(payloads):  # the payload's bytes and the counter agree
        seq_at, data_at = spans[i][0], spans[i][1]
        assert shm[seq_at : seq_at + 8].tobytes() == ref_shm[seq_at : seq_at + 8].tobytes()
        assert shm[data_at : data_at + len(p)].tobytes() == p
    for i in range(n):  # writers stopped mid-write
        if odd[i]:
            shm[spans[i][0]] += 1
            ref_shm[spans[i][0]] += 1
    out = np.full(64 * n, 0xEE, np.uint8)
    torn = np.zeros(n, np.int64)
    read = kernels.plan(
        "seq_read", src=shm, dst=out, table=kernels.table("seq_read", "table", spans), torn=torn
    )
    failed = kernels.KERNELS.seq_read(read)
    for i, p in enumerate(payloads):
        got = bytearray(64)
        try:
            blocks[i].read_into(memoryview(got), budget_s=0.0)
            want = bytes(got[: len(p)])
        except TornReadTimeout:
            want = b"\xee" * len(p)
        assert out[64 * i : 64 * i + len(p)].tobytes() == want
    assert failed == sum(odd[:n]) == int(torn.sum())


# -- the guard's screen --


@EXAMPLES
@given(
    q=vec(7, anything),
    qd=vec(7, st.floats(-3, 3)),
    tau=vec(7, st.floats(-300, 300)),
    wrench=vec(6, st.one_of(st.floats(-200, 200), anything)),
    cmd_tau=vec(7, st.one_of(st.floats(-300, 300), anything)),
    joint_on=hnp.arrays(np.uint8, 7, elements=st.integers(0, 1)),
    released=hnp.arrays(np.bool_, 7),
    status=st.sampled_from([0, 1, 2]),
    rows=st.integers(0, 10_000),
)
def test_guard_prepare(
    q: Any, qd: Any, tau: Any, wrench: Any, cmd_tau: Any, joint_on: Any, released: Any,
    status: int, rows: int,
) -> None:  # fmt: skip
    from redistro.esc import guard_layout as gl
    from redistro.esc.sender import TRACE_CYCLES, screen
    from redistro.localdata.block import Record
    from redistro.localdata.layout import COMMAND, FEEDBACK, HOME

    fb, cmd, home = Record(FEEDBACK), Record(COMMAND), Record(HOME)
    f, c = fb.array, cmd.array
    f["q_rad"], f["qd_rad_s"], f["tau_nm"], f["wrench"] = q, qd, tau, wrench
    c["tau_nm"], c["joint_on"], c["session_status"] = cmd_tau, joint_on, status
    home["step"] = 1234
    lim = np.zeros((), gl.LIMITS)
    lim["qd_max"], lim["tau_max"] = 2.0, [200, 200, 120, 120, 60, 60, 30]
    lim["force_max"], lim["moment_max"] = 120.0, 15.0
    lim["q_lo"], lim["q_hi"], lim["stop_k"] = -2.5, 2.5, 0.1
    outs = []
    for compiled in (True, False):
        on, rel, t = np.zeros(7, bool), released.copy(), np.zeros(7)
        trace, at = np.zeros(TRACE_CYCLES, gl.TRACE_ROW), np.zeros((), gl.TRACE_AT)
        at["rows"], at["cycle"] = rows, 77
        if compiled:
            f, c, h = FEEDBACK.fields, COMMAND.fields, HOME.fields
            assert f is not None and c is not None and h is not None
            fo, so, ho = (
                np.zeros((), gl.FB_OFF),
                np.zeros((), gl.SRC_OFF),
                np.zeros((), gl.HOME_OFF),
            )
            fo["q"], fo["qd"], fo["tau"], fo["wrench"] = (
                f[n][1] for n in ("q_rad", "qd_rad_s", "tau_nm", "wrench")
            )
            so["tau"], so["joint_on"], so["session_status"] = (
                c[n][1] for n in ("tau_nm", "joint_on", "session_status")
            )
            ho["step"] = h["step"][1]
            plan = kernels.plan(
                "guard_prepare", fb=fb.array.reshape(1).view(np.uint8), fb_off=fo,
                src=cmd.array.reshape(1).view(np.uint8), src_off=so,
                home=home.array.reshape(1).view(np.uint8), home_off=ho, limits=lim, on=on,
                released=rel, tau=t, trace=trace, trace_at=at,
            )  # fmt: skip
            flags = kernels.KERNELS.guard_prepare(plan)
        else:
            flags = screen(fb.array, cmd.array, status == 2, 1234, lim, on, rel, t, trace, at)
        outs.append((flags, on, t, trace, at))
    (fa, ona, ta, tra, ata), (fb_, onb, tb, trb, atb) = outs
    assert fa == fb_
    assert np.array_equal(ona, onb)
    assert np.array_equal(ta, tb, equal_nan=True)
    assert np.array_equal(elements(tra), elements(trb), equal_nan=True)
    assert elements(ata).tolist() == elements(atb).tolist()


# -- joint control --


@EXAMPLES
@given(
    gains=hnp.arrays(np.float64, (4, 7), elements=st.one_of(st.just(0.0), st.floats(1e-3, 100))),
    arrays=hnp.arrays(np.float64, (5, 7), elements=finite),
    integral=vec(7, st.floats(-10, 10)),
    on=hnp.arrays(np.bool_, 7),
    dt=st.floats(1e-4, 0.02),
)
def test_joint_pid(gains: Any, arrays: Any, integral: Any, on: Any, dt: float) -> None:
    from redistro.control.pid import PidGains, PidLoop, PidState

    g = PidGains(*gains)
    taus = []
    states = []
    for use in (True, False):
        state = PidState()
        state.integral[...] = integral
        tau = np.zeros(7)
        loop = PidLoop(g, state, *(a.copy() for a in arrays), on.copy(), tau, use_kernel=use)
        loop.update(dt)
        taus.append(tau)
        states.append(state.integral)
    assert np.array_equal(taus[0], taus[1]) and np.array_equal(states[0], states[1])


@EXAMPLES
@given(q0=vec(7), q1=vec(7), duration=st.floats(0.01, 100), t=st.floats(-10, 200))
def test_quintic(q0: Any, q1: Any, duration: float, t: float) -> None:
    from redistro.control.trajectory import QuinticRef

    out = []
    for use in (True, False):
        ref = QuinticRef(np.zeros(7), np.zeros(7), np.zeros(7), use_kernel=use)
        ref.start(q0, q1, duration)
        ref.at(t)
        out.append(np.array([ref.q, ref.qd, ref.qdd]))
    assert np.allclose(out[0], out[1], rtol=1e-14, atol=1e-12)


# -- the Cartesian law's decompositions --


@EXAMPLES
@given(a=hnp.arrays(np.float64, (3, 3), elements=st.floats(-100, 100)))
def test_eig3(a: Any) -> None:
    sym = (a + a.T) / 2
    w, v = np.zeros(3), np.zeros(9)
    kernels.KERNELS.eig3(kernels.plan("eig3", a=sym.reshape(9).copy(), w=w, v=v))
    V = v.reshape(3, 3)
    scale = max(1.0, float(np.abs(sym).max()))
    # every (w_i, V_i) an eigenpair, V orthonormal: w is sym's spectrum. (Not
    # against LAPACK's: its eigvalsh gave 1.50004 for [[0, 1.5, 0], [1.5, 0,
    # 2e-160], [0, 2e-160, 0]], whose eigenvalues are -1.5, 0, 1.5.)
    assert np.allclose(sym @ V, V * w, atol=1e-9 * scale)
    assert np.allclose(V @ np.diag(w) @ V.T, sym, atol=1e-9 * scale)
    assert np.allclose(V.T @ V, np.eye(3), atol=1e-9)


@EXAMPLES
@given(
    n=st.integers(1, 7),
    m=hnp.arrays(np.float64, (7, 7), elements=st.floats(-10, 10, allow_subnormal=False)),
    b=vec(7, st.floats(-10, 10)),
    shift=st.one_of(st.just(0.0), st.floats(-5, -1e-3), st.floats(1e-3, 5)),
)
def test_cholesky(n: int, m: Any, b: Any, shift: float) -> None:
    a = m[:n, :n] @ m[:n, :n].T + shift * np.eye(n)  # positive definite or not
    L, x = np.zeros(n * n), b[:n].copy()
    ok = kernels.KERNELS.cholesky(kernels.plan("cholesky", a=a.reshape(-1).copy(), l=L, b=x))
    if ok:
        low = L.reshape(n, n)
        assert np.array_equal(low, np.tril(low))
        assert np.allclose(low @ low.T, a, atol=1e-9 * max(1.0, np.abs(a).max()))
        if np.isfinite(x).all():  # (a near-singular matrix may overflow the solve)
            scale = max(1.0, np.abs(a).max() * np.abs(x).max())
            assert np.allclose(a @ x, b[:n], atol=1e-6 * scale)
    elif np.all(np.linalg.eigvalsh(a) > 1e-6 * max(1.0, np.abs(a).max())):
        pytest.fail("a positive definite matrix refused")


# -- the SSC's Cartesian law --


@pytest.fixture(scope="module")
def laws() -> Any:
    from redistro.control.cartesian import ForceParams, ImpedanceGains
    from redistro.control.cartesian_law import CartesianLaw
    from redistro.control.dynamics import ArmModel
    from redistro.robotmodel import Peg

    imp, fc, peg = CFG.ssc.impedance, CFG.ssc.force, CFG.workcell.peg
    gains = ImpedanceGains(
        *(np.asarray(v, float) for v in (imp.k, imp.d, imp.ki, imp.i_max, imp.k_null, imp.d_joint)),
        zeta=imp.zeta,
    )
    force = ForceParams(
        fc.k_adm, fc.k_adm_rot, fc.v_max, fc.w_max, fc.a_max, fc.alpha_max, fc.contact_n, fc.ramp_s
    )
    base = np.array([0.0, -0.45, 0.0])
    model = ArmModel(Peg(peg.side_m, peg.length_m, peg.mass_kg), list(base))
    pair = [CartesianLaw(gains, force, peg.length_m, base, use_kernel=k) for k in (True, False)]
    return model, pair


@EXAMPLES
@given(
    dq=vec(7, st.floats(-0.4, 0.4)),
    qd=vec(7, st.floats(-1, 1)),
    wrench=vec(6, st.floats(-30, 30)),
    sel=hnp.arrays(np.float64, 6, elements=st.sampled_from([0.0, 1.0])),
    goal=vec(6, st.floats(-0.2, 0.2)),
    goal_w=vec(6, st.floats(-20, 20)),
    frame=st.sampled_from(["world", "tool"]),
    seg_t=st.floats(0, 4),
    integrate=st.booleans(),
    state=vec(30, st.floats(-0.01, 0.01)),
    contact=st.booleans(),
)
def test_cartesian_law(
    laws: Any, dq: Any, qd: Any, wrench: Any, sel: Any, goal: Any, goal_w: Any, frame: str,
    seg_t: float, integrate: bool, state: Any, contact: bool,
) -> None:  # fmt: skip
    from redistro.control.cartesian import TaskFrameCommand, rotvec_to_matrix

    model, pair = laws
    q0 = np.array([0, 0.5, 0, -1.2, 0, 1.0, 0]) + dq
    cmd = TaskFrameCommand(goal + np.array([0.5, -0.3, 0.2, 0, 3.1, 0]), goal_w, sel, frame)  # type: ignore[arg-type]
    start_R = rotvec_to_matrix(np.array([0, 3.0, 0]) + goal[3:])
    for law in pair:
        law.start(cmd, np.array([0.5, -0.3, 0.3]) + goal[:3] / 2, start_R, 2.5, q0)
        s = law.state
        s["xi"], s["xi_v"], s["integral"] = state[:6], state[6:12], state[12:18]
        s["spring0"], s["a_ref"] = state[18:21], state[21:27]
        s["contact"], s["ramp"] = float(contact), 0.5 if contact else 0.0
        model.terms_into(q0, law.J, law.R, law.t, law.M, law.g)
        law.q[...], law.qd[...], law.wrench[...] = q0, qd, wrench
        law.update(seg_t, 0.005, 1.0 + seg_t, integrate)
    a, b = pair
    assert np.allclose(elements(a.out), elements(b.out), rtol=1e-7, atol=1e-8)
    assert np.allclose(elements(a.state), elements(b.state), rtol=1e-9, atol=1e-10)


# -- the chassis and the driver: the same boards, the same decode --


@pytest.fixture(scope="module")
def twin_chassis() -> Iterator[Any]:
    from redistro.plant.chassis import Chassis
    from redistro.plant.world import World

    worlds = [World(CFG), World(CFG)]
    yield [Chassis(CFG, w, HW, use_kernels=k) for w, k in zip(worlds, (True, False), strict=True)]
    for w in worlds:
        w.close()


@pytest.fixture(scope="module")
def driver_rig() -> Iterator[Any]:
    from redistro.drivers.robot import RobotDriver
    from redistro.plant.chassis import Chassis
    from redistro.plant.loopback import ChassisLoopback
    from redistro.plant.world import World

    world = World(CFG)
    chassis = Chassis(CFG, world, HW)
    drivers = [
        RobotDriver(HW["r2"], ChassisLoopback(chassis), 1000.0, use_kernels=use)
        for use in (True, False)
    ]
    for d in drivers:
        d.open(owner=False)
        d.jump_limit_rad_s = 20.0
    drivers[0].release_brakes()
    yield chassis, drivers
    world.close()


def _strain_offsets(c: Any) -> set[int]:
    out = set()
    for row in c.ft_rows:
        at = c.banks.offset(BoardType.FORCE, "in", int(row), "strain")
        out |= set(range(at, at + 24))
    return out


@EXAMPLES
@given(
    codes=hnp.arrays(np.int16, (2, 16), elements=st.integers(-600, 600)),
    brakes=st.integers(0, 0x7F),
    latch=st.integers(0, 1),
    steps=st.integers(1, 4),
)
def test_chassis_apply_and_sample(
    twin_chassis: Any, codes: Any, brakes: int, latch: int, steps: int
) -> None:
    """The same controller outputs on both chassis: the same registers (the
    gauges' counts may round one apart) and the same truth."""
    for c in twin_chassis:
        c.banks.out[BoardType.DIO]["outputs"] = brakes
        c.banks.out[BoardType.DAC]["code"] = codes
        c.banks.out[BoardType.ENCODER]["latch_mode"] = latch
        for _ in range(steps):
            c.apply_outputs(None, 0)
            c.step()
        c.fill_truth()
    fast, ref = twin_chassis
    diff = set(np.flatnonzero(fast.image != ref.image).tolist())
    assert diff <= _strain_offsets(fast), f"registers differ at {sorted(diff)[:8]}"
    assert np.array_equal(fast.truth_image, ref.truth_image)


@EXAMPLES
@given(tau=vec(7, st.floats(-10, 10)), steps=st.integers(1, 6))
def test_driver_decode_and_dac(driver_rig: Any, tau: Any, steps: int) -> None:
    """Two drivers on one chassis: the same DAC codes for the same torques,
    the same decoded figures from the same boards."""
    chassis, (fast, ref) = driver_rig
    tau = np.clip(tau - 30.0 * fast.qd, -10, 10)  # (damped: the arm stays slow)
    fast.send_torques(tau)
    ref.tau_cmd[...] = tau
    assert ref._dac_numpy() == 0
    for a, (_, ch) in fast.dac.items():  # this robot's channels of each DAC board
        assert np.array_equal(ref.regs.rec_out[a]["code"][ch], fast.regs.rec_out[a]["code"][ch])
    for _ in range(steps):
        chassis.apply_outputs(None, 0)
        chassis.step()
    refused = []
    for d in (fast, ref):
        try:
            d.sample()
            refused.append("")
        except IOFault as exc:  # (both refuse the same glitch alike)
            refused.append(str(exc))
    assert refused[0] == refused[1]
    for name in ("q", "qd", "tau", "wrench", "home_levels", "brakes", "latch_q", "latch_count"):
        assert np.array_equal(getattr(fast, name), getattr(ref, name)), name
    assert elements(fast._state).tolist() == elements(ref._state).tolist()

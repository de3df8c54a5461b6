"""``redistro bench kernels``: each compiled kernel against its numpy
reference, in one process, on the same inputs.

The numpy references are the vectorised code (index arrays, one operation
per bank or per quantity, preallocated outputs): what pure Python and numpy
reach. Each piece is called ``calls`` times in a hot loop and timed with
``thread_time`` around the call; the figures are CPU per call.

- chassis: the plant's step without PyBullet's ``stepSimulation`` (outputs
  applied to the joints, every board sampled, the truth filled), both arms;
- driver: one robot's ``sample()`` (its boards read over an in-process
  backplane and decoded) and ``send_torques()`` (screened, encoded, written);
- cartesian law: one arm's ``CartesianLaw.update`` (the SSC worker runs one
  per arm), with the arm's Pinocchio terms computed outside the timing;
- pid and quintic: one robot's joint PID update and quintic reference;
- ddm record: a record's crc32 and tag checked, and a record encoded and
  sealed (the reference: zlib and hashlib from Python).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from redistro.config.model import Config


def _time(fn: Callable[[], object], calls: int, between: Callable[[], object] | None = None) -> Any:
    clock = time.thread_time_ns
    out = np.empty(calls, dtype=np.int64)
    for _ in range(min(200, calls)):  # warm
        if between is not None:
            between()
        fn()
    for k in range(calls):
        if between is not None:
            between()
        c0 = clock()
        fn()
        out[k] = clock() - c0
    out.sort()
    return {
        "p50": round(float(out[calls // 2]) / 1e3, 2),
        "p99": round(float(out[min(calls - 1, int(calls * 0.99))]) / 1e3, 2),
    }


def _chassis(cfg: Config, hw: Any, use: bool, calls: int) -> Any:
    from redistro.plant.chassis import Chassis
    from redistro.plant.world import World

    world = World(cfg)
    try:
        c = Chassis(cfg, world, hw, use_kernels=use)
        c.banks.out[_board("DIO")]["outputs"] = 0x7F  # brakes released: the arms move
        now = [0]

        def step() -> None:
            now[0] += 1_000_000
            c.apply_outputs(None, now[0])
            c.sample()
            c.fill_truth()

        return _time(step, calls, c.step_physics)
    finally:
        world.close()


def _board(name: str) -> Any:
    from redistro.drivers.io.registers import BoardType

    return BoardType[name]


def _driver(cfg: Config, hw: Any, use: bool, calls: int) -> Any:
    from redistro.drivers.robot import RobotDriver
    from redistro.plant.chassis import Chassis
    from redistro.plant.loopback import ChassisLoopback
    from redistro.plant.world import World

    world = World(cfg)
    try:
        chassis = Chassis(cfg, world, hw)
        robot = sorted(hw)[-1]
        d = RobotDriver(hw[robot], ChassisLoopback(chassis), 1000.0, use_kernels=use)
        d.open(owner=False)
        tau = np.array([2.0, -3.0, 1.0, 1.0, 0.5, -0.5, 0.2])
        sample = _time(d.sample, calls, chassis.step)
        send = _time(lambda: d.send_torques(tau), calls)
        d.close()
        return {"sample": sample, "send": send}
    finally:
        world.close()


def _law(cfg: Config, use: bool, calls: int) -> Any:
    from redistro.control.cartesian import (
        ForceParams,
        ImpedanceGains,
        TaskFrameCommand,
        rotvec_to_matrix,
    )
    from redistro.control.cartesian_law import CartesianLaw
    from redistro.control.dynamics import ArmModel
    from redistro.robotmodel import Peg

    imp = cfg.ssc.impedance

    def a(v: Any) -> Any:
        return np.asarray(v, dtype=float)

    gains = ImpedanceGains(
        a(imp.k), a(imp.d), a(imp.ki), a(imp.i_max), a(imp.k_null), a(imp.d_joint), imp.zeta
    )
    fc = cfg.ssc.force
    force = ForceParams(
        fc.k_adm, fc.k_adm_rot, fc.v_max, fc.w_max, fc.a_max, fc.alpha_max, fc.contact_n, fc.ramp_s
    )
    peg = cfg.workcell.peg
    base = np.array([0.0, -0.45, 0.0])
    model = ArmModel(Peg(peg.side_m, peg.length_m, peg.mass_kg), list(base))
    law = CartesianLaw(gains, force, peg.length_m, base, use_kernel=use)
    q0 = np.array([0, 0.5, 0, -1.2, 0, 1.0, 0])
    # force control along z, position control of the rest: the insertion
    cmd = TaskFrameCommand(
        np.array([0.5, -0.3, 0.2, 0, 3.1, 0]),
        np.array([0, 0, -5.0, 0, 0, 0]),
        np.array([0, 0, 1.0, 0, 0, 0]),
        "world",
    )
    law.start(cmd, np.array([0.5, -0.3, 0.3]), rotvec_to_matrix(np.array([0, 3.1, 0])), 2.0, q0)
    rng = np.random.default_rng(1)
    q, qd, w = q0 + rng.normal(size=7) * 0.05, rng.normal(size=7) * 0.1, np.zeros(6)
    w[2] = -6.0
    model.terms_into(q, law.J, law.R, law.t, law.M, law.g)
    law.q[...], law.qd[...], law.wrench[...] = q, qd, w
    t = [0.0]

    def update() -> None:
        t[0] += 0.001
        law.update(t[0], 0.001, t[0], integrate=True)

    return _time(update, calls)


def _joints(use: bool, calls: int) -> Any:
    from redistro.control.pid import PidGains, PidLoop, PidState
    from redistro.control.trajectory import QuinticRef

    rng = np.random.default_rng(2)
    gains = PidGains(*(np.abs(rng.normal(size=7)) * 20 for _ in range(4)))
    q, qd, q_ref, qd_ref, g = (rng.normal(size=7) for _ in range(5))
    on = np.ones(7, dtype=bool)
    loop = PidLoop(gains, PidState(), q, qd, q_ref, qd_ref, g, on, np.zeros(7), use_kernel=use)
    ref = QuinticRef(np.zeros(7), np.zeros(7), np.zeros(7), use_kernel=use)
    ref.start(rng.normal(size=7), rng.normal(size=7), 2.5)
    t = [0.0]

    def at() -> None:
        t[0] = (t[0] + 0.001) % 3.0
        ref.at(t[0])

    return {"pid": _time(lambda: loop.update(0.001), calls), "quintic": _time(at, calls)}


def _wire(use: bool, calls: int) -> Any:
    """A DDM record's checksum and tag checked (what every record in costs)
    and a record encoded, checksummed and signed (every record out)."""
    from redistro.ddm import record as wire
    from redistro.kernels import KERNELS

    key = bytes(range(32))
    payload = np.zeros((), wire.PAYLOADS[wire.KIND_FEEDBACK]).tobytes()
    raw = wire.encode(
        wire.KIND_COMMAND, 1, "ssc", 1, 1, bytes(wire.PAYLOADS[wire.KIND_COMMAND].itemsize), key=key
    )
    enc = wire.Encoder(wire.KIND_FEEDBACK, 1, "esc.r1", key)
    if use:
        codec = wire._codec(key)
        verify: Callable[[], object] = lambda: KERNELS.wire_verify(codec, raw)  # noqa: E731
    else:
        enc.codec = None  # the Python path

        def verify() -> None:
            if int.from_bytes(raw[wire._CRC_AT : wire._CRC_AT + 4], "little") != wire._crc(raw):
                raise AssertionError("checksum")
            wire._check_tag(key, raw)

    seq = [0]

    def encode() -> None:
        seq[0] += 1
        enc.encode(seq[0], seq[0], payload)

    return {"verify": _time(verify, calls), "encode": _time(encode, calls)}


def run(cfg: Config, calls: int = 5000) -> dict[str, Any]:
    from redistro import kernels
    from redistro.config.hardware import load_hardware

    if not kernels.AVAILABLE:
        from redistro.errors import ConfigError

        raise ConfigError("redistro._kernels is not built: pip install -e . builds it")
    hw = load_hardware(cfg)
    rows: dict[str, Any] = {}
    for use, label in ((False, "numpy"), (True, "kernel")):
        rows.setdefault("chassis (both arms, no physics)", {})[label] = _chassis(
            cfg, hw, use, calls
        )
        d = _driver(cfg, hw, use, calls)
        rows.setdefault("driver sample()", {})[label] = d["sample"]
        rows.setdefault("driver send_torques()", {})[label] = d["send"]
        rows.setdefault("cartesian law, one arm", {})[label] = _law(cfg, use, calls)
        j = _joints(use, calls)
        rows.setdefault("joint pid", {})[label] = j["pid"]
        rows.setdefault("quintic reference", {})[label] = j["quintic"]
        w = _wire(use, calls)
        rows.setdefault("ddm record in: crc32 + tag", {})[label] = w["verify"]
        rows.setdefault("ddm record out: encoded, sealed", {})[label] = w["encode"]
    return {"calls": calls, "cpu_us_per_call": rows}


def print_figures(f: dict[str, Any], out: Any = sys.stdout) -> None:
    print(f"bench kernels: CPU per call, p50 / p99 [us], {f['calls']} calls each", file=out)
    for name, r in f["cpu_us_per_call"].items():
        a, b = r["numpy"], r["kernel"]
        print(
            f"  {name:34s} numpy {a['p50']:8.2f} / {a['p99']:8.2f}   kernel "
            f"{b['p50']:7.2f} / {b['p99']:7.2f}   x{a['p50'] / max(b['p50'], 0.01):.1f}",
            file=out,
        )

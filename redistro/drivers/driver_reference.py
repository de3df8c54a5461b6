"""The robot-level driver's decode in numpy: the reference the compiled
``driver_decode`` kernel (drivers/driver_kernel.c) is held to, and the path
taken when the kernels are off."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from redistro.drivers.io.dio import DioDriver
from redistro.drivers.io.force import ForceDriver
from redistro.drivers.io.registers import ENC_MODULO

if TYPE_CHECKING:
    from redistro.drivers.robot import RobotDriver

DOF = 7
_HALF = ENC_MODULO // 2
_MASK = ENC_MODULO - 1


def wrap(delta: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Signed changes between 24-bit counter readings (|change| < 2**23), per element."""
    out: np.ndarray[Any, Any] = ((delta + _HALF) & _MASK) - _HALF
    return out


def decode_numpy(d: RobotDriver) -> int:
    """The arithmetic of the ``driver_decode`` kernel (see it for the rules):
    0, -1 an incoherent snapshot to read again, or 1 + the joint whose
    counter jumped."""
    regs = d.regs
    recs = {a: regs.rec_in[a] for a in d.addresses}
    steps = [int(recs[a]["step"]) for a in d.enc]
    step = min(steps)
    st = d._state
    st["step"], st["coherent"] = step, min(steps) == max(steps)
    if not st["coherent"] and d._params["retry"]:
        return -1
    raw = np.zeros(DOF, dtype=np.int64)
    latch_raw = np.zeros(DOF, dtype=np.int64)
    for a, (js, axes) in d.enc.items():
        rec = recs[a]
        raw[js] = rec["counter"][axes]
        latch_raw[js] = rec["latch"][axes]
        d.latch_count[js] = rec["latch_count"][axes]
        d.latch_edge[js] = rec["latch_edge"][axes]
    if not st["have_ref"]:
        signed = np.where(raw >= ENC_MODULO // 2, raw - ENC_MODULO, raw)
        d._q_ref[...] = signed / d.counts_per_rad
        d._acc[:] = 0
        st["have_ref"] = 1
    else:
        delta = wrap(raw - d._raw)
        limit_rad_s = d._params["jump_limit_rad_s"]
        prev = int(st["prev_step"])
        if limit_rad_s > 0 and prev >= 0:
            n = max(1, step - prev)
            limit = limit_rad_s * d.counts_per_rad * n / d.physics_hz + 2
            bad = np.flatnonzero(np.abs(delta) > limit)
            if bad.size:
                j = int(bad[0])
                jump = d._jump
                jump["delta"], jump["limit"], jump["steps"] = delta[j], limit[j], n
                return j + 1
        d._acc += delta
    d._raw[...] = raw
    d.q[...] = d._q_ref + d._acc / d.counts_per_rad
    # a latched count is within half the counter's range of the present one
    d.latch_q[...] = d.q + wrap(latch_raw - raw) / d.counts_per_rad
    if d.has_tach:
        for a, (js, ch) in d.tach.items():
            d.qd[js] = recs[a]["code"][ch] * d.tach_scale[js]
    elif st["prev_step"] >= 0 and step > st["prev_step"]:
        dt = (step - int(st["prev_step"])) / d.physics_hz
        d.qd[...] = (d.q - d._prev_q) / dt
    st["prev_step"] = step
    d._prev_q[...] = d.q
    if d.has_torque:
        for a, (js, ch) in d.torque.items():
            d.tau[js] = recs[a]["code"][ch] * d.torque_scale[js]
    else:
        for a, (js, ch) in d.dac.items():
            d.tau[js] = recs[a]["readback"][ch] * d.dac_scale[js]
    for a, (js, bits) in d.home.items():
        d.home_levels[js] = DioDriver.bits(recs[a], bits)
    for a, (js, bits) in d.brake.items():
        d.brakes[js] = ~DioDriver.output_bits(recs[a], bits)
    d.wrench[:] = 0.0
    if d.hw.wrist is not None:
        d.wrench[...] = ForceDriver.wrench(recs[d.hw.wrist.address])
    return 0

"""The robot-level driver's compiled kernels (drivers/driver_kernel.c),
planned once over its register image and arena (:mod:`redistro.drivers.robot`;
the layouts: drivers/driver_layout.py)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from redistro import kernels
from redistro.drivers import driver_layout
from redistro.drivers.io.registers import BoardType

if TYPE_CHECKING:
    from redistro.drivers.robot import RobotDriver

DOF = 7


def driver_plans(d: RobotDriver) -> tuple[Any, Any]:
    """The driver's two kernels planned over its register image and
    arena: (driver_decode, driver_dac) plans."""
    regs, w = d.regs, d._wire
    enc, dac, adc, dio, force = (
        BoardType.ENCODER,
        BoardType.DAC,
        BoardType.ADC,
        BoardType.DIO,
        BoardType.FORCE,
    )
    at = regs.offsets

    def rows(kind: str) -> Any:
        return w[kind][:, 1] if len(w[kind]) else []

    def chs(kind: str) -> Any:
        return w[kind][:, 2] if len(w[kind]) else []

    none = np.full(DOF, -1, dtype=np.int64)
    # the wrist's strain and calibration registers (-1: no wrist)
    strain = np.full((), -1, driver_layout.ONE_OFFSET)
    cal = np.full((), -1, driver_layout.ONE_OFFSET)
    if d.hw.wrist is not None:
        wrist_row = [regs.row[d.hw.wrist.address]]
        strain["at"] = at(force, "in", "strain", wrist_row)[0]
        cal["at"] = at(force, "in", "calibration", wrist_row)[0]
    decode_plan = kernels.plan(
        "driver_decode",
        image=regs.image,
        step_off=at(enc, "in", "step", sorted(set(rows("encoder")))),
        counter_off=at(enc, "in", "counter", rows("encoder"), chs("encoder"), 4),
        latch_off=at(enc, "in", "latch", rows("encoder"), chs("encoder"), 4),
        latch_count_off=at(enc, "in", "latch_count", rows("encoder"), chs("encoder"), 4),
        latch_edge_off=at(enc, "in", "latch_edge", rows("encoder"), chs("encoder"), 1),
        tach_off=at(adc, "in", "code", rows("tach"), chs("tach"), 2) if d.has_tach else none,
        torque_off=at(adc, "in", "code", rows("torque"), chs("torque"), 2)
        if d.has_torque
        else none,
        readback_off=at(dac, "in", "readback", rows("dac"), chs("dac"), 2),
        home_word=at(dio, "in", "inputs", rows("home")),
        home_bit=np.ascontiguousarray(chs("home"), dtype=np.int64),
        brake_word=at(dio, "in", "outputs_readback", rows("brake")),
        brake_bit=np.ascontiguousarray(chs("brake"), dtype=np.int64),
        strain_off=strain,
        cal_off=cal,
        counts_per_rad=d.counts_per_rad,
        tach_scale=d.tach_scale,
        torque_scale=d.torque_scale,
        dac_scale=d.dac_scale,
        raw=d._raw,
        acc=d._acc,
        q_ref=d._q_ref,
        prev_q=d._prev_q,
        state=d._state,
        params=d._params,
        q=d.q,
        qd=d.qd,
        tau=d.tau,
        wrench=d.wrench,
        home=d.home_levels,
        brakes=d.brakes,
        latch_count=d.latch_count.view(np.uint8),
        latch_edge=d.latch_edge,
        latch_q=d.latch_q,
        out=d._jump,
    )
    dac_plan = kernels.plan(
        "driver_dac",
        image=regs.image,
        tau=d.tau_cmd,
        volts_per_nm=d.volts_per_nm,
        code_off=at(dac, "out", "code", rows("dac"), chs("dac"), 2),
        residual=d.dac_residual,
        carry=d.dac_carry,
    )
    return decode_plan, dac_plan

"""The simulated chassis' compiled kernels, planned once over its register
image and state (:mod:`redistro.plant.chassis`; the kernels:
plant/chassis_kernel.c), and the table that copies its truth out."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from redistro import kernels
from redistro.drivers.io import registers as R
from redistro.drivers.io.bank import TRUTH
from redistro.drivers.io.registers import BoardType

if TYPE_CHECKING:
    from redistro.plant.chassis import Chassis

DOF = 7
_AMPS_PER_CODE = R.DAC_FULL_SCALE_V / 2048  # volts per DAC code


def plan_kernels(ch: Chassis) -> tuple[Any, Any, Any]:
    """The chassis' two kernels planned over its image and state (their
    numpy reference: plant/chassis_reference.py), and the copy of its
    truth: (apply, sample, truth) plans."""
    truth_plan = kernels.plan("copy", src=ch.state.buffer, dst=ch.truth_image, table=ch._truth_copy)
    return _apply_plan(ch), _sample_plan(ch), truth_plan


def _every(ch: Chassis, t: BoardType) -> range:
    return range(len(ch.banks.inp[t]))


def _apply_plan(ch: Chassis) -> Any:
    """chassis_apply: the controller's outputs to the joints."""
    b = ch.banks
    enc, dac, dio = BoardType.ENCODER, BoardType.DAC, BoardType.DIO
    d, br = ch.dac, ch.brake_w

    at = b.offsets

    def every(t: BoardType) -> range:
        return _every(ch, t)

    copy = [  # the readbacks: what the DAC and DIO boards drive
        (
            b.offset(dac, "out", r, "code"),
            b.offset(dac, "in", r, "readback"),
            2 * R.DAC_CHANNELS,
            0,
        )
        for r in every(dac)
    ] + [
        (
            b.offset(dio, "out", r, "outputs"),
            b.offset(dio, "in", r, "outputs_readback"),
            4,
            R.DIO_MASK,
        )
        for r in every(dio)
    ]
    return kernels.plan(
        "chassis_apply",
        image=ch.image,
        brake_off=at(dio, "out", "outputs", br.rows),
        brake_bit=br.ch.astype(np.int64),
        dac_off=at(dac, "out", "code", d.rows, d.ch, 2),
        cut=ch._joint_cut,
        amps_per_code=_AMPS_PER_CODE * ch.motors.amps_per_volt,
        max_current=ch.motors.max_current_a,
        nm_per_amp=ch.motors.nm_per_amp,
        motor_tau=ch.motor_tau,
        brake=ch._brake,
        braked=ch.braked,
        copy=kernels.table("chassis_apply", "copy", copy),
        req_off=at(enc, "out", "preset_req", every(enc)),
        req_seen=ch.reg.requests_seen.view(np.uint8).reshape(-1),
    )


def _sample_plan(ch: Chassis) -> Any:
    """chassis_sample: the joints into the boards' in banks."""
    b = ch.banks
    enc, adc, dio, force = BoardType.ENCODER, BoardType.ADC, BoardType.DIO, BoardType.FORCE
    e, h = ch.enc, ch.home_w
    at = b.offsets

    def every(t: BoardType) -> range:
        return _every(ch, t)

    return kernels.plan(
        "chassis_sample",
        image=ch.image,
        q=ch.q,
        qd=ch.qd,
        tau=ch.tau,
        applied=ch.applied,
        motor_tau=ch.motor_tau,
        braked=ch.braked,
        held=ch.held,
        stopped=ch._stopped,
        counts_per_rad=ch.encoders.counts_per_rad,
        enc_offset=ch.encoders.offset,
        counts=ch.counts,
        counter_off=at(enc, "in", "counter", e.rows, e.ch, 4),
        home_center=ch.homes.center,
        home_on=ch.homes.on_within,
        home_off=ch.homes.off_beyond,
        switch=ch.homes.state,
        force=ch._home_force,
        home=ch.home,
        last_home=ch._last_home,
        edges=ch._edges,
        home_reg_off=at(enc, "in", "home", e.rows, e.ch, 1),
        dio_clear=at(dio, "in", "inputs", every(dio)),
        home_word=at(dio, "in", "inputs", h.rows),
        home_bit=h.ch.astype(np.int64),
        adc_src=ch.adc_src.astype(np.int64),
        adc_scale=np.ascontiguousarray(ch.adc_scale),
        adc_off=at(adc, "in", "code", ch.adc_rows, ch.adc_ch, 2),
        wrench=ch.wrenches,
        inverse=ch.wrists.inverse,
        noise=ch.wrists.noise,
        noise_at=ch.wrists.noise_at,
        strain_off=at(force, "in", "strain", ch.ft_rows),
        sample_off=at(force, "in", "sample", ch.ft_rows),
        step_off=np.concatenate([at(t, "in", "step", every(t)) for t in b.inp]),
        step=ch.step_rec,
    )


def truth_table(ch: Chassis) -> np.ndarray[Any, Any]:
    """What the truth records copy from the state: (src, dst, size) rows."""
    st, f = ch.state, TRUTH.fields
    assert f is not None
    rows: list[tuple[int, int, int]] = []
    wrist_of = {rig.name: k for rig, k in ch._wrist_rigs}
    for i, rig in enumerate(ch.rigs):
        at = i * TRUTH.itemsize
        rows.append((st.offset("step"), at + int(f["step"][1]), 8))
        for name, src, size in (
            ("q_rad", "q", 8),
            ("qd_rad_s", "qd", 8),
            ("tau_nm", "tau", 8),
            ("braked", "braked", 1),
            ("home", "switch", 1),
            ("encoder_offset_counts", "enc_offset", 8),
        ):
            rows.append((st.offset(src) + size * DOF * i, at + int(f[name][1]), size * DOF))
        k = wrist_of.get(rig.name)
        if k is not None:
            rows.append((st.offset("wrenches") + 48 * k, at + int(f["wrench_sensor"][1]), 48))
            rows.append((st.offset("tool_xyz") + 24 * k, at + int(f["tool_xyz_m"][1]), 24))
            rows.append((st.offset("tool_rot") + 72 * k, at + int(f["tool_rot"][1]), 72))
    return kernels.copy_table(rows)

"""The simulated chassis' per-step arithmetic in numpy: the reference the
compiled kernels (plant/chassis_kernel.c) are held to, and the path taken
when they are off (``REDISTRO_KERNELS=0``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from redistro.drivers.io import registers as R
from redistro.plant.world import BRAKE_STOPPED_RAD_S

if TYPE_CHECKING:
    from redistro.plant.chassis import Chassis

_AMPS_PER_CODE = R.DAC_FULL_SCALE_V / 2048  # volts per DAC code
count = np.count_nonzero  # on the hot path: a third of what ndarray.any() costs
HOME_AS_SWITCH, HOME_STUCK_ON = 0, 2


def apply_numpy(ch: Chassis, now_ns: int) -> None:
    """Controller outputs -> joints (the ``chassis_apply`` kernel's arithmetic)."""
    # fail-safe brakes: engaged unless their release output is on
    brake = ch._brake
    word = ch._word
    ch.reg.dio_outputs.take(ch.brake_w.rows, out=word)
    np.right_shift(word, ch._brake_bits, out=word)
    np.bitwise_and(word, 1, out=word)
    np.equal(word, 0, out=brake)
    np.logical_or(brake, ch._joint_cut, out=brake)  # the watchdog's relay drops them too
    # the amplifiers: DAC code -> current (saturated) -> joint torque;
    # inhibited while the joint's brake is on (interlock)
    d = ch.dac
    cur = ch._cur
    cur[...] = ch.reg.dac_code[d.rows, d.ch]
    np.multiply(cur, _AMPS_PER_CODE * ch.motors.amps_per_volt, out=cur)
    m = ch.motors
    np.minimum(cur, m.max_current_a, out=cur)
    np.maximum(cur, m.min_current_a, out=cur)
    np.multiply(cur, m.nm_per_amp, out=ch.motor_tau)
    np.copyto(ch.motor_tau, 0.0, where=brake)
    # what the boards say they drive
    ch.reg.dac_readback[...] = ch.reg.dac_code
    np.bitwise_and(ch.reg.dio_outputs, R.DIO_MASK, out=ch.reg.dio_readback)
    # encoder commands (presets, software latches): rare
    np.not_equal(ch.reg.enc_requests, ch.reg.requests_seen, out=ch.reg.req_changed)
    if count(ch.reg.req_changed):
        ch._encoder_commands()
    np.not_equal(brake, ch.braked, out=ch._changed)
    if count(ch._changed):
        ch._brakes_changed(brake, now_ns)


def sample_numpy(ch: Chassis) -> None:
    """Joint states -> the boards' in banks (the ``chassis_sample`` kernel's arithmetic)."""
    q, qd, n = ch.q, ch.qd, ch.n
    # PyBullet reports a braked joint's torque (its brake motor's), not a
    # torque-controlled one's: there the motor's is the joint's
    np.copyto(ch.tau, ch.motor_tau)
    np.copyto(ch.tau, ch.applied, where=ch.braked)
    # braked joints that have stopped: their brakes hold the angle from now
    # on (looked for only while a braked joint is not held yet)
    if ch._loose_any:
        np.abs(qd, out=ch._slow)
        np.less(ch._slow, BRAKE_STOPPED_RAD_S, out=ch._stopped)
        np.greater(ch.braked, ch.held, out=ch._loose)  # braked, not yet held
        np.logical_and(ch._stopped, ch._loose, out=ch._stopped)
        if count(ch._stopped):
            ch._settle()
        ch._loose_any = bool(count(np.greater(ch.braked, ch.held, out=ch._loose)))
    counts = ch.encoders.counts(q)
    ch.counts[...] = counts
    home = ch.home
    np.copyto(home, ch.homes.update(q))
    stuck = ch._home_force != HOME_AS_SWITCH
    if count(stuck):
        home[stuck] = ch._home_force[stuck] == HOME_STUCK_ON
    e = ch.enc
    ch.reg.enc_counter[e.rows, e.ch] = counts
    np.not_equal(home, ch._last_home, out=ch._edges)
    if count(ch._edges):  # a home input changed: its registers, its latches
        ch._home_edges(counts, registers=True)
    # torque sensors and tachometers -> ADC codes (rounded, saturated)
    src = ch._adc_in
    src[:n] = ch.tau
    src[n:] = qd
    v = ch._adc_v
    src.take(ch.adc_src, out=v)
    np.multiply(v, ch.adc_scale, out=v)
    np.rint(v, out=v)
    np.minimum(v, 32767, out=v)
    np.maximum(v, -32768, out=v)
    ch.reg.adc_code[ch.adc_rows, ch.adc_ch] = v
    if ch._wrist_rigs:
        ch.wrists.gauges_into(ch.wrenches, ch._strain)
        ch.reg.ft_strain[ch.ft_rows] = ch._strain
        ch.reg.ft_sample[ch.ft_rows] += 1
    for steps in ch.reg.steps_in:
        steps[...] = ch.step_count

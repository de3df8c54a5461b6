"""Device models of the plant and the register conversions (pure numpy)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from redistro.config.hardware import load_hardware
from redistro.config.loader import load_config
from redistro.drivers.io import registers as R
from redistro.plant.devices import Encoders, HomeSwitches, Motors, WristSensor

ROOT = Path(__file__).parents[2]
S = load_hardware(load_config(ROOT / "config" / "redistro.yaml"))["r1"].sensors


def test_motor_model_saturates_at_the_current_limit() -> None:
    m = Motors(S)
    tau = m.joint_torque_nm(np.full(7, 1.0))
    assert np.allclose(tau, 3.0 * 0.1 * np.asarray(S.gear_ratio))  # 3 A/V x Kt x gear
    big = m.joint_torque_nm(np.full(7, 10.0))
    assert np.allclose(big, np.asarray(S.max_current_a) * 0.1 * np.asarray(S.gear_ratio))
    assert np.all(m.joint_torque_nm(np.full(7, 1.0), enabled=False) == 0)


def test_encoder_counts_wrap_and_preset() -> None:
    e = Encoders(S, np.zeros(7), np.zeros(7))
    q = np.zeros(7)
    e.preset(0, 0.0, R.ENC_MODULO - 5)
    assert e.counts(q)[0] == R.ENC_MODULO - 5
    step = 10 / e.counts_per_rad[0]
    q[0] = step  # ten counts on: wrapped past zero
    assert e.counts(q)[0] == 5
    assert R.wrap_delta(5, R.ENC_MODULO - 5) == 10
    assert R.wrap_delta(R.ENC_MODULO - 5, 5) == -10


def test_power_on_disturbance_offsets_the_counters() -> None:
    d = np.array([0.01, 0, 0, 0, 0, 0, -0.02])
    e = Encoders(S, np.zeros(7), d)
    signed = (e.counts(np.zeros(7)) + R.ENC_MODULO // 2) % R.ENC_MODULO - R.ENC_MODULO // 2
    assert np.allclose(signed / e.counts_per_rad, d, atol=2 / e.counts_per_rad)


def test_home_switch_hysteresis() -> None:
    h = HomeSwitches(S)
    half, hyst = S.home_window_rad[0] / 2, S.home_hysteresis_rad[0] / 2
    sweep = np.linspace(-0.1, 0.1, 2001)
    states = [bool(h.update(np.full(7, q))[0]) for q in sweep]
    on = sweep[states.index(True)]
    off = sweep[len(states) - states[::-1].index(True)]
    assert abs(on - (-(half - hyst))) < 2e-4
    assert abs(off - (half + hyst)) < 2e-4
    back = [bool(h.update(np.full(7, q))[0]) for q in sweep[::-1]]
    assert abs(sweep[::-1][back.index(True)] - (half - hyst)) < 2e-4


def test_wrist_gauges_invert_the_calibration() -> None:
    c = np.asarray(S.ft_calibration)
    w = WristSensor(c, np.zeros(6), 0.0, 0.0, seed=1)
    wrench = np.array([1.0, -2.0, 20.0, 0.1, -0.2, 0.05])
    back = c @ w.gauges(wrench).astype(np.float64)
    assert np.allclose(back, wrench, atol=2e-3)


def test_converters_round_and_saturate() -> None:
    assert R.dac_code(10.0) == R.DAC_CODE_MAX and R.dac_code(-10.0) == R.DAC_CODE_MIN
    assert R.dac_code(20.0) == R.DAC_CODE_MAX
    assert abs(R.dac_volts(R.dac_code(1.2345)) - 1.2345) <= 10 / 2048
    assert abs(R.adc_volts(R.adc_code(-3.3)) + 3.3) <= 10 / 32768


class _Reactions:
    """PyBullet's three calls ``World.read_wrist`` makes, with the wrist
    joint's reaction set by the test (the sensor level, no tool weight)."""

    def __init__(self) -> None:
        self.fz = 0.0

    def getLinkState(self, *_a: object, **_k: object) -> tuple[object, ...]:
        return (None,) * 4 + ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))

    def getMatrixFromQuaternion(self, _q: object) -> tuple[float, ...]:
        return (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)

    def getJointState(self, *_a: object, **_k: object) -> tuple[object, ...]:
        return (0.0, 0.0, (0.0, 0.0, -self.fz, 0.0, 0.0, 0.0), 0.0)


def _wrist(bandwidth_hz: float) -> tuple[object, _Reactions]:
    from math import exp, pi

    from redistro.plant.world import Arm, World

    world = World.__new__(World)  # the read alone: no physics
    pb = _Reactions()
    world.pb, world.client, world.dt = pb, 0, 1e-3
    world.ft_alpha = 1.0 - exp(-2 * pi * bandwidth_hz * world.dt) if bandwidth_hz else 1.0
    arm = Arm("r2", 0, [], 0, 0, 0.0, np.zeros(3), np.zeros(7, bool), np.zeros(7))
    cfg = load_config(ROOT / "config" / "redistro.yaml")
    assert cfg.plant.ft_bandwidth_hz == 100.0  # the default the sessions use
    return (world, arm), pb


def test_the_wrist_sensor_reads_through_its_bandwidth() -> None:
    """A contact the rigid physics resolves in one 1 ms step is read at a
    fraction of its height (the sensor's low-pass); a sustained force is
    read whole within a few ms; a bandwidth of 0 reads every step as it is."""
    (world, arm), pb = _wrist(100.0)
    xyz, rot9, wrench = np.zeros(3), np.zeros(9), np.zeros(6)

    def read(fz: float) -> float:
        pb.fz = fz
        world.read_wrist(arm, xyz, rot9, wrench)  # type: ignore[attr-defined]
        return float(wrench[2])

    for _ in range(20):
        read(6.0)  # pressing 6 N
    assert abs(wrench[2] - 6.0) < 0.01
    spike = read(80.0)  # one step's impact
    assert 30.0 < spike < 45.0, spike
    after = [read(6.0) for _ in range(10)]
    assert after[0] < spike and abs(after[-1] - 6.0) < 0.1, after
    held = [read(150.0) for _ in range(5)]  # a sustained push: 95 % within 5 ms
    assert held[2] > 120.0 and held[-1] > 0.95 * 150.0, held

    (world, arm), pb = _wrist(0.0)
    wrench[:] = 0.0
    read(6.0)
    assert read(80.0) == 80.0 and read(6.0) == 6.0

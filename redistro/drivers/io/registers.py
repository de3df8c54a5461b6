"""The I/O chassis datasheet: every board's registers, declared once.

Each board has two register banks: ``in`` (the board writes: counters,
conversions, input bits) and ``out`` (the controller writes: DAC codes,
output bits, preset and latch requests). A request that has an effect inside
the board (an encoder preset, a software latch) is a *sequence-numbered
command*: the controller writes the argument, then bumps the request counter;
the board acts once per new count and echoes it in its ``in`` bank. The same
banks travel over every backplane (shared-memory register bank or CAN frames).

The simulated boards in :mod:`redistro.plant` implement this datasheet; the
I/O module drivers in this package speak it. Nothing else knows registers.
"""

from __future__ import annotations

import enum
from typing import Any

import numpy as np


class BoardType(enum.IntEnum):
    NONE = 0
    ENCODER = 1  # 4-axis 24-bit quadrature encoder counter
    DAC = 2  # 16-channel 12-bit bipolar +-10 V
    ADC = 3  # 16-channel 16-bit bipolar +-10 V
    DIO = 4  # 24 inputs, 24 outputs
    FORCE = 5  # 6-axis force/torque sensor receiver


BOARD_NAMES = {t.name.lower(): t for t in BoardType if t != BoardType.NONE}

# -- board constants (as the hardware table) --
ENC_AXES = 4
ENC_BITS = 24
ENC_MODULO = 1 << ENC_BITS
DAC_CHANNELS = 16
DAC_BITS = 12
DAC_FULL_SCALE_V = 10.0
DAC_CODE_MAX = (1 << (DAC_BITS - 1)) - 1  # 2047 -> +10 V * 2047/2048
DAC_CODE_MIN = -(1 << (DAC_BITS - 1))
ADC_CHANNELS = 16
ADC_BITS = 16
ADC_FULL_SCALE_V = 10.0
DIO_BITS = 24
DIO_MASK = (1 << DIO_BITS) - 1
FT_AXES = 6
FT_STRAIN_MAX = (1 << 23) - 1  # 24-bit signed gauge counts

# Board status bits (in every ``in`` bank).
STATUS_OK = 1
STATUS_FAULT = 2

# Encoder latch sources (per axis, ``latch_mode``).
LATCH_SOFTWARE = 0  # on a new ``latch_req`` count
LATCH_HOME_EDGES = 1  # on every edge of the axis's home (index) input, both directions

EDGE_RISING = 1
EDGE_FALLING = 2

# Every ``in`` bank starts with the same three words.
_IN_HEADER = [("board_type", "<u2"), ("channels", "<u2"), ("status", "<u4"), ("step", "<u8")]

ENCODER_IN = np.dtype(
    [
        *_IN_HEADER,
        ("counter", "<u4", ENC_AXES),  # 24-bit, wraps modulo 2**24
        ("latch", "<u4", ENC_AXES),  # counter captured by the last latch
        ("latch_count", "<u4", ENC_AXES),  # latches so far (hardware and software)
        ("latch_edge", "u1", ENC_AXES),  # EDGE_RISING / EDGE_FALLING of the last home latch
        ("home", "u1", ENC_AXES),  # level of each axis's home (index) input
        ("preset_ack", "<u4", ENC_AXES),  # last preset_req applied
    ]
)
ENCODER_OUT = np.dtype(
    [
        ("preset_value", "<u4", ENC_AXES),
        ("preset_req", "<u4", ENC_AXES),
        ("latch_req", "<u4", ENC_AXES),
        ("latch_mode", "u1", ENC_AXES),
    ]
)

DAC_IN = np.dtype([*_IN_HEADER, ("readback", "<i2", DAC_CHANNELS)])
# watchdog: written with a new non-zero value on every write of the bank; the
# board's amplifiers stay enabled while it keeps moving (0: no watchdog)
DAC_OUT = np.dtype([("code", "<i2", DAC_CHANNELS), ("watchdog", "<u4")])

ADC_IN = np.dtype([*_IN_HEADER, ("code", "<i2", ADC_CHANNELS)])
ADC_OUT = np.dtype([("reserved", "<u4")])

DIO_IN = np.dtype([*_IN_HEADER, ("inputs", "<u4"), ("outputs_readback", "<u4")])
DIO_OUT = np.dtype([("outputs", "<u4")])

FORCE_IN = np.dtype(
    [
        *_IN_HEADER,
        ("strain", "<i4", FT_AXES),  # raw gauge counts
        ("sample", "<u4"),  # conversions so far
        ("calibration", "<f4", (FT_AXES, FT_AXES)),  # wrench [N, N m] = C @ strain
    ]
)
FORCE_OUT = np.dtype([("reserved", "<u4")])

BANKS: dict[BoardType, tuple[np.dtype[Any], np.dtype[Any]]] = {
    BoardType.ENCODER: (ENCODER_IN, ENCODER_OUT),
    BoardType.DAC: (DAC_IN, DAC_OUT),
    BoardType.ADC: (ADC_IN, ADC_OUT),
    BoardType.DIO: (DIO_IN, DIO_OUT),
    BoardType.FORCE: (FORCE_IN, FORCE_OUT),
}

CHANNELS = {
    BoardType.ENCODER: ENC_AXES,
    BoardType.DAC: DAC_CHANNELS,
    BoardType.ADC: ADC_CHANNELS,
    BoardType.DIO: DIO_BITS,
    BoardType.FORCE: FT_AXES,
}


def dac_code(volts: np.ndarray[Any, Any] | float) -> np.ndarray[Any, Any]:
    """Volts to DAC codes (rounded, saturated at the converter's range)."""
    code = np.rint(np.asarray(volts) * (2048 / DAC_FULL_SCALE_V))
    return np.clip(code, DAC_CODE_MIN, DAC_CODE_MAX).astype(np.int16)


def dac_volts(code: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    return np.asarray(code, dtype=np.float64) * (DAC_FULL_SCALE_V / 2048)


def adc_code(volts: np.ndarray[Any, Any] | float) -> np.ndarray[Any, Any]:
    code = np.rint(np.asarray(volts) * (32768 / ADC_FULL_SCALE_V))
    return np.clip(code, -32768, 32767).astype(np.int16)


def adc_volts(code: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    return np.asarray(code, dtype=np.float64) * (ADC_FULL_SCALE_V / 32768)


def wrap_delta(new: int, old: int) -> int:
    """The signed change between two 24-bit counter readings (|change| < 2**23)."""
    d = (new - old) % ENC_MODULO
    return d - ENC_MODULO if d >= ENC_MODULO // 2 else d

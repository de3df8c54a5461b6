"""Per-robot hardware configs: the I/O interface config and the sensor/actuator config.

As in the paper's data tables, each robot has two files:

- the **I/O interface config** (``r1.io.yaml``): the boards the robot uses
  (type and chassis address) and, per joint, which channel carries what:
  encoder axis, DAC channel, home switch input bit, brake output bit,
  optional torque-sensor and tachometer ADC channels; and the wrist
  force-sensor receiver;
- the **sensor/actuator config** (``r1.sensors.yaml``): per joint, counts per
  motor revolution, gear ratio, amplifier and motor constants, brake torque,
  sensor scalings and the home switch window; the wrist sensor's calibration.

Channels are written ``board.channel`` (``enc_a.2``, ``dio.9``). A channel
used twice, a board that is missing or of the wrong type, or a channel out of
a board's range is a ConfigError naming the file and the field.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from redistro.config.model import Config, RobotConfig
from redistro.config.validate import build
from redistro.drivers.io.registers import BOARD_NAMES, CHANNELS, DIO_BITS
from redistro.errors import ConfigError

DOF = 7
BoardKind = Literal["encoder", "dac", "adc", "dio", "force"]


@dataclass(frozen=True)
class BoardConfig:
    type: BoardKind
    address: int = field(metadata={"ge": 1, "le": 255})


@dataclass(frozen=True)
class JointChannels:
    """Where one joint is wired. Empty strings mean 'not fitted'.

    brake: the DIO output that *releases* the joint's brake. Brakes are
    fail-safe: engaged whenever that output is off (power-on, a dead driver).
    """

    encoder: str
    dac: str
    home: str
    brake: str
    torque: str = ""
    tach: str = ""


@dataclass(frozen=True)
class IOConfig:
    boards: dict[str, BoardConfig]
    joints: list[JointChannels] = field(metadata={"len": DOF})
    wrist: str = ""
    # the DIO output that closes the flange's gripper (on: closed; off, the
    # board's power-on state: open). Empty: no gripper fitted.
    gripper: str = ""


@dataclass(frozen=True)
class SensorsConfig:
    """Per joint (lists of 7) unless noted.

    counts_per_rev: encoder counts per motor revolution (after quadrature).
    gear_ratio: motor revolutions per joint revolution.
    torque_constant_nm_a: motor torque per amplifier current [N m / A].
    amps_per_volt: amplifier transconductance [A / V of DAC output].
    max_current_a: amplifier current limit [A].
    brake_torque_nm: holding torque of the joint brake [N m, joint side].
    tach_volts_per_rad_s: tachometer output per joint speed [V / (rad/s)].
    torque_volts_per_nm: torque-sensor output per joint torque [V / N m].
    home_angle_rad: centre of the home switch window (the joint's zero mark).
    home_window_rad: width of the home switch window.
    home_hysteresis_rad: the switch turns on this much inside the window
        edges and off this much outside them (half each side).
    ft_calibration: 6x6 matrix, wrench [N, N m] = C @ gauge counts.
    dac_error_feedback: the driver carries the joint's DAC rounding error
        into its next code (a torque under one code comes out on average);
        off, each code is the torque rounded (a light link that one code
        kicks hard is quieter so).
    """

    counts_per_rev: list[int] = field(metadata={"len": DOF, "ge": 4})
    gear_ratio: list[float] = field(metadata={"len": DOF, "gt": 0})
    torque_constant_nm_a: list[float] = field(metadata={"len": DOF, "gt": 0})
    amps_per_volt: list[float] = field(metadata={"len": DOF, "gt": 0})
    max_current_a: list[float] = field(metadata={"len": DOF, "gt": 0})
    brake_torque_nm: list[float] = field(metadata={"len": DOF, "gt": 0})
    tach_volts_per_rad_s: list[float] = field(metadata={"len": DOF, "gt": 0})
    torque_volts_per_nm: list[float] = field(metadata={"len": DOF, "gt": 0})
    home_angle_rad: list[float] = field(metadata={"len": DOF})
    home_window_rad: list[float] = field(metadata={"len": DOF, "gt": 0})
    home_hysteresis_rad: list[float] = field(metadata={"len": DOF, "ge": 0})
    ft_calibration: list[list[float]] = field(metadata={"len": 6})
    dac_error_feedback: list[bool] = field(
        default_factory=lambda: [True] * DOF, metadata={"len": DOF}
    )


@dataclass(frozen=True)
class Channel:
    board: str  # board name in the I/O config
    address: int
    index: int  # axis, channel or bit


@dataclass(frozen=True)
class JointWiring:
    encoder: Channel
    dac: Channel
    home: Channel
    brake: Channel
    torque: Channel | None
    tach: Channel | None


@dataclass(frozen=True)
class RobotHardware:
    """A robot's hardware, checked: its I/O config resolved to channels, and its
    sensor/actuator config."""

    name: str
    io: IOConfig
    sensors: SensorsConfig
    joints: list[JointWiring]
    wrist: Channel | None
    io_path: str
    sensors_path: str
    gripper: Channel | None = None

    def boards(self) -> dict[int, str]:
        """address -> board type name."""
        return {b.address: b.type for b in self.io.boards.values()}


def by_board(channels: list[Channel | None]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Joints grouped by the board they are wired to: address -> (joint
    indices, channel indices), for vectorized access to a board's registers."""
    out: dict[int, tuple[list[int], list[int]]] = {}
    for j, ch in enumerate(channels):
        if ch is not None:
            js, ks = out.setdefault(ch.address, ([], []))
            js.append(j)
            ks.append(ch.index)
    return {a: (np.array(js), np.array(ks)) for a, (js, ks) in out.items()}


def _resolve(base: Path, rel: str) -> Path:
    p = Path(rel)
    return p if p.is_absolute() else base / p


def _channel(
    io: IOConfig,
    text: str,
    kind: str,
    where: str,
    origin: str,
    used: dict[tuple[int, str, int], str],
) -> Channel:
    board, sep, idx = text.partition(".")
    if not sep or not (idx.isascii() and idx.isdigit()):
        raise ConfigError(
            f"{origin}: {where}: expected board.channel (e.g. {kind}.0), got {text!r}"
        )
    if board not in io.boards:
        raise ConfigError(
            f"{origin}: {where}: no board named {board!r} (boards: {', '.join(sorted(io.boards))})"
        )
    b = io.boards[board]
    if b.type != kind:
        raise ConfigError(f"{origin}: {where}: board {board} is a {b.type} board, not {kind}")
    index = int(idx)
    limit = DIO_BITS if kind == "dio" else CHANNELS[BOARD_NAMES[kind]]
    if not 0 <= index < limit:
        raise ConfigError(f"{origin}: {where}: channel {index} out of range 0..{limit - 1}")
    # DIO inputs and outputs are separate registers: a bit may be used once each way.
    direction = "out" if where.endswith((".brake", "gripper")) else "in"
    key = (b.address, direction, index)
    if key in used:
        raise ConfigError(f"{origin}: {where}: channel {text} already used by {used[key]}")
    used[key] = where
    return Channel(board, b.address, index)


def check_io(io: IOConfig, origin: str) -> tuple[list[JointWiring], Channel | None, Channel | None]:
    """The joints' wires, the wrist sensor's receiver and the gripper's output."""
    addresses: dict[int, str] = {}
    for name, b in io.boards.items():
        if b.address in addresses:
            raise ConfigError(
                f"{origin}: boards.{name}.address: {b.address} already used by "
                f"boards.{addresses[b.address]}"
            )
        addresses[b.address] = name
    used: dict[tuple[int, str, int], str] = {}
    joints = []
    for j, jc in enumerate(io.joints):
        at = f"joints[{j}]"
        joints.append(
            JointWiring(
                encoder=_channel(io, jc.encoder, "encoder", f"{at}.encoder", origin, used),
                dac=_channel(io, jc.dac, "dac", f"{at}.dac", origin, used),
                home=_channel(io, jc.home, "dio", f"{at}.home", origin, used),
                brake=_channel(io, jc.brake, "dio", f"{at}.brake", origin, used),
                torque=_channel(io, jc.torque, "adc", f"{at}.torque", origin, used)
                if jc.torque
                else None,
                tach=_channel(io, jc.tach, "adc", f"{at}.tach", origin, used) if jc.tach else None,
            )
        )
    wrist = None
    if io.wrist:
        if io.wrist not in io.boards:
            raise ConfigError(f"{origin}: wrist: no board named {io.wrist!r}")
        b = io.boards[io.wrist]
        if b.type != "force":
            raise ConfigError(f"{origin}: wrist: board {io.wrist} is a {b.type} board, not force")
        wrist = Channel(io.wrist, b.address, 0)
    gripper = _channel(io, io.gripper, "dio", "gripper", origin, used) if io.gripper else None
    return joints, wrist, gripper


def load_robot(name: str, robot: RobotConfig, base: Path, origin: str) -> RobotHardware:
    from redistro.config.loader import read_yaml

    if not robot.io or not robot.sensors:
        raise ConfigError(f"{origin}: robots.{name}: needs both io and sensors files")
    io_path = _resolve(base, robot.io)
    sensors_path = _resolve(base, robot.sensors)
    io = build(IOConfig, read_yaml(io_path), origin=str(io_path))
    sensors = build(SensorsConfig, read_yaml(sensors_path), origin=str(sensors_path))
    for i, row in enumerate(sensors.ft_calibration):
        if len(row) != 6:
            raise ConfigError(
                f"{sensors_path}: ft_calibration[{i}]: expected a list of exactly 6 items, "
                f"got {row!r}"
            )
    joints, wrist, gripper = check_io(io, str(io_path))
    return RobotHardware(name, io, sensors, joints, wrist, str(io_path), str(sensors_path), gripper)


def load_hardware(cfg: Config, base: Path | str | None = None) -> dict[str, RobotHardware]:
    """Every robot's hardware files, read and checked; board addresses must not
    collide between robots (they share one chassis); the safety limits within
    the hardware's ratings and the arm model's joint limits."""
    base_dir = Path(base) if base is not None else Path(cfg.source).parent
    out: dict[str, RobotHardware] = {}
    owner: dict[int, str] = {}
    for name, robot in cfg.robots.items():
        hw = load_robot(name, robot, base_dir, cfg.source)
        for bname, b in hw.io.boards.items():
            if b.address in owner:
                raise ConfigError(
                    f"{hw.io_path}: boards.{bname}.address: {b.address} is already "
                    f"a board of robot {owner[b.address]}"
                )
            owner[b.address] = name
        out[name] = hw
    for key, table in (
        ("plant.encoder_disturbance_rad", cfg.plant.encoder_disturbance_rad),
        ("plant.ft_bias", cfg.plant.ft_bias),
    ):
        for rname in table:
            if rname not in cfg.robots:
                raise ConfigError(f"{cfg.source}: {key}.{rname}: no robot named {rname!r}")
    for oname in cfg.plant.objects:
        if oname not in cfg.workcell.objects:
            raise ConfigError(
                f"{cfg.source}: plant.objects.{oname}: no object named {oname!r} in "
                f"workcell.objects"
            )
    from redistro.config.limits import check_ratings

    check_ratings(cfg, out)
    return out

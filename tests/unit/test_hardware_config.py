from __future__ import annotations

from pathlib import Path

import pytest

from redistro.config.hardware import load_hardware
from redistro.config.loader import load_config
from redistro.errors import ConfigError

ROOT = Path(__file__).parents[2]
IO = (ROOT / "config" / "robots" / "r1.io.yaml").read_text()


def test_shipped_hardware_loads() -> None:
    hw = load_hardware(load_config(ROOT / "config" / "redistro.yaml"))
    assert set(hw) == {"r1", "r2"}
    assert hw["r2"].joints[0].tach is not None and hw["r1"].joints[0].tach is None
    assert hw["r1"].wrist is not None


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            "dac: dac.1,",
            "dac: dac.0,",
            r"joints\[1\]\.dac: channel dac\.0 already used by joints\[0\]\.dac",
        ),
        ("encoder: enc_a.2", "encoder: enc_c.2", r"joints\[2\]\.encoder: no board named 'enc_c'"),
        ("home: dio.3,", "home: dac.3,", r"joints\[3\]\.home: board dac is a dac board, not dio"),
        ("dac: dac.4,", "dac: dac.16,", r"joints\[4\]\.dac: channel 16 out of range 0\.\.15"),
        (
            "address: 17}",
            "address: 16}",
            r"boards\.enc_b\.address: 16 already used by boards\.enc_a",
        ),
        ("wrist: ft", "wrist: dac", r"wrist: board dac is a dac board, not force"),
        ("encoder: enc_a.0", "encoder: 3", r"joints\[0\]\.encoder: expected a string"),
    ],
)
def test_bad_io_config_names_the_field(tmp_path: Path, old: str, new: str, message: str) -> None:
    assert old in IO
    bad = tmp_path / "r1.io.yaml"
    bad.write_text(IO.replace(old, new, 1))
    cfg = load_config(ROOT / "config" / "redistro.yaml", [f"robots.r1.io={bad}"])
    with pytest.raises(ConfigError, match=message) as info:
        load_hardware(cfg)
    assert str(bad) in str(info.value)
    assert "\n" not in str(info.value)


def test_boards_shared_between_robots_are_refused(tmp_path: Path) -> None:
    bad = tmp_path / "r2.io.yaml"
    text = (ROOT / "config" / "robots" / "r2.io.yaml").read_text()
    bad.write_text(text.replace("address: 33}", "address: 32}"))
    cfg = load_config(ROOT / "config" / "redistro.yaml", [f"robots.r2.io={bad}"])
    with pytest.raises(
        ConfigError, match=r"boards\.dac\.address: 32 is already a board of robot r1"
    ):
        load_hardware(cfg)


def test_sensor_lists_need_seven_values(tmp_path: Path) -> None:
    text = (ROOT / "config" / "robots" / "r1.sensors.yaml").read_text()
    bad = tmp_path / "r1.sensors.yaml"
    bad.write_text(text.replace("gear_ratio:          [100, 100,", "gear_ratio:          [100,"))
    cfg = load_config(ROOT / "config" / "redistro.yaml", [f"robots.r1.sensors={bad}"])
    with pytest.raises(ConfigError, match=r"gear_ratio: expected a list of exactly 7 items"):
        load_hardware(cfg)

from __future__ import annotations

import json
from pathlib import Path

import pytest

from redistro.drivers import positions
from redistro.drivers.positions import PositionsUnknown

Q = {"r1": [0.1 * i for i in range(7)], "r2": [-0.1 * i for i in range(7)]}


def test_round_trip_and_atomic_replace(tmp_path: Path) -> None:
    p = tmp_path / "positions.json"
    positions.write(p, "s1", Q, clean=True)
    got = positions.read(p, ["r1", "r2"])
    assert got.session == "s1" and got.clean and got.q_rad == Q
    positions.write(p, "s2", Q, clean=True)
    assert positions.read(p).session == "s2"
    assert [e.name for e in tmp_path.iterdir()] == ["positions.json"]  # no temporary left


@pytest.mark.parametrize(
    ("damage", "reason"),
    [
        (lambda p: p.unlink(), "missing"),
        (lambda p: p.write_text(p.read_text()[:40]), "corrupt"),
        (lambda p: p.write_text(p.read_text().replace("0.1", "0.2", 1)), "corrupt"),
        (lambda p: p.write_text("[]"), "corrupt"),
    ],
)
def test_untrusted_files_are_reported(tmp_path: Path, damage, reason: str) -> None:  # type: ignore[no-untyped-def]
    p = tmp_path / "positions.json"
    positions.write(p, "s1", Q, clean=True)
    damage(p)
    with pytest.raises(PositionsUnknown) as info:
        positions.read(p)
    assert info.value.reason == reason
    assert str(p) in str(info.value)


def test_unclean_shutdown_is_not_trusted(tmp_path: Path) -> None:
    p = tmp_path / "positions.json"
    positions.write(p, "s1", Q, clean=False)
    with pytest.raises(PositionsUnknown, match="unclean"):
        positions.read(p)


def test_missing_robot_and_bad_values(tmp_path: Path) -> None:
    p = tmp_path / "positions.json"
    positions.write(p, "s1", {"r1": Q["r1"]}, clean=True)
    with pytest.raises(PositionsUnknown, match="no positions for robot r2"):
        positions.read(p, ["r1", "r2"])
    doc = json.loads(p.read_text())
    doc["q_rad"]["r1"] = [1.0] * 6
    body = {k: v for k, v in doc.items() if k != "sha256"}
    doc["sha256"] = positions._digest(body)
    p.write_text(json.dumps(doc))
    with pytest.raises(PositionsUnknown, match="7 finite numbers"):
        positions.read(p)

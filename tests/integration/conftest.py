"""Fixtures of the integration tests that several modules share."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.helpers import LOCKSTEP, run_cli


@pytest.fixture(scope="session")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A runs folder whose positions files are known (a short self-calibration,
    in lockstep); tests copy it (positions and the arms' pose) before they
    move the arms."""
    runs = tmp_path_factory.mktemp("calibrated") / "runs"
    done = run_cli(
        *LOCKSTEP,
        "--set",
        f"session.runs_dir={runs}",
        "session",
        "tasks/self_calibration_short.yaml",
        "--out",
        str(runs.parent / "cal"),
        timeout=240,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return runs

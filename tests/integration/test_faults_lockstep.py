"""The fault harness's scenarios whose verdict is not a time, in lockstep.

`redistro faults --clock lockstep` runs every scenario of the catalogue
whose verdict is what the session did (refused the bad records, froze on
the bad command, ended ``ok`` or was refused), not how soon: the sessions
are paced by the plant, beside the unit tests at the default scheduling.
What froze after the fault is told by plant step. The scenarios whose
verdict is a time run in real time (`test_faults.py`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from redistro.faults.catalogue import CATALOGUE
from tests.helpers import LOCKSTEP, run_cli
from tests.integration.test_faults import campaign, check_row, check_table

pytestmark = [pytest.mark.slow, pytest.mark.timeout(3600)]
UNTIMED = [s.name for s in CATALOGUE if not s.timed]


@pytest.fixture(scope="module")
def table(calibrated: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    tmp = tmp_path_factory.mktemp("faults_lockstep")
    return campaign(calibrated, tmp, *LOCKSTEP, "faults", timeout=3000)


@pytest.mark.parametrize("name", UNTIMED)
def test_scenario(table: dict[str, Any], name: str) -> None:
    done = table["done"]
    assert name in table["rows"], done.stdout[-3000:] + done.stderr[-3000:]
    row = table["rows"][name]
    check_row(name, row)
    if "all_frozen" in row:  # a session's: judged by plant step
        assert row.get("clock") == "lockstep", row
        # every node's end seen by the plant at once: no tick waited out
        assert row.get("waits_missed") == 0, row


def test_the_table_leaves_the_timed_scenarios_to_real_time(table: dict[str, Any]) -> None:
    check_table(table, UNTIMED)
    doc = table["doc"]
    assert doc["clock"] == "lockstep"
    assert doc["left_out"] == [s.name for s in CATALOGUE if s.timed]
    assert f"in lockstep: {len(UNTIMED)} scenarios" in table["done"].stdout


def test_a_timed_scenario_is_refused_in_lockstep_in_one_line() -> None:
    done = run_cli("faults", "--clock", "lockstep", "--only", "kill-ssc-worker", timeout=60)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "--only kill-ssc-worker: its verdict is a time" in lines[0], lines

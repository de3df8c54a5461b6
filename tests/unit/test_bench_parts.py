from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from redistro.bench.baseline import cpu_steal_ticks, histogram_percentiles, steal_report
from redistro.bench.cycle import parse_stages
from redistro.errors import ConfigError
from redistro.process.spec import NodeSpec, WorkerSpec
from redistro.process.stats import Samples

CYCLICTEST = """# /dev/cpu_dma_latency set to 0us
000000 000000
000010 000050
000020 000049
000900 000001
# Total: 000000100
# Min Latencies: 00010
# Avg Latencies: 00024
# Max Latencies: 00900
# Histogram Overflows: 00000
"""


def test_cyclictest_histogram_percentiles() -> None:
    stats = histogram_percentiles(CYCLICTEST)
    assert stats == {"p50": 10.0, "p99": 20.0, "max": 900.0, "samples": 100}
    stats = histogram_percentiles(CYCLICTEST, period_us=500)
    assert stats is not None and stats["over_period_fraction"] == 0.01
    assert histogram_percentiles("garbage") is None


def test_stage_specs() -> None:
    assert parse_stages(None, 3) == [0, 1, 2]
    assert parse_stages("parallel", 3) == [0, 0, 0]
    assert parse_stages("2,1", 3) == [0, 0, 1]
    with pytest.raises(ConfigError):
        parse_stages("2,2", 3)
    with pytest.raises(ConfigError):
        parse_stages("a", 3)


def test_node_spec_groups_stages_and_round_trips(tmp_path) -> None:  # type: ignore[no-untyped-def]
    spec = NodeSpec(
        session_id="s",
        node="n",
        kind="bench",
        rate_hz=100.0,
        heartbeat_limit_cycles=5,
        workers=[
            WorkerSpec("a", "busy", 0),
            WorkerSpec("b", "busy", 1),
            WorkerSpec("c", "busy", 1),
        ],
    )
    assert spec.stages() == [[0], [1, 2]]
    path = tmp_path / "spec.json"
    spec.save(path)
    assert NodeSpec.load(path) == spec


def test_samples_summary() -> None:
    s = Samples(size=4)
    for v in (1000, 2000, 3000, 4000, 5000):  # ring keeps the last 4
        s.add(v)
    assert s.count == 5
    assert sorted(s.values_ns()) == [2000, 3000, 4000, 5000]
    out = s.summary_us()
    assert out["max"] == 5.0 and out["p50"] == pytest.approx(3.5)
    assert Samples().summary_us() == {"p50": 0.0, "p99": 0.0, "max": 0.0}
    assert np.isfinite(out["p99"])


def test_host_steal_from_proc_stat(tmp_path: Path) -> None:
    stat = tmp_path / "stat"
    stat.write_text(
        "cpu  10 0 5 100 0 0 0 30 0 0\n"
        "cpu0 5 0 2 50 0 0 0 10 0 0\n"
        "cpu1 5 0 3 50 0 0 0 20 0 0\n"
        "intr 1 2 3\n"
    )
    before = cpu_steal_ticks(str(stat))
    assert before == {"cpu0": 10, "cpu1": 20}  # the total line is left out
    hz = os.sysconf("SC_CLK_TCK")
    after = {"cpu0": 10 + hz, "cpu1": 20}  # one second stolen from cpu0
    r = steal_report(before, after, seconds=10.0)
    assert r["ms"] == {"cpu0": 1000.0, "cpu1": 0.0}
    assert r["percent_of_run"]["cpu0"] == 10.0
    assert cpu_steal_ticks(str(tmp_path / "missing")) == {}
    assert cpu_steal_ticks()  # this machine's kernel reports it


def test_group_figures_from_a_summary() -> None:
    """bench group puts a session's own figures side by side: per process,
    the node's CPU as the sum of its processes, the group's with the plant
    and the log writers."""
    from redistro.bench.group import figures

    def worker(name: str, cpu: float) -> dict[str, object]:
        return {
            "name": name,
            "cycles": 100,
            "overruns": 1,
            "compute_us": {"p50": 20.0, "p99": 30.0, "max": 40.0},
            "step_cpu_us": {"p50": 10.0, "p99": 15.0, "max": 25.0},
            "lateness_us": {"p50": 5.0, "p99": 9.0, "max": 12.0},
            "cpu_percent": cpu,
        }

    summary = {
        "task": "t",
        "result": "ok",
        "reason": "",
        "nodes": {
            "esc.r1": {
                "rate_hz": 200.0,
                "cycles": 998,
                "missed_ticks": 2,
                "overruns": 3,
                "lateness_us": {"p50": 40.0, "p99": 80.0, "max": 900.0},
                "manager": {"cpu_percent": 2.0},
                "workers": [worker("acquisition", 3.0), worker("sender", 4.0)],
            }
        },
        "plant": {"rtf": 0.99, "cpu_percent": 20.0, "step_us": {"p50": 100.0}},
        "log": {"dropped": 0, "nodes": {"ssc": {"writer_cpu_percent": 5.0, "dropped": 0}}},
        "ddm": {"esc.r1": {"command_latency_us": {"p50": 150.0, "p99": 400.0, "max": 900.0}}},
    }
    f = figures(summary)
    n = f["nodes"]["esc.r1"]
    assert n["overrun_percent"] == 0.3  # of 1000 periods (cycles + missed ticks)
    assert n["cpu_percent"] == 9.0
    assert n["processes"]["sender"]["step_cpu_us"]["p99"] == 15.0
    # 4 % of a vCPU at 200 Hz: 200 us a cycle (a recorder's step drains many)
    assert n["processes"]["sender"]["cpu_per_cycle_us"] == 200.0
    assert n["processes"]["manager"]["cpu_per_cycle_us"] == 100.0
    assert f["group_cpu_percent"] == 34.0  # 9 + the plant's 20 + the writer's 5
    assert f["ddm"]["r1"]["command_latency_us"]["p50"] == 150.0


def test_the_socket_floor_measures_every_exchange() -> None:
    """The floor's three processes pass a stamp at the rate asked for (a
    wake-up that finds two stamps takes the later one, the other counted);
    the replier times each receive and reply and each stamp's way."""
    from redistro.bench import floor

    got = floor.measure(500.0, 0.2, 19)
    cpu, latency = got["reply_cpu_us"], got["latency_us"]
    assert got["stamps"] == 100, got
    assert got["exchanges"] + got["coalesced"] == got["stamps"], got
    assert got["stamps"] // 4 <= cpu["samples"] == got["exchanges"], got  # late at times
    assert cpu["samples"] == latency["samples"], got
    assert 0 < cpu["p50"] <= cpu["p99"] <= cpu["max"], got
    assert 0 < latency["p50"] <= latency["p99"] <= latency["max"] < 1e6, got


def test_the_socket_floor_sends_to_every_robot_in_turn() -> None:
    """With three repliers each gets every stamp (its samples summed into
    the worst robot's percentiles)."""
    from redistro.bench import floor

    got = floor.measure(500.0, 0.2, 19, robots=3)
    assert got["robots"] == 3, got
    cpu, latency = got["reply_cpu_us"], got["latency_us"]
    assert got["exchanges"] + got["coalesced"] == got["stamps"] == 100, got
    assert got["stamps"] // 4 <= got["exchanges"], got
    assert cpu["samples"] == 3 * got["exchanges"], got
    assert cpu["samples"] == latency["samples"], got
    assert 0 < latency["p50"] <= latency["p99"] <= latency["max"] < 1e6, got


def test_the_zenoh_floor_answers_every_command_of_every_robot() -> None:
    """Bare zenoh-python: the commander puts each robot's command at the
    rate, each replier answers in zenoh's thread; every command that came
    timed and answered. Zenoh drops under congestion (``DROP``, as the ddm
    does): a host busy elsewhere loses a few, never most."""
    from redistro.bench import floor

    got = floor.measure(200.0, 0.5, 19, robots=2, module="redistro.bench.zenoh_floor")
    cpu, latency = got["reply_cpu_us"], got["latency_us"]
    assert got["commands"] == 2 * 100, got
    assert cpu["samples"] == latency["samples"] <= got["commands"], got  # commands that came
    assert 0.9 * got["commands"] <= got["replies"] <= latency["samples"], got
    assert 0 < latency["p50"] <= latency["p99"] <= latency["max"] < 1e6, got


def test_the_kernels_bench_times_each_kernel_and_its_reference() -> None:
    from pathlib import Path

    from redistro import kernels as built
    from redistro.bench import kernels
    from redistro.config.loader import load_config

    if not built.AVAILABLE:
        pytest.skip("redistro._kernels not built")
    cfg = load_config(Path(__file__).parents[2] / "config" / "redistro.yaml")
    got = kernels.run(cfg, calls=50)["cpu_us_per_call"]
    assert len(got) == 8, sorted(got)
    assert "ddm record in: crc32 + tag" in got
    assert "ddm record out: encoded, sealed" in got
    for name, row in got.items():
        for side in ("numpy", "kernel"):
            assert 0 < row[side]["p50"] <= row[side]["p99"], (name, row)

from __future__ import annotations

from pathlib import Path

import pytest

from redistro.config import Config, load_config, parse_override
from redistro.config.model import PAPER_PRIORITIES
from redistro.errors import ConfigError
from tests.helpers import ROOT


def test_defaults_without_a_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)  # no config/redistro.yaml here
    cfg = load_config(None, [])
    assert cfg == Config()
    assert cfg.bench.rate_hz > 0
    assert cfg.scheduling.priorities["acquisition"] == 19


def test_shipped_config_matches_the_defaults() -> None:
    shipped = load_config(Path(__file__).parents[2] / "config" / "redistro.yaml")
    assert shipped == Config()
    assert shipped.scheduling.priorities == PAPER_PRIORITIES


def test_overrides_parse_yaml_values(tmp_path: Path) -> None:
    cfg = load_config(None, ["bench.rate_hz=500", "bench.cpus=[0, 1]", "scheduling.policy=nice"])
    assert cfg.bench.rate_hz == 500.0
    assert cfg.bench.cpus == [0, 1]
    assert cfg.scheduling.policy == "nice"
    cfg = load_config(None, ["scheduling.priorities.pid=30"])
    assert cfg.scheduling.priorities["pid"] == 30


def test_override_beats_file(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("bench:\n  rate_hz: 250\n")
    assert load_config(path, []).bench.rate_hz == 250
    assert load_config(path, ["bench.rate_hz=300"]).bench.rate_hz == 300


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "bench:\n  rate: 1\n",
            "c.yaml: bench.rate: unknown key (known: cpus, heartbeat_limit_cycles, rate_hz)",
        ),
        (
            "bench:\n  rate_hz: 0\n",
            "c.yaml: bench.rate_hz: expected a number > 0 and <= 10000, got 0",
        ),
        ("bench:\n  rate_hz: true\n", "c.yaml: bench.rate_hz: expected a number"),
        (
            "bench:\n  heartbeat_limit_cycles: 2.5\n",
            "bench.heartbeat_limit_cycles: expected an integer",
        ),
        ("bench:\n  cpus: 1\n", "bench.cpus: expected a list of an integer"),
        ("bench:\n  cpus: [-1]\n", "bench.cpus[0]: expected an integer >= 0"),
        ("bench: 3\n", "c.yaml: bench: expected a mapping of NodeConfig fields, got 3"),
        (
            "scheduling:\n  priorities: {pid: 200}\n",
            "scheduling.priorities.pid: expected an integer >= 1 and <= 99",
        ),
        (
            "scheduling:\n  lock_memory: yes please\n",
            "scheduling.lock_memory: expected true or false",
        ),
        ("[1, 2]\n", "c.yaml: <top>: expected a mapping of config sections"),
        ("bench: {rate_hz: .nan}\n", "bench.rate_hz: expected a finite number"),
    ],
)
def test_errors_name_file_field_expected_and_got(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(path, [])
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_override_errors_say_set() -> None:
    with pytest.raises(ConfigError, match=r"^--set: bench.rate_hz: expected a number > 0"):
        load_config(None, ["bench.rate_hz=-2"])
    with pytest.raises(ConfigError, match=r"^--set bench.nope: no such config key"):
        load_config(None, ["bench.nope=1"])
    with pytest.raises(ConfigError, match=r"expected dotted\.key=value"):
        parse_override("bench.rate_hz")
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(Path("/no/such/file.yaml"), [])


def test_config_error_is_a_value_error() -> None:
    assert issubclass(ConfigError, ValueError)


def test_more_robots_than_the_layout_holds_are_refused() -> None:
    from redistro.config import load_config
    from redistro.errors import ConfigError

    sets = [f"robots.r{i}={{io: r1.io.yaml, sensors: r1.sensors.yaml}}" for i in range(3, 7)]
    with pytest.raises(ConfigError, match="at most 4 robots in a group"):
        load_config(ROOT / "config/redistro.yaml", sets)


def test_the_reaper_reports_an_object_it_may_not_remove(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    import posix_ipc

    from redistro.ipc import session

    def refuse(name: str) -> None:
        raise posix_ipc.PermissionsError("Permission denied")

    name = "/redistro.20261126T000000-abcdef.test.refused"
    shm = posix_ipc.SharedMemory(name, posix_ipc.O_CREX, mode=0o600, size=64)
    shm.close_fd()
    real_unlink = posix_ipc.unlink_shared_memory
    monkeypatch.setattr(posix_ipc, "unlink_shared_memory", refuse)
    try:
        assert session.unlink("shm", name) is False
        assert "not removed: Permission denied" in caplog.text
    finally:
        real_unlink(name)


def test_a_forged_estop_or_finished_flag_is_refused() -> None:
    import numpy as np

    from redistro.ddm.record import KIND_COMMAND, encode
    from redistro.ddm.record import check as check_record
    from redistro.errors import WireError
    from redistro.localdata.layout import COMMAND, SessionStatus

    cmd = np.zeros((), COMMAND)
    cmd["session_status"] = SessionStatus.FINISHED
    for estop in (True, False):
        forged = encode(KIND_COMMAND, 0, "ssc", 9, 9, cmd, estop=estop, key=b"x" * 32)
        with pytest.raises(WireError, match="auth"):
            check_record(forged, b"k" * 32)


def test_the_reflective_network_and_the_can_bus_stay_on_loopback() -> None:
    import socket
    import struct

    from redistro.ddm.reflective import _multicast_socket
    from redistro.drivers.io.can import open_bus
    from redistro.ipc.names import new_session_id

    s = _multicast_socket("239.255.68.68", 0)
    try:
        assert s.getsockname()[0] == "239.255.68.68"  # the group's datagrams only
    finally:
        s.close()
    bus = open_bus("udp_multicast", "", 0, new_session_id())
    try:
        sock = bus._multicast._socket
        iface = sock.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, 4)
        assert socket.inet_ntoa(struct.pack("4s", iface)) == "127.0.0.1"
    finally:
        bus.shutdown()


def test_a_resolved_config_and_task_come_back_equal(tmp_path: Path) -> None:
    """What the session owner hands down (resolved, in the node's spec file)
    rebuilds the same config and task in every process, without the YAML."""
    import json

    from redistro.config.loader import from_resolved, resolved
    from redistro.config.model import Config
    from redistro.config.task import Task, load_task
    from redistro.process.spec import NodeSpec

    root = Path(__file__).parents[2]
    # (the objects of grasp_lift, dual_carry_short and dual_peg)
    block = (
        "{block: {size_xyz_m: [0.04, 0.04, 0.06], xy_m: [0.5, 0.3]}, "
        "bar: {size_xyz_m: [0.04, 0.4, 0.06], xy_m: [0.5, 0.0], mass_kg: 2.0}, "
        "socket: {size_xyz_m: [0.05, 0.24, 0.06], xy_m: [0.45, 0.25], hole_side_m: 0.021, "
        "hole_depth_m: 0.04, hole_at_xy_m: [0.0, -0.09]}, "
        "peg: {size_xyz_m: [0.02, 0.02, 0.18], xy_m: [0.42, -0.28]}}"
    )
    cfg = load_config(
        root / "config" / "redistro.yaml",
        ["esc.rate_hz=1000", "ddm.transport=reflective", f"workcell.objects={block}"],
    )
    back = from_resolved(Config, json.loads(json.dumps(resolved(cfg))))
    assert back == cfg
    assert back.source == cfg.source and back.overridden == cfg.overridden
    assert back.origin("esc.rate_hz") == "--set"
    tasks = sorted((root / "tasks").glob("*.yaml")) + sorted(
        p for p in (root / "tests" / "data").glob("*.yaml") if "segments:" in p.read_text()
    )
    for path in tasks:  # the tests' tasks too: joint goals, unset fields
        task = load_task(path, cfg)
        again = from_resolved(Task, json.loads(json.dumps(resolved(task))))
        assert again == task and again.source == task.source, path
    spec = NodeSpec(
        "s", "ssc", "ssc", 200.0, 25, [], config=resolved(cfg), task_data=resolved(task)
    )
    spec.save(tmp_path / "spec.json")
    loaded = NodeSpec.load(tmp_path / "spec.json")
    assert loaded.cfg() == cfg and loaded.task() == task


@pytest.mark.parametrize("levels", [65, 100_000])
@pytest.mark.parametrize("loader", ["libyaml", "python"])
def test_deep_yaml_is_one_refusal_whichever_parser_finds_it(
    levels: int, loader: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # libyaml has its own nesting limit (far above ours) that it may reach
    # while scanning ahead; the pure-Python parser has none.
    import yaml

    from redistro.config import inputs

    if loader == "python":
        monkeypatch.setattr(inputs, "_LOADER", yaml.SafeLoader)
    elif not hasattr(yaml, "CSafeLoader"):
        pytest.skip("PyYAML without libyaml")
    text = "task: " + "[" * levels + "]" * levels + "\n"
    with pytest.raises(ConfigError) as err:
        inputs.load_yaml(text, "deep.yaml")
    assert str(err.value) == "deep.yaml:1: invalid YAML (nested deeper than 64 levels)"


def test_a_strategy_task_calibrates_first_as_its_own_section_says() -> None:
    """The self-calibration before a strategy task (its positions unknown)
    takes the task's ``calibration`` section; a task without one, the defaults."""
    from redistro.config.task import CalibrationTask, load_task
    from redistro.session.run import calibration_first

    cfg = load_config(ROOT / "config/redistro.yaml")
    drill = load_task(ROOT / "tasks/fault_drill.yaml", cfg)
    cal = calibration_first(drill, ["r2"])
    assert cal.kind == "self_calibration" and cal.robots == ["r2"]
    assert cal.calibration.segment_s == [2.4, 2.4, 1.8] and cal.calibration.range_deg == 12.0
    peg = load_task(ROOT / "tasks/peg_insertion.yaml", cfg)
    assert calibration_first(peg, ["r1", "r2"]).calibration == CalibrationTask()


def test_an_error_message_quotes_a_huge_value_without_walking_it() -> None:
    """A value as a message shows it: cut short, and made from its first
    items only (a document expanded to millions of items is not printed
    whole first)."""
    import time

    from redistro.errors import shown

    huge = [[i] * 8 for i in range(1_000_000)]
    t0 = time.process_time()
    text = shown(huge)
    assert time.process_time() - t0 < 0.05
    assert len(text) <= 60 and text.startswith("[[0, 0, 0")
    assert len(shown(10**80)) <= 60 and shown(10**80).startswith("1000")
    assert "..." in shown("x" * 1000) and len(shown("x" * 1000)) <= 60


def test_a_config_that_extends_another(tmp_path: Path) -> None:
    """``extends: FILE``: the other file's values with this one's on top,
    mappings merged key by key; an error names the file the value came from."""
    root = Path(__file__).parents[2]
    base = load_config(root / "config" / "redistro.yaml")
    dual = load_config(root / "config" / "dual_arm.yaml")
    assert dual.robots["r2"].peg is False and base.robots["r2"].peg is True
    assert dual.robots["r2"].io == base.robots["r2"].io  # (the rest of r2 from the base)
    assert dual.robots["r1"] == base.robots["r1"] and dual.esc == base.esc
    assert (
        set(dual.workcell.objects) == {"bar", "block"} and dual.workcell.hole == base.workcell.hole
    )
    assert dual.origin("robots.r2.peg") == str(root / "config" / "dual_arm.yaml")
    over = tmp_path / "over.yaml"
    over.write_text(f"extends: {root / 'config' / 'redistro.yaml'}\nesc: {{rate_hz: -5}}\n")
    with pytest.raises(ConfigError, match=r"over\.yaml: esc\.rate_hz: expected a number"):
        load_config(over)
    over.write_text(f"extends: {root / 'config' / 'redistro.yaml'}\nssc: {{rate_hz: 500}}\n")
    cfg = load_config(over, ["esc.rate_hz=1000"])
    assert cfg.ssc.rate_hz == 500 and cfg.esc.rate_hz == 1000 and cfg.ssc.cpus == base.ssc.cpus
    with pytest.raises(ConfigError, match=r"base\.yaml"):  # (the value from the base, named there)
        (tmp_path / "base.yaml").write_text("esc: {rate_hz: -5}\n")
        over.write_text("extends: base.yaml\n")
        load_config(over)
    over.write_text("extends: missing.yaml\n")
    with pytest.raises(ConfigError, match=r"missing\.yaml"):
        load_config(over)
    (tmp_path / "base.yaml").write_text("extends: over.yaml\n")
    over.write_text("extends: base.yaml\n")
    with pytest.raises(ConfigError, match="extends no other"):
        load_config(over)

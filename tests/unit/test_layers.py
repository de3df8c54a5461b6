"""The layers' imports: what may import what (read from the sources, no import run)."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).parents[2] / "redistro"
# the layers below the session: they offer hook points, they never import the harness
BELOW_SESSION = ("plant", "ddm", "esc", "ssc", "process", "drivers", "localdata", "ipc",
                 "control", "config", "log")  # fmt: skip


def _imports(path: Path) -> set[str]:
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
    return out


def test_no_layer_below_the_session_imports_the_fault_harness() -> None:
    offenders = [
        str(path.relative_to(PACKAGE))
        for layer in BELOW_SESSION
        for path in sorted((PACKAGE / layer).rglob("*.py"))
        if any(m == "redistro.faults" or m.startswith("redistro.faults.") for m in _imports(path))
    ]
    assert not offenders, offenders


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _runtime_imports(path: Path) -> set[str]:
    """The redistro modules ``path`` imports, at load time or inside its
    functions (not those under ``if TYPE_CHECKING``: types only)."""
    tree = ast.parse(path.read_text(), str(path))
    typing_only = {
        id(n)
        for block in ast.walk(tree)
        if isinstance(block, ast.If) and "TYPE_CHECKING" in ast.unparse(block.test)
        for n in ast.walk(block)
    }
    out: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
            out.update(f"{node.module}.{a.name}" for a in node.names)
    return {m for m in out if m.startswith("redistro")}


def test_no_import_circle() -> None:
    modules = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph = {m: {i for i in _runtime_imports(p) if i in modules and i != m}
             for m, p in modules.items()}  # fmt: skip
    circles: list[list[str]] = []
    state: dict[str, int] = {}  # 1: on the path, 2: done

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                circles.append([*path[path.index(n) :], n])
            elif n not in state:
                visit(n, [*path, n])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not circles, circles


def test_backends_come_from_one_table_each() -> None:
    """Every backplane and transport key resolves, lazily, to its interface;
    an unknown key names the known ones."""
    import pytest

    from redistro.ddm.transport import TRANSPORTS, Transport, transport_class
    from redistro.drivers.io.backplane import BACKPLANES, Backplane, backplane_class

    for key in BACKPLANES:
        assert issubclass(backplane_class(key), Backplane)
    for key in TRANSPORTS:
        assert issubclass(transport_class(key), Transport)
    with pytest.raises(KeyError, match=r"unknown backplane 'pci'.*shm, can"):
        backplane_class("pci")
    with pytest.raises(KeyError, match="unknown transport 'carrier-pigeon'"):
        transport_class("carrier-pigeon")


def test_the_sub_controllers_do_not_import_each_other() -> None:
    """ESC and SSC share what they need through lower layers (process/, ddm/,
    config/); the session log imports neither."""
    rules = {"esc": ("ssc",), "ssc": ("esc",), "log": ("esc", "ssc")}
    offenders = [
        f"{path.relative_to(PACKAGE)} imports {m}"
        for layer, banned in rules.items()
        for path in sorted((PACKAGE / layer).rglob("*.py"))
        for m in sorted(_imports(path))
        if any(m == f"redistro.{b}" or m.startswith(f"redistro.{b}.") for b in banned)
    ]
    assert not offenders, offenders


# The controller's packages: what they know of the plant's section is the I/O
# boards' datasheet (config.model.CONTROLLER_KEYS), never the world's truth.
CONTROLLER = ("esc", "ssc", "ddm", "control", "drivers")


def _plant_reads(path: Path) -> set[str]:
    """The attributes read off a ``.plant`` in ``path`` (``cfg.plant.hole``: hole)."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if (
            isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Attribute)
            and node.value.attr == "plant"
        ):
            out.add(node.attr)
    return out


def test_controller_packages_read_only_the_boards_datasheet_of_the_plant() -> None:
    from redistro.config.model import CONTROLLER_KEYS

    offenders = {
        str(path.relative_to(PACKAGE)): sorted(reads - set(CONTROLLER_KEYS))
        for layer in CONTROLLER
        for path in sorted((PACKAGE / layer).rglob("*.py"))
        if (reads := _plant_reads(path)) - set(CONTROLLER_KEYS)
    }
    assert not offenders, offenders
    # and the check itself sees such a read
    probe = PACKAGE.parent / "tests" / "unit" / "_probe_plant_read.py"
    probe.write_text("def f(cfg):\n    return cfg.plant.hole.offset_xyz_m\n")
    try:
        assert _plant_reads(probe) == {"hole"}
    finally:
        probe.unlink()


def test_controller_nodes_get_no_plant_truth() -> None:
    """The specs of the ESCs and the SSC carry the config's controller view:
    a hole offset, the encoders' disturbance, the sensor's bias are not in it."""
    from redistro.config import load_config
    from redistro.config.hardware import load_hardware
    from redistro.config.loader import from_resolved
    from redistro.config.model import Config
    from redistro.config.task import load_task
    from redistro.esc.plan import esc_spec
    from redistro.ssc.plan import ssc_spec

    root = PACKAGE.parent
    cfg = load_config(
        root / "config" / "redistro.yaml",
        [
            "plant.hole.offset_xyz_m=[0.002, -0.001, 0]",
            "plant.hole.offset_radius_m=0.003",
            "plant.hole.yaw_deg=1.5",
            "plant.ft_bias.r2=[1, 2, 3, 0, 0, 0]",
        ],
    )
    task = load_task(root / "tasks" / "peg_insertion_short.yaml", cfg)
    ssc = ssc_spec(cfg, task, "s", run_dir="")
    hw = load_hardware(cfg)
    specs = [ssc] + [
        esc_spec(cfg, task, r, hw[r], "s", positions_file="p.json") for r in task.robots
    ]
    for spec in specs:
        seen = from_resolved(Config, spec.config)
        assert seen.plant.hole == type(cfg.plant.hole)(), spec.node
        assert seen.plant.encoder_disturbance_rad == {} and seen.plant.ft_bias == {}, spec.node
        assert seen.plant.physics_hz == cfg.plant.physics_hz  # the boards' rate stays
        assert seen.workcell == cfg.workcell  # what it believes: the drawn work-cell


def test_a_parallel_ssc_runs_each_arm_in_one_stage_and_the_clock_after() -> None:
    """ssc.parallel_arms: a worker per robot in stage 0 (they run in
    parallel), each owning its robot, then the clock's worker in stage 1."""
    from redistro.config import load_config
    from redistro.config.task import load_task
    from redistro.ssc.plan import ssc_spec

    root = PACKAGE.parent
    for parallel, names, stages in (
        (False, ["worker"], [[0]]),
        (True, ["arm.r1", "arm.r2", "worker"], [[0, 1], [2]]),
    ):
        cfg = load_config(root / "config" / "redistro.yaml", [f"ssc.parallel_arms={parallel}"])
        task = load_task(root / "tasks" / "peg_insertion_short.yaml", cfg)
        spec = ssc_spec(cfg, task, "s", run_dir="")
        assert [w.name for w in spec.workers] == [*names, "logger", "ddm"]
        assert spec.stages() == stages
        assert all(w.role == "worker" for w in spec.workers[: len(names)])
        params = [w.params for w in spec.workers]
        want = [{"arm": 0}, {"arm": 1}, {"lead": True}] if parallel else [{}]
        assert params == [*want, {}, {}]

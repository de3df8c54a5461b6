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

"""The code stays sized for a reader: no C file over 600 lines, no C
function over 120, no Python function over 80 (tables excepted), no class
over 400; the compiled layer loads nothing at run time (no dlopen, no
dlsym) and no C file is left over from the single file it once was."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).parents[2]
PACKAGE = ROOT / "redistro"
# functions that are tables (one entry per line): the argument parser
TABLES = {("cli.py", "_parser")}


def _c_files() -> list[Path]:
    return sorted(PACKAGE.rglob("*.c"))


def test_c_files_and_functions_are_short() -> None:
    assert _c_files(), "no C sources found"
    assert not (PACKAGE / "_kernels.c").exists()
    long_files, long_functions = [], []
    for path in _c_files():
        lines = path.read_text().splitlines()
        if len(lines) > 600:
            long_files.append(f"{path.name}: {len(lines)} lines")
        start = None
        for i, line in enumerate(lines):
            if start is None and re.match(r"^[A-Za-z].*\)\s*\{\s*$", line):
                start = i
            elif start is not None and line == "}":
                if i - start + 1 > 120:
                    long_functions.append(f"{path.name}:{start + 1}: {i - start + 1} lines")
                start = None
    assert not long_files, long_files
    assert not long_functions, long_functions


def test_the_compiled_layer_loads_nothing_at_run_time() -> None:
    for path in [*_c_files(), *PACKAGE.rglob("*.h"), ROOT / "setup.py"]:
        text = path.read_text()
        assert "dlopen" not in text and "dlsym" not in text, path
    setup = (ROOT / "setup.py").read_text()
    assert '"crypto"' in setup and '"z"' in setup  # libcrypto and zlib, linked


def test_python_functions_and_classes_are_short() -> None:
    long = []
    for path in sorted([*PACKAGE.rglob("*.py"), *(ROOT / "tools").rglob("*.py")]):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = (node.end_lineno or 0) - node.lineno + 1
                if n > 80 and (path.name, node.name) not in TABLES:
                    long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}: {n}")
            elif isinstance(node, ast.ClassDef):
                n = (node.end_lineno or 0) - node.lineno + 1
                if n > 400:
                    long.append(f"{path.relative_to(ROOT)}:{node.lineno} class {node.name}: {n}")
    assert not long, "\n".join(long)

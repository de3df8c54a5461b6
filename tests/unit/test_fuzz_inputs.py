"""Property-based fuzzing of the front door: random mutations of every shipped
task and config file, random ``--set`` lines, and random ``log`` and ``top``
inputs. Each must end with exit 0 or one line and exit 2: never a traceback,
a hang (pytest-timeout) or anything left behind (the autouse leak check).

The commands run in-process through ``redistro.cli.main``: ``check`` (the
whole pre-flight of a session, which starts nothing), ``log summary`` and
``top --once``.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import io
import os
import shutil
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.helpers import ROOT

# make test: 300 of each kind; make fuzz: 2 000 (docs/SAFETY.md)
EXAMPLES = int(os.environ.get("REDISTRO_FUZZ_EXAMPLES", "300"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
    derandomize=True,
)
TASKS = sorted((ROOT / "tasks").glob("*.yaml"))
CONFIG = ROOT / "config" / "redistro.yaml"

scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
    st.sampled_from(["r1", "r2", "joint", "force", "socket", "1e300", "-1", "", "..", "a:b"]),
)
values = st.recursive(
    scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=8), st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=12,
)


def _paths(doc: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [prefix]
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            out += _paths(v, (*prefix, i))
    return out


def _mutate(doc: Any, path: tuple[Any, ...], op: str, value: Any) -> Any:
    if not path:
        return value if op == "set" else doc
    parent = doc
    for p in path[:-1]:
        parent = parent[p]
    last = path[-1]
    if op == "delete":
        del parent[last]
    elif op == "add" and isinstance(parent, dict):
        parent[f"{last}_x"] = value
    elif op == "add" and isinstance(parent, list):
        parent.append(value)
    else:
        parent[last] = value
    return doc


@functools.cache
def _parsed(source: Path) -> Any:
    """A shipped file as a document, parsed once (libyaml where present): the
    pure-Python parser spent 60 ms on every example."""
    return yaml.load(source.read_text(), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))


@st.composite
def mutated_yaml(draw: st.DrawFn, source: Path) -> bytes:
    doc = copy.deepcopy(_parsed(source))
    for _ in range(draw(st.integers(min_value=1, max_value=3))):
        paths = _paths(doc)
        path = draw(st.sampled_from(paths))
        op = draw(st.sampled_from(["set", "set", "delete", "add"]))
        doc = _mutate(doc, path, op, draw(values))
    try:
        text = yaml.safe_dump(doc, allow_unicode=True).encode()
    except (yaml.YAMLError, ValueError):
        text = source.read_bytes()
    if draw(st.booleans()):  # and byte-level damage: flips, cuts, insertions
        data = bytearray(text)
        for _ in range(draw(st.integers(min_value=1, max_value=4))):
            if not data:
                break
            at = draw(st.integers(min_value=0, max_value=len(data) - 1))
            kind = draw(st.sampled_from(["flip", "cut", "insert"]))
            if kind == "flip":
                data[at] = draw(st.integers(min_value=0, max_value=255))
            elif kind == "cut":
                del data[at : at + draw(st.integers(min_value=1, max_value=40))]
            else:
                data[at:at] = draw(st.binary(min_size=1, max_size=8))
        text = bytes(data)
    return text


def _known_keys() -> list[str]:
    doc = _parsed(CONFIG)
    keys = []
    for path in _paths(doc):
        if path and all(isinstance(p, str) for p in path):
            keys.append(".".join(path))
    return keys


KEYS = _known_keys()
# what a hostile --set value carries: deep nesting, anchors and aliases, huge
# numbers, unicode digits and markup
hostile_values = st.one_of(
    st.integers(min_value=1, max_value=4000).map(lambda n: "[" * n + "]" * (n // 2)),
    st.integers(min_value=1, max_value=3000).map(lambda n: "{a: " * n + "1" + "}" * n),
    st.sampled_from(
        [
            "&a [1, 2]",
            "[&a [1, 2], *a]",
            "[&a [x, x], &b [*a, *a], [*b, *b]]",
            "*a",
            "!!python/object:os.system ls",
            "!!binary AAAA",
            "1:2:3:4:5:6:7:8:9:10:11:12:13:14:15:16:17:18:19:20",
        ]
    ),
    st.integers(min_value=20, max_value=6000).map(lambda n: "9" * n),
    st.integers(min_value=20, max_value=6000).map(lambda n: "-0x" + "f" * n),
    st.integers(min_value=20, max_value=6000).map(lambda n: "1" + "0" * n + ".5e3"),
    st.text(alphabet="٠١٢٣٤٥٦٧٨٩０１２３４５６７８９²³¹", min_size=1, max_size=12),
    st.text(alphabet="[]/bold red:", min_size=1, max_size=20),
)
set_lines = st.one_of(
    st.builds(lambda k, v: f"{k}={v}", st.sampled_from(KEYS), hostile_values),
    st.builds(
        lambda k, v: f"{k}={v}",
        st.one_of(st.sampled_from(KEYS), st.text(max_size=30)),
        st.one_of(
            values.map(lambda v: yaml.safe_dump(v, default_flow_style=True).strip()),
            st.text(max_size=30),
        ),
    ),
    st.text(max_size=40),
)


def _run(argv: list[str], cwd: Path) -> tuple[int, str, str]:
    from redistro import cli

    out, err = io.StringIO(), io.StringIO()
    old = Path.cwd()
    os.chdir(cwd)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                rc = cli.main(argv)
            except SystemExit as exc:  # argparse: usage errors exit 2
                rc = int(exc.code or 0)
    finally:
        os.chdir(old)
    return rc, out.getvalue(), err.getvalue()


def _one_line_or_ok(rc: int, err: str, what: str) -> None:
    assert rc in (0, 2), f"{what}: exit {rc}: {err[-2000:]}"
    assert "Traceback" not in err, f"{what}: {err[-2000:]}"
    if rc == 2:
        lines = [ln for ln in err.strip().splitlines() if ln]
        if lines and lines[0].startswith("usage:"):  # argparse: usage, then the error line
            lines = lines[-1:]
        assert len(lines) == 1, f"{what}: {err[-2000:]}"
        assert lines[0].startswith("redistro") and len(lines[0]) < 600, f"{what}: {lines[0]}"


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A copy of the shipped config (hardware files beside it) and a runs folder."""
    root = tmp_path_factory.mktemp("fuzz")
    shutil.copytree(ROOT / "config", root / "config")
    shutil.copytree(ROOT / "tasks", root / "tasks")
    (root / "runs").mkdir()
    return root


@pytest.fixture(autouse=True)
def _quiet_signals(monkeypatch: pytest.MonkeyPatch) -> None:
    # the CLI blocks the runtime signals of its process; not the test runner's
    monkeypatch.setattr("redistro.ipc.signals.block_runtime_signals", lambda: None)


@pytest.mark.timeout(900)
def test_mutated_task_files(workdir: Path) -> None:
    @FUZZ
    @given(st.sampled_from(TASKS).flatmap(lambda t: mutated_yaml(t).map(lambda b: (t, b))))
    def run(case: tuple[Path, bytes]) -> None:
        task, text = case
        target = workdir / "fuzz-task.yaml"
        target.write_bytes(text)
        rc, _, err = _run(["--set", "session.runs_dir=runs", "check", str(target)], workdir)
        _one_line_or_ok(rc, err, f"{task.name} mutated")

    run()


@pytest.mark.timeout(900)
def test_mutated_config_files(workdir: Path) -> None:
    @FUZZ
    @given(mutated_yaml(CONFIG))
    def run(text: bytes) -> None:
        target = workdir / "config" / "fuzz.yaml"
        target.write_bytes(text)
        argv = ["--config", str(target), "check", "tasks/peg_insertion_short.yaml"]
        rc, _, err = _run(argv, workdir)
        _one_line_or_ok(rc, err, "config mutated")

    run()


@pytest.mark.timeout(900)
def test_random_set_lines(workdir: Path) -> None:
    @FUZZ
    @given(st.lists(set_lines, min_size=1, max_size=3))
    def run(lines: list[str]) -> None:
        argv = [a for line in lines for a in ("--set", line)]
        argv += ["--set", "session.runs_dir=runs", "check", "tasks/peg_insertion_short.yaml"]
        rc, _, err = _run(argv, workdir)
        _one_line_or_ok(rc, err, f"--set {lines!r}")

    run()


SUMMARY = {
    "task": "peg_insertion",
    "kind": "strategy",
    "result": "ok",
    "reason": "",
    "started": "2026-11-26T10:00:00",
    "ended": "2026-11-26T10:01:00",
    "inserted": True,
    "insertion_depth_m": 0.035,
    "segments": [
        {
            "name": "approach",
            "robot": "r2",
            "scheme": "position",
            "duration_s": 4.0,
            "final_pose_error": {"position_m": 0.0002, "orientation_rad": 0.001},
        }
    ],
    "nodes": {"ssc": {"result": "ok", "cycles": 100, "rate_hz": 200.0, "overruns": 0}},
    "log": {"nodes": {"ssc": {"recorded": 100, "dropped": 0}}},
}
META = {
    "task": "peg_insertion",
    "physics_hz": 1000.0,
    "hole_xyz_m": [0.55, -0.35, 0.15],
    "robots": {"r2": {"base_xyz_m": [0.0, -0.45, 0.0], "peg": [0.02, 0.1, 0.1]}},
}
markup = st.text(alphabet="[]/bold red:x ", max_size=16)


@st.composite
def mutated_doc(draw: st.DrawFn, doc: dict[str, Any]) -> Any:
    out = copy.deepcopy(doc)
    for _ in range(draw(st.integers(min_value=1, max_value=3))):
        path = draw(st.sampled_from(_paths(out)))
        op = draw(st.sampled_from(["set", "set", "delete", "add"]))
        out = _mutate(out, path, op, draw(st.one_of(values, markup)))
    return out


def _write_log(path: Path, meta: Any, names: list[str]) -> None:
    """A small session log: a feedback-like JSON channel, segment events
    named ``names``, and ``meta`` as its redistro.meta metadata."""
    import json

    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("redistro/Event", "jsonschema", b"{}")
        cid = w.register_channel("/ssc/segments", "json", sid)
        for i, name in enumerate(names):
            w.add_message(cid, i + 1, json.dumps({"name": name, "cycle": i}).encode(), i + 1)
        if isinstance(meta, dict):
            w.add_metadata("redistro.meta", {str(k): json.dumps(v) for k, v in meta.items()})
        w.finish()


@pytest.mark.timeout(900)
def test_mutated_summaries_metadata_and_markup_names(workdir: Path) -> None:
    """log summary over a summary.json and a session log's metadata of the
    shape a session writes, mutated, with names that look like markup."""
    import json

    run_dir = workdir / "runs" / "mutated"
    run_dir.mkdir(parents=True, exist_ok=True)

    @FUZZ
    @given(mutated_doc(SUMMARY), mutated_doc(META), st.lists(markup, max_size=3))
    def run(summary: Any, meta: Any, names: list[str]) -> None:
        (run_dir / "summary.json").write_text(json.dumps(summary))
        _write_log(run_dir / "session.mcap", meta, names)
        rc, out, err = _run(["log", "summary", str(run_dir)], workdir)
        _one_line_or_ok(rc, err, f"log summary of {summary!r:.200} / {meta!r:.200}")
        if rc == 0 and isinstance(summary, dict) and isinstance(summary.get("task"), str):
            squeeze = "".join(summary["task"].split())
            assert squeeze in "".join(out.split()), out

    run()


@pytest.mark.timeout(900)
def test_random_log_and_top_inputs(workdir: Path) -> None:
    run_dir = workdir / "runs" / "fuzzrun"
    run_dir.mkdir(parents=True, exist_ok=True)

    @FUZZ
    @given(
        st.binary(max_size=400),
        st.one_of(values.map(lambda v: yaml.safe_dump(v)), st.text(max_size=50)),
        st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8)),
    )
    def run(mcap: bytes, summary: str, interval: Any) -> None:
        (run_dir / "session.mcap").write_bytes(b"\x89MCAP0\r\n" + mcap)
        (run_dir / "summary.json").write_text(summary)
        rc, _, err = _run(["log", "summary", str(run_dir)], workdir)
        _one_line_or_ok(rc, err, "log summary")
        rc, _, err = _run(["top", "--once", "--interval", str(interval)], workdir)
        _one_line_or_ok(rc, err, f"top --interval {interval!r}")

    run()

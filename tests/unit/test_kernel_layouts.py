"""The kernels' buffers: declared layouts, checked plans, no out-of-bounds access.

Every kernel's signature (names, element types, size rules) comes from the
C; every buffer with fields has one declared layout (redistro/*_layout.py).
These tests hold the two together and show that a wrong buffer (one element
short, the wrong element type, a field moved) is refused with an error that
names it, before any kernel runs.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from redistro import kernel_layouts, kernels
from redistro.kernel_layouts import LayoutMismatch, Table

pytestmark = pytest.mark.skipif(not kernels.AVAILABLE, reason="the kernels are not built")

TYPES = {"d": np.float64, "q": np.int64, "B": np.uint8}
WRONG = {"d": np.float32, "q": np.int32}  # same family, other width


def _signatures() -> dict[str, tuple[tuple[str, str, int, int, str, int], ...]]:
    k = kernels.KERNELS
    return {name: k.signature(name) for name in k.KERNEL_NAMES}


def _valid(kernel: str) -> dict[str, np.ndarray[Any, Any]]:
    """Buffers that satisfy ``kernel``'s size rules: 2 of every dimension,
    2 rows of a table, 64 elements where any size goes."""
    out = {}
    for name, t, size, row, dim, per in kernels.KERNELS.signature(kernel):
        n = size or 2 * row or 2 * per if dim or size or row else 64
        out[name] = np.zeros(n, TYPES[t])
    return out


def _declared() -> list[tuple[str, str]]:
    return sorted(
        (k, b)
        for k, bufs in kernel_layouts.all_layouts().items()
        for b in bufs
        if k in _signatures()
    )


def test_every_layout_is_a_buffer_of_its_kernels_signature() -> None:
    sigs = _signatures()
    layouts = kernel_layouts.all_layouts()
    for kernel, bufs in layouts.items():
        if kernel == "answer":  # the CompiledAnswer's state: checked by its constructor
            continue
        assert kernel in sigs, f"{kernel}: declared, but no such kernel"
        args = {a[0]: a for a in sigs[kernel]}
        for buf, layout in bufs.items():
            assert buf in args, f"{kernel}.{buf}: declared, but not an argument"
            _, t, size, row, _dim, per = args[buf]
            dt = kernel_layouts.dtype_of(layout)
            elem = kernel_layouts.element(dt)
            assert elem == np.dtype(TYPES[t]), f"{kernel}.{buf}: {elem} vs C type {t}"
            n = dt.itemsize // elem.itemsize
            rule = row or per if isinstance(layout, Table) else size
            assert rule == n, f"{kernel}.{buf}: the C's size rule {rule}, the layout's {n}"


@pytest.mark.parametrize("kernel", sorted(_signatures()))
def test_a_short_or_mistyped_buffer_is_refused_by_the_plan(kernel: str) -> None:
    """Below the Python check: the C plan itself refuses every buffer that
    breaks its size rule, or is of the wrong element type."""
    Plan = kernels.KERNELS.Plan
    sig = kernels.KERNELS.signature(kernel)
    Plan(kernel, _valid(kernel))  # the valid set plans
    dims: dict[str, int] = {}
    for a in sig:
        if a[4]:
            dims[a[4]] = dims.get(a[4], 0) + 1
    for name, t, size, row, dim, per in sig:
        bufs = _valid(kernel)
        bufs[name] = bufs[name][:-1]
        if size or row > 1 or (dim and (per > 1 or dims[dim] > 1)):
            with pytest.raises(ValueError, match=f"kernel {kernel}: argument "):
                Plan(kernel, bufs)
        if t in WRONG:
            bufs = _valid(kernel)
            bufs[name] = bufs[name].astype(WRONG[t])
            with pytest.raises(TypeError, match=f"kernel {kernel}: argument {name}"):
                Plan(kernel, bufs)


@pytest.mark.parametrize(("kernel", "buf"), _declared())
def test_a_declared_buffer_is_checked_against_its_layout(kernel: str, buf: str) -> None:
    layout = kernel_layouts.all_layouts()[kernel][buf]
    dt = kernel_layouts.dtype_of(layout)
    elem = kernel_layouts.element(dt)
    n = dt.itemsize // elem.itemsize
    rec = np.zeros(2 if isinstance(layout, Table) else (), dt)
    flat = kernel_layouts.flat(kernel, buf, rec, layout)
    assert flat.dtype == elem and np.shares_memory(flat, rec)
    where = f"kernel {kernel}: buffer {buf}"
    short = np.zeros(n - 1, elem)
    with pytest.raises(LayoutMismatch, match=f"{where}: {n - 1} elements"):
        kernel_layouts.flat(kernel, buf, short, layout)
    wrong = np.zeros(n, np.float32 if elem != np.float32 else np.int16)
    with pytest.raises(LayoutMismatch, match=f"{where}: elements of"):
        kernel_layouts.flat(kernel, buf, wrong, layout)
    # a record whose first field is renamed, or of another type
    assert dt.names is not None
    first = dt.names[0]
    renamed = np.dtype({**_spec(dt), "names": ["x_" + first, *dt.names[1:]]})
    with pytest.raises(LayoutMismatch, match=f"{where}: field {first} missing"):
        kernel_layouts.flat(kernel, buf, np.zeros((), renamed), layout)
    other = _spec(dt)
    other["formats"] = [np.dtype((np.int8 if elem == np.float64 else np.float64, dt[0].shape))]
    other["formats"] += [dt[i] for i in range(1, len(dt))]
    other.pop("itemsize")
    other.pop("offsets")
    with pytest.raises(LayoutMismatch, match=f"{where}: field {first}"):
        kernel_layouts.flat(kernel, buf, np.zeros((), np.dtype(other)), layout)


def _spec(dt: np.dtype[Any]) -> dict[str, Any]:
    assert dt.fields is not None and dt.names is not None
    return {
        "names": list(dt.names),
        "formats": [dt.fields[n][0] for n in dt.names],
        "offsets": [dt.fields[n][1] for n in dt.names],
        "itemsize": dt.itemsize,
    }


def test_the_python_plan_names_the_field_that_does_not_fit() -> None:
    from redistro.control import cartesian_layout as lay

    bufs: dict[str, Any] = {
        "kin": np.zeros((), lay.KIN),
        "ref": np.zeros((), lay.REF),
        "cmd": np.zeros((), lay.CMD),
        "gains": np.zeros((), lay.GAINS),
        "state": np.zeros((), lay.STATE),
        "out": np.zeros((), lay.OUT),
    }
    kernels.plan("cartesian_law", **bufs)
    bufs["gains"] = np.zeros(lay.GAINS.itemsize // 8 - 1)  # one short
    with pytest.raises(LayoutMismatch, match="kernel cartesian_law: buffer gains: 50 elements"):
        kernels.plan("cartesian_law", **bufs)
    moved = np.dtype([("k", "<f8", 6), ("ki", "<f8", 6)])
    bufs["gains"] = np.zeros((), moved)
    with pytest.raises(LayoutMismatch, match="buffer gains: field d missing"):
        kernels.plan("cartesian_law", **bufs)


def test_the_header_gives_every_field_its_offset() -> None:
    header = kernel_layouts.header()
    assert f'#define KERNEL_LAYOUTS_DIGEST "{kernel_layouts.digest()}"' in header
    assert "#define CARTESIAN_LAW_KIN_G 103\n" in header  # J 42, R 9, t 3, M 49
    assert "#define CARTESIAN_LAW_KIN_J__LEN 42\n" in header
    assert "#define GUARD_PREPARE_LIMITS__N 37\n" in header
    assert "#define WIRE_CODEC_KEY_LEN 192\n" in header  # a byte buffer counts bytes
    assert kernel_layouts.digest() == kernels.KERNELS.LAYOUTS_DIGEST


def test_no_python_module_indexes_a_kernel_buffer_by_number() -> None:
    """The owners read and write their kernel buffers by field name: no
    ``state[2]``-style index on the names that hold them."""
    import re
    from pathlib import Path

    root = Path(kernel_layouts.__file__).parent
    # names only kernel buffers have, and common names on an owner's object
    unique = r"gains0?|trace_at|_jump|admit_rows|emit_rows|noise_at|step_rec|guard_limits|codec"
    fields = r"kin|ref|cmd|state|out|params|_state|_params|answer_state|reply|time|_dt"
    owned = rf"(?:self|law|kernel_path|st|ssc|esc)\.(?:{fields})"
    pattern = re.compile(rf"(?:\b(?:{unique})|{owned})\[-?\d+(?::-?\d*)?\]")
    for bad in (
        "gains[5] = 1.0",
        "int(kernel_path.state[2])",
        "self._params[4] = 0.0",
        "ref = law.out[0:7]",
    ):
        assert pattern.search(bad), bad  # (the search finds what it is for)
    hits = []
    for path in sorted(root.rglob("*.py")):
        if path.name.endswith("_layout.py"):
            continue
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if pattern.search(line.split("#")[0]):
                hits.append(f"{path.relative_to(root)}:{n}: {line.strip()}")
    assert not hits, "\n".join(hits)

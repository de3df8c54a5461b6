"""The compiled kernels (``redistro._kernels``, C) and what they work on.

A kernel runs one cycle's arithmetic of an I/O path in one call (see
redistro/kernel_core.c for why). Its caller builds a Plan once, in
Initialization, from named buffers (:func:`plan`); a buffer with fields has
one declared layout (:mod:`redistro.kernel_layouts`), checked here, and the
C reads its fields at offsets generated from that same layout. An
:class:`Arena` hands out typed, aligned views of one byte buffer, so that
the many small vectors a kernel touches can also be copied with one table
(:func:`copy_table`).

Every module that uses a kernel keeps a numpy implementation of the same
arithmetic (the reference; its unit tests run both on the same inputs and
compare byte for byte), and uses it when the extension is missing (``pip
install`` builds it; ``REDISTRO_KERNELS=0`` turns it off).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from redistro import kernel_layouts


class StaleKernels(ImportError):
    """The compiled kernels were built from other layouts than the source's."""


KERNELS: Any
try:
    if os.environ.get("REDISTRO_KERNELS", "1") == "0":
        raise ImportError("turned off by REDISTRO_KERNELS=0")
    from redistro import _kernels

    KERNELS = _kernels
except ImportError:  # pragma: no cover - the build makes it
    KERNELS = None

if KERNELS is not None and kernel_layouts.digest() != KERNELS.LAYOUTS_DIGEST:
    raise StaleKernels(
        "redistro._kernels was built from other kernel layouts than the source's: "
        "rebuild it (make, or pip install -e .)"
    )

AVAILABLE = KERNELS is not None
__all__ = [
    "AVAILABLE",
    "KERNELS",
    "Arena",
    "address_in",
    "copier",
    "copy_rows",
    "copy_table",
    "plan",
    "record",
    "table",
]


_LAYOUTS: dict[str, dict[str, Any]] = {}


def plan(kernel: str, **buffers: Any) -> Any:
    """A Plan of ``kernel`` over ``buffers`` (each an array or a writable
    buffer; the kernel's signature says which names and element types).
    A buffer with a declared layout may be a structured record (or a table
    of them) of exactly that layout, or its flat elements; either is checked
    against the layout (LayoutMismatch names the kernel, buffer and field)."""
    assert KERNELS is not None
    if not _LAYOUTS:
        _LAYOUTS.update(kernel_layouts.all_layouts())
    declared = _LAYOUTS.get(kernel, {})
    flat = {
        name: kernel_layouts.flat(kernel, name, buf, declared[name]) if name in declared else buf
        for name, buf in buffers.items()
    }
    return KERNELS.Plan(kernel, flat)


def _layout(kernel: str, buf: str) -> Any:
    if not _LAYOUTS:
        _LAYOUTS.update(kernel_layouts.all_layouts())
    return _LAYOUTS[kernel][buf]


def table(kernel: str, buf: str, rows: list[tuple[Any, ...]]) -> np.ndarray[Any, Any]:
    """A table of ``kernel``'s buffer ``buf``: one record of its declared
    layout per row (each a tuple in the layout's field order)."""
    dtype = kernel_layouts.dtype_of(_layout(kernel, buf))
    out: np.ndarray[Any, Any] = np.array([tuple(r) for r in rows], dtype=dtype).reshape(-1)
    return out


def record(kernel: str, buf: str) -> np.ndarray[Any, Any]:
    """A zeroed record of ``kernel``'s buffer ``buf``'s declared layout (a
    0-d structured array: fields by name, ``rec["q_lo"][...] = ...``)."""
    out: np.ndarray[Any, Any] = np.zeros((), dtype=kernel_layouts.dtype_of(_layout(kernel, buf)))
    return out


class Arena:
    """One byte buffer carved into named, typed, aligned views (numpy arrays
    that share its memory): ``arena.take("q", np.float64, 14)``."""

    def __init__(self, size: int) -> None:
        self.buffer = np.zeros(size, dtype=np.uint8)
        self.used = 0
        self.views: dict[str, tuple[int, np.ndarray[Any, Any]]] = {}

    def take(self, name: str, dtype: Any, shape: int | tuple[int, ...]) -> np.ndarray[Any, Any]:
        dt = np.dtype(dtype)
        start = (self.used + 7) // 8 * 8
        count = int(np.prod(shape))
        end = start + dt.itemsize * count
        if end > self.buffer.size:
            raise ValueError(f"arena of {self.buffer.size} bytes: no room for {name}")
        view: np.ndarray[Any, Any] = self.buffer[start:end].view(dt).reshape(shape)
        self.used = end
        self.views[name] = (start, view)
        return view

    def alias(self, name: str, view: np.ndarray[Any, Any]) -> None:
        """Name a part of an existing view (e.g. one element of a state vector)."""
        self.views[name] = (address_in(self.buffer, view), view)

    def offset(self, name: str) -> int:
        """Byte offset of the view ``name`` in the buffer."""
        return self.views[name][0]


def address_in(buffer: np.ndarray[Any, Any], view: np.ndarray[Any, Any]) -> int:
    """Byte offset of ``view`` inside ``buffer`` (a view of its memory)."""
    base = buffer.__array_interface__["data"][0]
    at = view.__array_interface__["data"][0]
    if not base <= at < base + buffer.nbytes:
        raise ValueError("the view is not inside the buffer")
    return int(at - base)


def copy_table(rows: list[tuple[int, int, int]]) -> np.ndarray[Any, Any]:
    """(src, dst, size) rows for the ``copy`` kernel (COPY_ROW, core_layout.py)."""
    return table("copy", "table", rows)


def copy_rows(src: np.ndarray[Any, Any], dst: np.ndarray[Any, Any], rows: np.ndarray) -> None:
    """The ``copy`` kernel's arithmetic in numpy (reference and fallback)."""
    spans = zip(rows["src"].tolist(), rows["dst"].tolist(), rows["size"].tolist(), strict=True)
    for s, d, n in spans:
        dst[d : d + n] = src[s : s + n]


def copier(arena: Arena, record: np.ndarray[Any, Any], fields: dict[str, str]) -> Any:
    """A callable that copies views of ``arena`` into fields of ``record`` (a
    0-d structured array): ``fields`` maps arena view -> record field (same
    size in bytes). One kernel call per use."""
    spec = record.dtype.fields
    assert spec is not None
    dst = record.reshape(1).view(np.uint8)
    rows = []
    for src, name in fields.items():
        ftype, off = spec[name][0], int(spec[name][1])
        view = arena.views[src][1]
        if view.nbytes != ftype.itemsize:
            raise ValueError(f"{src} ({view.nbytes} bytes) does not fit {name} ({ftype.itemsize})")
        rows.append((arena.offset(src), off, ftype.itemsize))
    rows_ = copy_table(rows)
    if AVAILABLE:
        p = plan("copy", src=arena.buffer, dst=dst, table=rows_)
        run = KERNELS.copy
        return lambda: run(p)
    return lambda: copy_rows(arena.buffer, dst, rows_)

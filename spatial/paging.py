"""Passes over arrays that may be mapped from a file, a step at a time.

A page of a file mapped into the process counts as the process's memory once read, until it
is unmapped or handed back. A pass over a mapped array of boxes (an import's: 32 bytes an
item, 3.2 GB at 1e8 items) read whole would hold all of it; read a step at a time, each
step's pages handed back once read, it holds a step. For an array in memory, stepping costs a
call a step and releases nothing.

What it promises: a pass made of these (``steps``, ``in_steps``, ``steps_at``, ``filled``,
``in_file``, ``bounds``) holds about ``STEP_BYTES`` of a mapped array at a time, whatever its
length; one written at random (``windows``, ``placed``) holds a window of it, the
``window_bytes`` of the ``budget.MemoryBudget`` held (``budget.current()``). ``release`` and
``release_rows`` hand pages back, and are no-ops for arrays in memory, so a caller need not
know where its arrays are. The values a pass computes are the same in memory and in files.
"""

from __future__ import annotations

import mmap
from collections.abc import Callable, Iterator

import numpy as np

from . import _kernels
from .budget import current

__all__ = [
    "STEP_BYTES",
    "Scratch",
    "bounds",
    "filled",
    "in_file",
    "in_steps",
    "mapping",
    "new_array",
    "placed",
    "release",
    "release_rows",
    "steps",
    "steps_at",
    "windows",
]

STEP_BYTES = 1 << 24  # bytes of a mapped array a pass reads before handing them back
# Makes an array of a length and type in a file, mapped shared and writable: what a build
# keeps there is written and read a step at a time, its pages handed back after each
Scratch = Callable[[int, type[np.generic]], np.ndarray]


def steps(n: int, row_bytes: int) -> Iterator[tuple[int, int]]:
    """``(lo, hi)`` row ranges covering ``0..n``, each about ``STEP_BYTES`` of rows."""
    step = max(1, STEP_BYTES // max(1, row_bytes))
    for lo in range(0, n, step):
        yield lo, min(lo + step, n)


def windows(rows: int, row_bytes: int, in_file: bool) -> Iterator[tuple[int, int]]:
    """``(a, b)`` ranges covering ``0..rows`` of an array written (or read) at random, a pass
    each: the budget's ``window_bytes`` of rows at a time when it is in a file (each window's
    pages handed back before the next; the rest written by the passes after, each page written
    held until its pass ends), all of them at once in memory (nothing to hand back).

    >>> list(windows(5, 8, in_file=False))
    [(0, 5)]
    """
    window = max(1, current().window_bytes // max(1, row_bytes)) if in_file else max(1, rows)
    for a in range(0, rows, window):
        yield a, min(a + window, rows)


def in_steps(rows: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
    """``(lo, rows[lo:hi])``, a step of ``rows`` at a time, each step's pages handed back
    (``release_rows``) once the caller moves on, or stops."""
    row_bytes = rows.itemsize * (rows.size // len(rows)) if len(rows) else 1
    for lo, hi in steps(len(rows), row_bytes):
        view = rows[lo:hi]
        try:
            yield lo, view
        finally:
            release_rows(view)


def steps_at(rows: np.ndarray, row_bytes: int) -> Iterator[tuple[int, int]]:
    """``(lo, hi)`` ranges covering ``rows`` (ascending row numbers of an array), each of the
    rows lying within about ``STEP_BYTES`` of that array's: a step over sparse rows reads the
    pages of a step, not a few rows on every page of the array."""
    step, lo, most = max(1, STEP_BYTES // max(1, row_bytes)), 0, int(np.iinfo(rows.dtype).max)
    while lo < len(rows):
        # the bound in the rows' own type: another would have numpy convert all of them first
        last = rows.dtype.type(min(int(rows[lo]) + step - 1, most))
        hi = int(np.searchsorted(rows, last, side="right"))
        yield lo, hi
        lo = hi


def mapping(buffer: object) -> mmap.mmap | None:
    """The ``mmap`` under ``buffer`` (a memoryview or an array), or None: in memory."""
    while buffer is not None and not isinstance(buffer, mmap.mmap):
        buffer = buffer.base if isinstance(buffer, np.ndarray) else getattr(buffer, "obj", None)
    return buffer


def release(buffer: object) -> None:
    """Hand the pages of a file mapped under ``buffer`` (a memoryview or an array over an
    ``mmap``) that this process has read back to the page cache: the process stops counting
    them, the next read maps them again. A no-op for a buffer in memory."""
    if (mapped := mapping(buffer)) is not None:
        mapped.madvise(mmap.MADV_DONTNEED)


def new_array(scratch: Scratch | None, length: int, dtype: type[np.generic]) -> np.ndarray:
    """An array of ``length`` values of ``dtype``, not filled in: in a file (``scratch``), or
    in memory without one."""
    return np.empty(length, dtype) if scratch is None else scratch(length, dtype)


def filled(array: np.ndarray, value: int) -> np.ndarray:
    """``array`` filled with ``value`` a step at a time, each step's pages handed back."""
    for _, step in in_steps(array):
        step.fill(value)
    return array


def in_file(array: np.ndarray, scratch: Scratch | None, dtype: type[np.generic] | None = None) -> np.ndarray:
    """``array`` (as ``dtype``: None, its own) copied into a file (``scratch``) a step at a
    time, each step's pages handed back; without one, ``array`` itself (or a copy as
    ``dtype``)."""
    if scratch is None:
        return array if dtype is None else array.astype(dtype, copy=False)
    out = scratch(array.size, dtype or array.dtype.type).reshape(array.shape)
    for lo, step in in_steps(array):
        into = out[lo : lo + len(step)]
        into[:] = step
        release_rows(into)
    return out


def placed(order: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``out``, with each position's place in ``order`` written at it (``out[order[k]] =
    k``), a step of ``order`` at a time. Mapped from a file (the writes land all over it): a
    pass over ``order`` for each window of ``out`` (``windows``), its pages handed back
    after each."""
    for a, b in windows(len(out), out.itemsize, mapping(out) is not None):
        for lo, step in in_steps(order):
            _kernels.place_within(step, lo, a, b, out)
        release(out)
    return out


def release_rows(view: np.ndarray) -> None:
    """``release`` only the pages under ``view`` (an array mapped from a file: a step of a
    pass over it), not the whole file's: a pass's steps each cost their own pages alone."""
    if (mapped := mapping(view)) is None or not view.nbytes:
        return
    at = view.ctypes.data - np.frombuffer(mapped, np.uint8).ctypes.data
    lo = at - at % mmap.PAGESIZE
    mapped.madvise(mmap.MADV_DONTNEED, lo, at + view.nbytes - lo)


def bounds(boxes: np.ndarray) -> tuple[float, float, float, float]:
    """``(x0, y0, x1, y1)`` enclosing every one of ``boxes`` ((n, 4)), read a step at a time."""
    x0, y0, x1, y1 = np.inf, np.inf, -np.inf, -np.inf
    for _, rows in in_steps(boxes):
        a, b, c, d = _kernels.bounds(rows)
        x0, y0, x1, y1 = min(x0, a), min(y0, b), max(x1, c), max(y1, d)
    return x0, y0, x1, y1

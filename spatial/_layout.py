"""Where a tree's items go, step by step over boxes that may be mapped from a file: the square
world its keys cut up, each box's Morton key, the nodes the sorted keys split into, the boxes
placed in the tree's order a step at a time, and its arrays aligned to cache lines.
``QuadTree``'s builds call these; the loops themselves are compiled in ``_kernels``."""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np

from . import _kernels, paging
from .paging import Scratch, bounds, in_steps, mapping, new_array, placed, release, release_rows

__all__ = [
    "aligned",
    "aligned_empty",
    "in_order",
    "leaf_runs",
    "morton_keys",
    "outward_float32",
    "placed_rows",
    "slots",
    "split",
    "world",
]


def world(boxes: np.ndarray, max_depth: int) -> tuple[float, float, float, int]:
    """The square the keys cut up: origin, half its side, and how many times to halve it.

    Halving stops while a cell is still >= 4 float spacings of the largest coordinate, so
    cells never shrink below what the coordinates can tell apart. Half sides stay finite
    even for a world spanning the whole float range.
    """
    if boxes.shape[0] == 0:
        return 0.0, 0.0, 0.0, 0
    ox, oy, x1, y1 = bounds(boxes)
    half_side = max(x1 * 0.5 - ox * 0.5, y1 * 0.5 - oy * 0.5)
    spacing = math.ulp(max(abs(ox), abs(oy), abs(x1), abs(y1)))  # finite even at the largest double
    if not half_side > 1e-290:  # a single point, or subnormal extents: one cell
        return ox, oy, 0.0, 0
    cells = half_side / (2.0 * spacing)  # underflows to 0 when the side is far below a spacing
    bits = math.floor(math.log2(cells)) if cells >= 1.0 else 0
    return ox, oy, half_side, max(0, min(max_depth, bits))


def morton_keys(
    boxes: np.ndarray, world: tuple[float, float, float, int], scratch: Scratch | None = None
) -> np.ndarray:
    """Each box's key (``_kernels.morton_keys``) as uint64, the boxes read a step at a time;
    with ``scratch``, into a file, each step's pages handed back."""
    keys = new_array(scratch, len(boxes), np.int64)
    for lo, rows in in_steps(boxes):
        out = keys[lo : lo + len(rows)]
        out[:] = _kernels.morton_keys(rows, *world)
        release_rows(out)
    return keys.view(np.uint64)


def split(keys: np.ndarray, leaf_size: int, like: np.ndarray) -> np.ndarray:
    """``_kernels.split``'s nodes; over keys mapped from a file, made a step of them at a time
    (``split_some``), the pages read handed back after each."""
    if mapping(keys) is None:
        return _kernels.split(keys, leaf_size, like)
    link, m = _kernels.split_root(len(keys), leaf_size, like)
    i, most = 0, max(1, paging.STEP_BYTES // keys.itemsize)
    while i < m:
        link, m, i = _kernels.split_some(keys, leaf_size, link, m, i, most)
        release(keys)
    return link[:m]


def in_order(boxes: np.ndarray, order: np.ndarray) -> np.ndarray:
    """``boxes[order]``, for boxes mapped from a file: each step of them read where it lies and
    put where it goes (each box's place, ``order`` inverted, 4 bytes an item), so a step of
    them is held at a time; gathered in ``order`` they would all be read at random, and held."""
    return placed_rows(boxes, slots(order), 0, len(boxes), aligned_empty(boxes.shape, np.float64))


def placed_rows(boxes: np.ndarray, place: np.ndarray, a: int, b: int, out: np.ndarray) -> np.ndarray:
    """``out``, slots ``a..b`` of the boxes in the tree's order (``place``: each box's slot):
    a pass over ``boxes`` a step at a time, each step's pages handed back."""
    for lo, rows in in_steps(boxes):
        _kernels.scatter_rows(rows, place[lo : lo + len(rows)], a, b, out)
        release_rows(place[lo : lo + len(rows)])
    return out


def leaf_runs(starts: np.ndarray, n: int, most: int) -> Iterator[tuple[int, int, int, int]]:
    """``(k0, k1, a, b)``: runs of whole leaves ``k0..k1`` (``starts``: each leaf's first
    item, ascending from 0, the leaves tiling ``0..n``), items ``a..b``, of at most ``most``
    items where a leaf is no larger."""
    k0 = 0
    while k0 < len(starts):
        a = int(starts[k0])
        k1 = (
            len(starts) if a + most >= n else max(k0 + 1, int(np.searchsorted(starts, a + most, "right")) - 1)
        )
        yield k0, k1, a, int(starts[k1]) if k1 < len(starts) else n
        k0 = k1


def slots(order: np.ndarray, scratch: Scratch | None = None) -> np.ndarray:
    """Each item's slot, ``order`` inverted (4 bytes an item while they fit), a step at a
    time; with ``scratch``, in a file."""
    return placed(order, new_array(scratch, len(order), _kernels.index_type(len(order))))


def outward_float32(boxes: np.ndarray) -> np.ndarray:
    """``boxes`` as float32, each side moved outward to the next float32 where rounding moved
    it inward: the rounded box always contains the exact one."""
    limit = float(np.finfo(np.float32).max)
    if boxes.size and np.abs(boxes).max() > limit:
        row = int(np.argwhere(np.abs(boxes) > limit)[0, 0])
        raise ValueError(f"box {row} is beyond float32's range (|v| <= {limit:.4g}); use coords='float64'")
    rounded = boxes.astype(np.float32)
    lo, hi = rounded[:, :2], rounded[:, 2:]
    down = lo > boxes[:, :2]
    lo[down] = np.nextafter(lo[down], np.float32(-np.inf))
    up = hi < boxes[:, 2:]
    hi[up] = np.nextafter(hi[up], np.float32(np.inf))
    return rounded


def aligned(array: np.ndarray) -> np.ndarray:
    """A copy of ``array`` starting on a 64-byte boundary, so each node record is one cache line."""
    out = aligned_empty(array.shape, array.dtype)
    out[...] = array
    return out


def aligned_empty(shape: tuple[int, ...], dtype: Any) -> np.ndarray:
    """An array starting on a 64-byte boundary, not filled in."""
    size = int(np.prod(shape)) * np.dtype(dtype).itemsize
    raw = np.empty(size + 64, np.uint8)
    offset = -raw.ctypes.data % 64
    return raw[offset : offset + size].view(dtype).reshape(shape)

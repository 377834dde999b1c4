"""Validation of boxes and rectangles at the library's door, with messages that name the fix.

Boxes and viewports are ``(x0, y0, x1, y1)`` with ``x0 <= x1`` and ``y0 <= y1``, all finite.
Intervals are closed: boxes that touch intersect.
"""

import math
from collections.abc import Sequence

import numpy as np

__all__ = [
    "RectLike",
    "as_box_array",
    "as_ids",
    "as_min_size",
    "as_rect",
    "first_bad_box",
]

RectLike = Sequence[float] | np.ndarray
_INF = math.inf
_AXES = ("x0", "y0", "x1", "y1")


def as_rect(rect: RectLike, name: str = "rect") -> tuple[float, float, float, float]:
    """``rect`` as four floats, or ValueError saying which coordinate is wrong.

    >>> as_rect([0, 1, 2, 3])
    (0.0, 1.0, 2.0, 3.0)
    """
    try:
        x0, y0, x1, y1 = rect
        x0, y0, x1, y1 = float(x0), float(y0), float(x1), float(y1)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be four numbers (x0, y0, x1, y1), got {rect!r}") from None
    # One chained comparison rejects NaN, infinities and inverted sides on the fast path.
    if -_INF < x0 <= x1 < _INF and -_INF < y0 <= y1 < _INF:
        return x0, y0, x1, y1
    for axis, value in zip(_AXES, (x0, y0, x1, y1), strict=True):
        if not math.isfinite(value):
            raise ValueError(f"{name} has {axis}={value}; coordinates must be finite")
    if x0 > x1:
        raise ValueError(f"{name} has x0={x0} > x1={x1}; swap them")
    raise ValueError(f"{name} has y0={y0} > y1={y1}; swap them")


def as_box_array(boxes: object) -> np.ndarray:
    """``boxes`` as a C-contiguous (n, 4) float64 array, or ValueError naming the first bad row."""
    array = np.ascontiguousarray(boxes, dtype=np.float64)
    if array.size == 0:
        return np.empty((0, 4), np.float64)
    if array.ndim != 2 or array.shape[1] != 4:
        raise ValueError(f"boxes must have shape (n, 4) as x0, y0, x1, y1; got {array.shape}")
    bad = first_bad_box(array)
    if bad is not None:
        raise ValueError(f"box {bad[0]} has {bad[1]}")
    return array


def first_bad_box(boxes: np.ndarray) -> tuple[int, str] | None:
    """``(row, why)`` for the first box of an (n, 4) float64 array that is not finite or is
    inverted, or None when all are valid."""
    bad = ~np.isfinite(boxes)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        return int(row), f"{_AXES[col]}={boxes[row, col]}; coordinates must be finite"
    for lo, hi in ((0, 2), (1, 3)):
        inverted = np.flatnonzero(boxes[:, lo] > boxes[:, hi])
        if inverted.size:
            row = int(inverted[0])
            return row, f"{_AXES[lo]}={boxes[row, lo]} > {_AXES[hi]}={boxes[row, hi]}; swap them"
    return None


def as_ids(ids: object, n: int) -> np.ndarray:
    """``ids`` as an int64 array of length n (default ``0..n-1``); uniqueness is checked by the tree."""
    if ids is None:
        return np.arange(n, dtype=np.int64)
    array = np.asarray(ids)
    if array.ndim != 1 or array.shape[0] != n:
        raise ValueError(f"ids must be a 1-d array of {n} integers, one per box; got shape {array.shape}")
    if array.size and not np.issubdtype(array.dtype, np.integer):
        raise ValueError(f"ids must be integers; got dtype {array.dtype}")
    return np.ascontiguousarray(array, dtype=np.int64)


def as_min_size(min_size: float, name: str = "min_size") -> float:
    """``min_size`` as a float >= 0, or ValueError."""
    value = float(min_size)
    if not 0.0 <= value < _INF:
        raise ValueError(f"{name} must be finite and >= 0, got {min_size!r}")
    return value

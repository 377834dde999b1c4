"""Validation of boxes and rectangles at the library's door, with messages that name the fix.

Boxes and viewports are ``(x0, y0, x1, y1)`` with ``x0 <= x1`` and ``y0 <= y1``, all finite.
Intervals are closed: boxes that touch intersect.
"""

import math
from collections.abc import Iterable, Sequence

import numpy as np

from .paging import in_steps

__all__ = [
    "Rect",
    "RectLike",
    "as_box_array",
    "as_id",
    "as_ids",
    "as_min_size",
    "as_rect",
    "first_bad_box",
    "touches",
]

Rect = tuple[float, float, float, float]  # (x0, y0, x1, y1), checked
RectLike = Sequence[float] | np.ndarray  # anything as_rect takes
_INF = math.inf
_AXES = ("x0", "y0", "x1", "y1")
_ID_MIN, _ID_MAX = -(2**63), 2**63 - 1


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
    raise ValueError(f"{name} has {_fault(x0, y0, x1, y1)}")


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
    """``(row, why)`` for the first row of an (n, 4) float64 array that is not finite or is
    inverted, or None when all are valid.

    >>> first_bad_box(np.array([[0, 0, 1, 1], [0, 5, 1, 4], [5, 0, 4, np.nan]]))
    (1, 'y0=5.0 > y1=4.0; swap them')
    """
    for lo, rows in in_steps(boxes):  # a mapped import's boxes: a step's pages held at once
        good = np.isfinite(rows).all(axis=1) & (rows[:, 0] <= rows[:, 2]) & (rows[:, 1] <= rows[:, 3])
        if not good.all():
            row = lo + int(np.argmin(good))  # the first False: the smallest bad row, whatever makes it bad
            return row, _fault(*boxes[row].tolist())
    return None


def _fault(x0: float, y0: float, x1: float, y1: float) -> str:
    """Why a box is bad: its first coordinate that is not finite, else its first inverted side."""
    for axis, value in zip(_AXES, (x0, y0, x1, y1), strict=True):
        if not math.isfinite(value):
            return f"{axis}={value}; coordinates must be finite"
    if x0 > x1:
        return f"x0={x0} > x1={x1}; swap them"
    return f"y0={y0} > y1={y1}; swap them"


def as_id(item_id: object) -> int:
    """``item_id`` as a Python int: a Python or numpy integer in int64's range; not a float
    (not even 8.0: ids are never rounded into another item's) and not a bool.

    >>> as_id(np.int32(7)), as_id(2**63 - 1)
    (7, 9223372036854775807)

    :raises ValueError: naming the id, if it is not an integer or is outside int64's range
    """
    if not isinstance(item_id, int | np.integer) or isinstance(item_id, bool):
        raise ValueError(f"id {item_id!r} is not an integer; ids must be integers (Python or numpy ints)")
    value = int(item_id)
    if not _ID_MIN <= value <= _ID_MAX:
        raise ValueError(f"id {value} is outside int64's range [-2**63, 2**63 - 1]; ids must fit in it")
    return value


def as_ids(ids: object, n: int) -> np.ndarray:
    """``ids`` as an int64 array of length n (default ``0..n-1``); uniqueness is checked by the tree.

    :raises ValueError: if there are not n ids, or naming the first id that ``as_id`` refuses
    """
    if ids is None:
        return np.arange(n, dtype=np.int64)
    array = np.asarray(ids)
    if array.ndim != 1 or array.shape[0] != n:
        raise ValueError(f"ids must be a 1-d array of {n} integers, one per box; got shape {array.shape}")
    if array.dtype.kind == "i" or (array.dtype.kind == "u" and not (array.size and array.max() > _ID_MAX)):
        return np.ascontiguousarray(array, dtype=np.int64)
    # Floats, bools, objects, or uint64 past int64 (numpy's dtype for Python ints beyond it):
    # check each as given, so the first bad id is named as the caller wrote it (an array, or an
    # array-like that can't be iterated, through its list).
    given = ids if isinstance(ids, Iterable) and not isinstance(ids, np.ndarray) else array.tolist()
    return np.fromiter(map(as_id, given), np.int64, n)


def as_min_size(min_size: float, name: str = "min_size") -> float:
    """``min_size`` as a float >= 0.

    :raises ValueError: naming the value, if it is not one number or not finite and >= 0
    """
    try:
        value = float(min_size)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be one number, got {min_size!r}") from None
    if not 0.0 <= value < _INF:
        raise ValueError(f"{name} must be finite and >= 0, got {min_size!r}")
    return value


def touches(a: RectLike, b: RectLike) -> bool:
    """Whether boxes ``a`` and ``b`` intersect or touch (closed intervals), the one rule every
    answer follows.

    >>> touches((0, 0, 1, 1), (1, 1, 2, 2)), touches((0, 0, 1, 1), (1.5, 0, 2, 1))
    (True, False)
    """
    return a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]

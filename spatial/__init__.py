"""Vantage's spatial index: a query-optimised quadtree with viewport diffs and level of detail.

Beside ``QuadTree`` and the rect helpers, the bounded-memory foundation builds stand on is
public: ``spatial.paging`` (passes a step or a window at a time over arrays mapped from
files), ``spatial.sorting`` (keys sorted in files a run at a time), ``spatial.budget``
(``MemoryBudget``: what a build in files holds at once) and ``spatial.kernels`` (what
compiled code outside the library may call). Modules whose names start with ``_`` are the
library's own.
"""

from . import _cpu  # noqa: F401  (first: the CPU numba compiles the kernels for)
from .budget import MemoryBudget
from .quadtree import QuadTree
from .rect import Rect, RectLike, touches

__all__ = [
    "MemoryBudget",
    "QuadTree",
    "Rect",
    "RectLike",
    "touches",
]

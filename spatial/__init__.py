"""Vantage's spatial index: a query-optimised quadtree with viewport diffs and level of detail."""

from . import _cpu  # noqa: F401  (first: the CPU numba compiles the kernels for)
from .quadtree import QuadTree
from .rect import Rect, RectLike, touches

__all__ = [
    "QuadTree",
    "Rect",
    "RectLike",
    "touches",
]

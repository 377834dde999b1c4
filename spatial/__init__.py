"""Vantage's spatial index: a query-optimised quadtree with viewport diffs and level of detail."""

from .quadtree import QuadTree
from .rect import Rect, RectLike, touches

__all__ = [
    "QuadTree",
    "Rect",
    "RectLike",
    "touches",
]

"""Brute force: the obviously-correct answers every index answer is compared with."""

import numpy as np


def hits(boxes: np.ndarray, rect, min_size: float = 0.0) -> np.ndarray:
    """Mask of boxes that intersect or touch ``rect`` (closed intervals) and are >= min_size."""
    x0, y0, x1, y1 = rect
    size = np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])
    touching = (boxes[:, 0] <= x1) & (boxes[:, 2] >= x0) & (boxes[:, 1] <= y1) & (boxes[:, 3] >= y0)
    return touching & (size >= min_size)


def query(boxes: np.ndarray, ids: np.ndarray, rect, min_size: float = 0.0) -> set[int]:
    return set(ids[hits(boxes, rect, min_size)].tolist())

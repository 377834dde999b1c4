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


def check_shown(boxes: np.ndarray, ids: list[str], rect, size: float, entries: list[dict]) -> None:
    """``entries`` (an answer's items and aggregates) show ``rect`` at a level of detail: exactly
    the items of at least ``size`` touching it, and for every smaller item touching it, an
    aggregate whose box contains its box; every aggregate touches ``rect``."""
    real = {e["id"] for e in entries if "agg" not in e}
    assert real == {ids[i] for i in np.flatnonzero(hits(boxes, rect, size))}
    aggs = np.array([[e[k] for k in ("x0", "y0", "x1", "y1")] for e in entries if "agg" in e]).reshape(-1, 4)
    assert hits(aggs, rect).all(), "an aggregate that does not touch the viewport"
    small = boxes[hits(boxes, rect) & ~hits(boxes, rect, size)]
    for box in small:
        inside = (
            (aggs[:, 0] <= box[0]) & (aggs[:, 1] <= box[1]) & (box[2] <= aggs[:, 2]) & (box[3] <= aggs[:, 3])
        )
        assert inside.any(), f"item {box.tolist()} is neither shown nor inside an aggregate"

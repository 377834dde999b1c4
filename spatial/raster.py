"""Occupancy in a pixel grid: which pixels the members of each group of boxes touch.

A screen draws a box over every pixel it touches, and over one pixel at least, however small
it is. :func:`occupancy` gives, for each group (an aggregate), the pixels of that grid its
members touch, over the pixels its own box touches: what drawing every member would ink,
without sending the members.

>>> import numpy as np
>>> members = np.array([[0.0, 0.0, 0.2, 0.2], [3.5, 1.0, 3.6, 1.2]])
>>> (c0, r0, w, h), = occupancy(members, np.array([0, 0]), np.array([[0.0, 0.0, 4.0, 2.0]]), (0.0, 0.0), 1.0)[0]
>>> (c0, r0, w, h)
(0, 0, 4, 2)
>>> occupancy(members, np.array([0, 0]), np.array([[0.0, 0.0, 4.0, 2.0]]), (0.0, 0.0), 1.0)[1][0].tolist()
[[True, False, False, False], [False, False, False, True]]
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["occupancy", "pixel_spans"]


def pixel_spans(lo: np.ndarray, hi: np.ndarray, origin: float, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """First and last pixel along one axis that each box ``[lo, hi]`` touches, at least one,
    in a grid of ``scale`` pixels a unit whose pixel 0 starts at ``origin``. Bounded to
    +-2**52, so any finite box has spans."""
    limit = 2.0**52
    with np.errstate(over="ignore", invalid="ignore"):
        first = np.clip(np.floor((lo - origin) * scale), -limit, limit)
        last = np.clip(np.ceil((hi - origin) * scale) - 1, -limit, limit)
    first = np.nan_to_num(first, nan=0.0)
    last = np.maximum(np.nan_to_num(last, nan=0.0), first)
    return first.astype(np.int64), last.astype(np.int64)


def occupancy(
    members: np.ndarray,
    owner: np.ndarray,
    groups: np.ndarray,
    origin: tuple[float, float],
    scale: float,
    most: int = 1 << 22,
    slack: float = 0.0,
    total: int | None = None,
) -> tuple[list[tuple[int, int, int, int]], list[np.ndarray]]:
    """For each of ``groups`` (boxes, (g, 4)): the window of pixels its box touches, ``(c0, r0,
    w, h)``, and which of them its ``members`` (boxes, (m, 4), each of group ``owner[i]``)
    touch, a (h, w) bool array. ``origin`` is the canvas point where pixel (0, 0) starts; every
    box counts as ``slack`` pixels larger on each side (for a grid placed to within it). A
    group whose window holds more than ``most`` pixels gets none (w = h = 0), and so do the
    groups past the first whose windows hold ``total`` pixels together. Cost: O(members + the
    windows' pixels), compiled: at most ``total``."""
    if slack:
        members, groups = _grown(members, slack / scale), _grown(groups, slack / scale)
    c0, c1 = pixel_spans(groups[:, 0], groups[:, 2], origin[0], scale)
    r0, r1 = pixel_spans(groups[:, 1], groups[:, 3], origin[1], scale)
    w, h = c1 - c0 + 1, r1 - r0 + 1
    area = w.astype(np.float64) * h
    huge = area > most
    if total is not None:  # in order, while the windows fit in ``total`` together
        huge |= np.cumsum(np.where(huge, 0.0, area)) > total
    w[huge] = h[huge] = 0
    mc0, mc1 = pixel_spans(members[:, 0], members[:, 2], origin[0], scale)
    mr0, mr1 = pixel_spans(members[:, 1], members[:, 3], origin[1], scale)
    starts = np.concatenate([[0], np.cumsum(w * h)])
    bits = _raster(mc0, mc1, mr0, mr1, np.asarray(owner, np.int64), c0, r0, w, h, starts)
    windows = list(zip(c0.tolist(), r0.tolist(), w.tolist(), h.tolist(), strict=True))
    masks = [bits[starts[k] : starts[k + 1]].reshape(h[k], w[k]) for k in range(len(groups))]
    return windows, masks


def _grown(boxes: np.ndarray, by: float) -> np.ndarray:
    return boxes + np.array([-by, -by, by, by])


@nb.njit(cache=True, nogil=True)
def _raster(mc0, mc1, mr0, mr1, owner, c0, r0, w, h, starts):  # pragma: no cover - compiled
    """Each member's pixels, clipped to its group's window, marked in a difference grid per
    group (four corners each), then summed along both axes: the pixels covered."""
    corner = np.empty(len(w) + 1, np.int64)  # where each group's difference grid starts
    corner[0] = 0
    for k in range(len(w)):
        corner[k + 1] = corner[k] + (w[k] + 1) * (h[k] + 1)
    diff = np.zeros(corner[-1], np.int32)
    for i in range(len(owner)):
        k = owner[i]
        a0 = max(mc0[i] - c0[k], 0)
        a1 = min(mc1[i] - c0[k], w[k] - 1)
        b0 = max(mr0[i] - r0[k], 0)
        b1 = min(mr1[i] - r0[k], h[k] - 1)
        if a0 > a1 or b0 > b1:
            continue
        o, s = corner[k], w[k] + 1
        diff[o + b0 * s + a0] += 1
        diff[o + b0 * s + a1 + 1] -= 1
        diff[o + (b1 + 1) * s + a0] -= 1
        diff[o + (b1 + 1) * s + a1 + 1] += 1
    bits = np.zeros(starts[-1], np.bool_)
    for k in range(len(w)):
        o, s, out = corner[k], w[k] + 1, starts[k]
        for y in range(h[k]):
            for x in range(w[k]):
                here = diff[o + y * s + x]
                if x > 0:
                    here += diff[o + y * s + x - 1]
                if y > 0:
                    here += diff[o + (y - 1) * s + x]
                if x > 0 and y > 0:
                    here -= diff[o + (y - 1) * s + x - 1]
                diff[o + y * s + x] = here
                bits[out + y * w[k] + x] = here > 0
    return bits

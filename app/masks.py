"""Aggregates' masks in answers: the pixels of the client's screen an aggregate's members cover.

An aggregate's box is a poor stand-in for what it holds when its members leave much of the box
empty (a round cluster of notes, a field of specks): drawn whole, it paints canvas that is
blank. So each aggregate in an answer at a level of detail carries a *mask*, one bit a pixel
of the client's screen over its box: the pixels its members touch, as drawing each member (one
pixel at least) would ink (``Overview.masks`` finds them). Here: the screen's pixel grid, and
the JSON.
"""

from __future__ import annotations

import base64
import math

import numpy as np

from .snapshots import Snapshot

__all__ = [
    "Grid",
    "MAX_ANSWER_MASK_PIXELS",
    "MAX_MASK_PIXELS",
    "PHASE_STEPS",
    "grid_of",
    "mask_json",
    "masks",
    "windows",
]

MAX_MASK_PIXELS = 1 << 22  # an aggregate whose box covers more pixels goes without a mask
# An answer's masks cover at most this many pixels together (a full-HD screen with its
# overscan needs ~3M): past it, aggregates go without, so no request can ask for unbounded work.
MAX_ANSWER_MASK_PIXELS = 1 << 24
PHASE_STEPS = 256  # a screen's pixel grid is placed to 1/256 of a pixel

# A screen's pixel grid: pixels a unit, and where its lines fall within a pixel along x and y
# (in PHASE_STEPS). Two viewports a whole number of pixels apart at one scale share it, so a
# mask made for one is right for the other; any other move makes masks anew.
Grid = tuple[float, int, int]


def grid_of(corner: tuple[float, float], scale: float | None) -> Grid | None:
    """The pixel grid of a screen of ``scale`` pixels a unit whose pixel (0, 0) starts at
    ``corner`` (None without a scale)."""
    if not scale:
        return None
    at = [c * scale for c in corner]  # past 2**52 every float is whole: phase 0, as for an overflow
    phase = [round(a % 1.0 * PHASE_STEPS) % PHASE_STEPS if math.isfinite(a) else 0 for a in at]
    return scale, phase[0], phase[1]


def masks(snap: Snapshot, band: int, aggregates: np.ndarray, grid: Grid) -> list[bytes]:
    """The ``"mask"`` JSON member of each of ``band``'s ``aggregates``, in order (``b""`` for
    one without: too big), in the pixels of ``grid``. A mask's corner is a grid point, so the
    same aggregate in the same grid has the same mask, byte for byte."""
    if snap.overview is None or not len(aggregates) or not grid[0] > 0:
        return [b""] * len(aggregates)
    return [
        mask_json(window, mask, grid)
        for window, mask in zip(*windows(snap, band, aggregates, grid), strict=True)
    ]


def windows(
    snap: Snapshot, band: int, aggregates: np.ndarray, grid: Grid
) -> tuple[list[tuple[int, int, int, int]], list[np.ndarray]]:
    """Each of ``band``'s ``aggregates``' window of ``grid``'s pixels and which of them its
    members touch (``Overview.masks``; none past MAX_MASK_PIXELS, or past
    MAX_ANSWER_MASK_PIXELS together). ``snap`` has an overview."""
    overview = snap.overview
    assert overview is not None
    scale = grid[0]
    # A grid point near 0; the screen's own is within 1/512 pixel of it: every box counts as
    # 1/256 pixel larger, so no pixel a member touches is missed.
    corner = (grid[1] / PHASE_STEPS / scale, grid[2] / PHASE_STEPS / scale)
    return overview.masks(
        band,
        aggregates,
        corner,
        scale,
        snap.tree,
        snap.item_boxes,
        MAX_MASK_PIXELS,
        1 / PHASE_STEPS,
        MAX_ANSWER_MASK_PIXELS,
    )


def mask_json(window: tuple[int, int, int, int], mask: np.ndarray, grid: Grid) -> bytes:
    """An aggregate's ``"mask"`` JSON member: its corner and cell in canvas units, its size in
    cells and its bits, row by row, least significant first, base64 (``b""``: no mask, as past
    MAX_MASK_PIXELS or the answer's MAX_ANSWER_MASK_PIXELS: the aggregate is drawn as its box)."""
    c0, r0, w, h = window
    if not w:
        return b""
    scale = grid[0]
    packed = base64.b64encode(np.packbits(mask, bitorder="little").tobytes()).decode()
    x0, y0 = float((c0 + grid[1] / PHASE_STEPS) / scale), float((r0 + grid[2] / PHASE_STEPS) / scale)
    return f'"mask":{{"x0":{x0!r},"y0":{y0!r},"cell":{1.0 / scale!r},"w":{w},"h":{h},"bits":"{packed}"}}'.encode()

"""Viewports as pictures (trades 2 and 6): each box fills the pixels it touches, the topmost kind wins;
or, as ink, each box at an opacity."""

from __future__ import annotations

import numpy as np

from spatial import Rect, scenes

SCREEN = (1920, 1080)  # pixels of the rasterised pictures (level of detail)
Z_ORDER = ("page", "frame", "image", "note", "box", "text")  # kinds painted bottom to top


def pixel_span(lo: np.ndarray, hi: np.ndarray, origin: float, zoom: float, n: int) -> tuple[np.ndarray, ...]:
    """First and last pixel a box covers along one axis: at least one, clipped to the screen."""
    first = np.floor((lo - origin) * zoom)
    last = np.maximum(np.ceil((hi - origin) * zoom) - 1, first)
    return np.clip(first, 0, n - 1).astype(np.intp), np.clip(last, 0, n - 1).astype(np.intp)


def coverage(c0: np.ndarray, c1: np.ndarray, r0: np.ndarray, r1: np.ndarray) -> np.ndarray:
    """Boxes covering each pixel, (h, w): corner increments summed along both axes."""
    w, h = SCREEN
    stride = w + 1
    corners = np.concatenate(
        [r0 * stride + c0, r0 * stride + c1 + 1, (r1 + 1) * stride + c0, (r1 + 1) * stride + c1 + 1]
    )
    signs = np.repeat(np.array([1.0, -1.0, -1.0, 1.0]), c0.size)
    grid = np.bincount(corners, weights=signs, minlength=(h + 1) * stride).reshape(h + 1, stride)
    return grid.cumsum(axis=0).cumsum(axis=1)[:h, :w]


def render(boxes: np.ndarray, kinds: np.ndarray, view: Rect, zoom: float) -> np.ndarray:
    """The viewport as a (h, w) picture: each pixel holds the topmost kind covering it (0: none).

    Kinds are painted bottom to top in ``Z_ORDER`` (pages under images under words), each box
    filling every pixel it touches and at least one.
    """
    w, h = SCREEN
    picture = np.zeros((h, w), np.uint8)
    c0, c1 = pixel_span(boxes[:, 0], boxes[:, 2], view[0], zoom, w)
    r0, r1 = pixel_span(boxes[:, 1], boxes[:, 3], view[1], zoom, h)
    for layer, name in enumerate(Z_ORDER, 1):
        sel = kinds == scenes.KINDS.index(name)
        if sel.any():
            picture[coverage(c0[sel], c1[sel], r0[sel], r1[sel]) > 0.5] = layer
    return picture


def ink(boxes: np.ndarray, alpha: np.ndarray, view: Rect, zoom: float) -> np.ndarray:
    """The viewport as (h, w) opacities in 0..1: each box fills every pixel it touches (and at
    least one) at its ``alpha``, the most opaque one showing where boxes overlap. Solid boxes
    (alpha 1) in one pass, the others one by one."""
    w, h = SCREEN
    c0, c1 = pixel_span(boxes[:, 0], boxes[:, 2], view[0], zoom, w)
    r0, r1 = pixel_span(boxes[:, 1], boxes[:, 3], view[1], zoom, h)
    solid = alpha >= 1.0
    picture = (coverage(c0[solid], c1[solid], r0[solid], r1[solid]) > 0.5).astype(np.float64)
    for k in np.flatnonzero(~solid)[np.argsort(alpha[~solid], kind="stable")]:
        cell = picture[r0[k] : r1[k] + 1, c0[k] : c1[k] + 1]
        np.maximum(cell, alpha[k], out=cell)
    return picture


def paint_masks(
    picture: np.ndarray, masks: list[tuple[tuple[int, int, int, int], np.ndarray, int]]
) -> np.ndarray:
    """``picture`` with each mask's set pixels painted its kind's layer, over what is lower in
    ``Z_ORDER`` (a mask's window ``(c0, r0, w, h)`` is in the picture's pixels; kind 0 paints
    layer 1, for ink)."""
    h_screen, w_screen = picture.shape
    for (c0, r0, w, h), bits, kind in masks:
        layer = Z_ORDER.index(scenes.KINDS[kind]) + 1 if kind else 1
        x0, y0 = max(c0, 0), max(r0, 0)
        x1, y1 = min(c0 + w, w_screen), min(r0 + h, h_screen)
        if x0 >= x1 or y0 >= y1:
            continue
        window = picture[y0:y1, x0:x1]
        inked = bits[y0 - r0 : y1 - r0, x0 - c0 : x1 - c0]
        window[inked] = np.maximum(window[inked], layer)
    return picture

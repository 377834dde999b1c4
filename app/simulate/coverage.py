"""Blank area: what a person sees at the screen's edge while data is on its way."""

from __future__ import annotations

from spatial import Rect

__all__ = ["blank_share"]


def blank_share(screen: Rect, held: Rect | None) -> float:
    """Share of ``screen`` outside ``held``, the rect whose items the client has received.

    >>> blank_share((0, 0, 100, 100), (50, 0, 300, 300))
    0.5
    >>> blank_share((0, 0, 100, 100), None)
    1.0
    """
    if held is None:
        return 1.0
    area = (screen[2] - screen[0]) * (screen[3] - screen[1])
    if area <= 0:
        return 0.0
    w = min(screen[2], held[2]) - max(screen[0], held[0])
    h = min(screen[3], held[3]) - max(screen[1], held[1])
    return 1.0 - max(w, 0.0) * max(h, 0.0) / area

"""When the page asks the server for more, and for which rect: read from the file the page
reads (``static/policy.json``), with the page's arithmetic (``static/vantage-client.js``), so the
simulator's users fetch as a person's page does.

The page asks for the screen plus an overscan margin on every side, stretched towards where a
moving screen will be in ``lookaheadS`` seconds, and asks again when the screen, looking half
that far ahead, comes within ``refetchAt`` of that margin's edge, or when the zoom changed by
more than ``lodStep``.
"""

from __future__ import annotations

import json
import math
from importlib import resources

from spatial import Rect

__all__ = ["Fetcher", "POLICY"]

POLICY: dict[str, float] = json.loads((resources.files("app") / "static" / "policy.json").read_text())


def on_pixels(rect: Rect, screen: Rect, scale: float) -> Rect:
    """The page's ``onPixels``: ``rect`` grown out to ``screen``'s pixel grid at ``scale``."""
    sx, sy = screen[0], screen[1]
    return (
        sx + math.floor((rect[0] - sx) * scale) / scale,
        sy + math.floor((rect[1] - sy) * scale) / scale,
        sx + math.ceil((rect[2] - sx) * scale) / scale,
        sy + math.ceil((rect[3] - sy) * scale) / scale,
    )


def grown(rect: Rect, share: float) -> Rect:
    dx, dy = (rect[2] - rect[0]) * share, (rect[3] - rect[1]) * share
    return rect[0] - dx, rect[1] - dy, rect[2] + dx, rect[3] + dy


def inside(inner: Rect, outer: Rect) -> bool:
    return inner[0] >= outer[0] and inner[1] >= outer[1] and inner[2] <= outer[2] and inner[3] <= outer[3]


class Fetcher:
    """One page's fetch decisions; ``overscan`` (the page's by default) may be varied to compare."""

    def __init__(self, overscan: float = POLICY["overscan"]) -> None:
        self.overscan = overscan
        self.velocity = (0.0, 0.0)  # canvas units per second, smoothed
        self._last: tuple[float, float, float, float] | None = None  # t, x, y, scale

    def track(self, t: float, screen: Rect, scale: float) -> None:
        """The page's ``track``: the screen's velocity, smoothed over ``smoothingS``; a zoom is not a fling."""
        x, y = screen[0], screen[1]
        if self._last is not None and t > self._last[0]:
            dt = t - self._last[0]
            k = min(1.0, dt / POLICY["smoothingS"])
            vx = self.velocity[0] + k * ((x - self._last[1]) / dt - self.velocity[0])
            vy = self.velocity[1] + k * ((y - self._last[2]) / dt - self.velocity[1])
            self.velocity = (0.0, 0.0) if scale != self._last[3] else (vx, vy)
        self._last = (t, x, y, scale)

    def ahead(self, rect: Rect, seconds: float) -> Rect:
        """``rect`` stretched towards where the screen is heading in ``seconds``."""
        dx, dy = self.velocity[0] * seconds, self.velocity[1] * seconds
        return rect[0] + min(dx, 0), rect[1] + min(dy, 0), rect[2] + max(dx, 0), rect[3] + max(dy, 0)

    def needs(self, requested: Rect | None, requested_scale: float, screen: Rect, scale: float) -> bool:
        """The page's ``needsRequest``."""
        if requested is None:
            return True
        ratio = scale / requested_scale
        if ratio > POLICY["lodStep"] or ratio < 1 / POLICY["lodStep"]:
            return True
        margin = self.overscan
        safe = grown(requested, -POLICY["refetchAt"] * margin / (1 + 2 * margin))
        return not inside(self.ahead(screen, POLICY["lookaheadS"] / 2), safe)

    def rect(self, screen: Rect, scale: float) -> Rect:
        """The page's ``nextRequest``: the rect to ask for."""
        return on_pixels(self.ahead(grown(screen, self.overscan), POLICY["lookaheadS"]), screen, scale)

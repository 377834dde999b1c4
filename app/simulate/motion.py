"""How people pan: seeded camera paths of steady scrolls, flings that decay, pauses, zooms
around a point, and jumps to an item ("go to search result"), one camera per 60 Hz frame; and
for some, every so often, a look at the whole document (zoom out to Fit, look, dive in
elsewhere), as people on a canvas do."""

from __future__ import annotations

import numpy as np

__all__ = ["FPS", "fit_scale", "screen_rect", "user_path"]

FPS = 60
# behaviour: (share of segments, seconds it lasts: low, high)
BEHAVIOURS = {
    "scroll": (0.40, 0.6, 2.5),  # steady, 300-1500 px/s, mostly down
    "fling": (0.20, 0.8, 1.6),  # 2,000-8,000 px/s, decaying with a 0.35 s time constant
    "pause": (0.20, 0.3, 1.5),
    "zoom": (0.12, 0.3, 0.7),  # 0.5x-2x around a point on screen
    "jump": (0.08, 0.2, 0.2),  # to a random item, then a short rest
}
# A look at the whole document, seconds (low, high) of each step: zooming out to Fit (unless
# the Fit key, one frame, a share FIT_KEY of the time), looking (with a nudge of NUDGE pixels
# in some direction, taking NUDGE_S, in the middle), and diving in elsewhere.
ZOOM_OUT, LOOK, DIVE, FIT_KEY = (0.4, 1.2), (1.0, 3.0), (0.6, 1.5), 0.3
NUDGE, NUDGE_S = (100.0, 400.0), (0.2, 0.5)


def fit_scale(bounds: tuple[float, float, float, float], screen: tuple[float, float]) -> float:
    """The page's Fit (``fit(true)`` in ``static/app.js``): the scale at which the document's
    bounds fit the screen, with 5% to spare.

    >>> fit_scale((0, 0, 1000, 100), (1280, 800))
    1.216
    """
    w, h = max(bounds[2] - bounds[0], 1e-9), max(bounds[3] - bounds[1], 1e-9)
    return min(screen[0] / w, screen[1] / h) * 0.95


def screen_rect(camera: np.ndarray, screen: tuple[float, float]) -> tuple[float, float, float, float]:
    """The canvas rect a camera ``(x, y, scale)`` shows: ``x, y`` at the top-left corner."""
    x, y, scale = (float(v) for v in camera)
    return x, y, x + screen[0] / scale, y + screen[1] / scale


def user_path(
    seed: int,
    bounds: tuple[float, float, float, float],
    anchors: np.ndarray,
    seconds: float,
    screen: tuple[float, float] = (1280.0, 800.0),
    zoom_out_every: float | None = None,
    places: np.ndarray | None = None,
) -> np.ndarray:
    """Cameras ``(x, y, scale)`` for each frame of ``seconds`` at 60 Hz, over a document with
    these ``bounds``; jumps land on one of ``anchors`` ((k, 2) item centres).

    The start is a random anchor at a scale where the document's width fits the screen, or at
    1 px per unit for documents wider than ten screens; zooms stay within 1/8x-4x of it.

    With ``zoom_out_every`` (seconds), the user also looks at the whole document about that
    often (the first time within that many seconds, then every 0.5x-1.5x of it): zooms out to
    Fit (``fit_scale``) around the screen's centre, or presses the Fit key, looks for 1-3 s,
    then dives back in to near the start's scale on one of ``places`` ((k, 2) points; default
    ``anchors``), the point under the cursor staying under it as it does with a mouse wheel.
    Without it, the path is the same as before this option (its own random numbers).
    """
    rng = np.random.default_rng(seed)
    looks = np.random.default_rng([seed, 1])  # the looks' times and targets, apart from the rest
    targets = anchors if places is None or not len(places) else places
    every = zoom_out_every or np.inf
    next_look = looks.uniform(0, every) if zoom_out_every else np.inf
    width = bounds[2] - bounds[0]
    base = 1.0 if width > 10 * screen[0] else screen[0] / max(width, 1e-9) * 0.95
    names = list(BEHAVIOURS)
    shares = np.array([BEHAVIOURS[n][0] for n in names])
    n = max(1, round(seconds * FPS))
    out = np.empty((n, 3))
    cx, cy = anchors[rng.integers(len(anchors))] if len(anchors) else (0.0, 0.0)
    scale = base
    i = 0
    while i < n:
        if i / FPS >= next_look:
            i, cx, cy, scale = _look(out, i, looks, bounds, targets, (cx, cy, scale), base, screen)
            next_look = i / FPS + looks.uniform(0.5, 1.5) * every
            continue
        name = names[rng.choice(len(names), p=shares / shares.sum())]
        _, low, high = BEHAVIOURS[name]
        frames = min(n - i, max(1, round(rng.uniform(low, high) * FPS)))
        vx = vy = 0.0  # px per second
        zoom_to, pivot = scale, (0.0, 0.0)
        if name == "scroll":
            vy = rng.uniform(300, 1500) * (1 if rng.random() < 0.8 else -1)
            vx = rng.normal(0, 40)
        elif name == "fling":
            angle = rng.normal(np.pi / 2, 0.3) + (np.pi if rng.random() < 0.2 else 0.0)
            speed = rng.uniform(2000, 8000)
            vx, vy = speed * np.cos(angle), speed * np.sin(angle)
        elif name == "zoom":
            zoom_to = float(np.clip(scale * rng.uniform(0.5, 2.0), base / 8, base * 4))
            pivot = (rng.uniform(-0.4, 0.4) * screen[0], rng.uniform(-0.4, 0.4) * screen[1])
        elif name == "jump" and len(anchors):
            cx, cy = anchors[rng.integers(len(anchors))]
        start_scale = scale
        for k in range(frames):
            dt = 1.0 / FPS
            if name == "fling":
                decay = np.exp(-k * dt / 0.35)
                cx, cy = cx + vx * decay * dt / scale, cy + vy * decay * dt / scale
            elif name == "scroll":
                cx, cy = cx + vx * dt / scale, cy + vy * dt / scale
            elif name == "zoom":  # the canvas point under the pivot stays under it
                new = start_scale * (zoom_to / start_scale) ** ((k + 1) / frames)
                px, py = cx + pivot[0] / scale, cy + pivot[1] / scale
                cx, cy = px - pivot[0] / new, py - pivot[1] / new
                scale = new
            cx = float(np.clip(cx, bounds[0], bounds[2]))  # people stop at the document's edges
            cy = float(np.clip(cy, bounds[1], bounds[3]))
            out[i] = (cx - screen[0] / 2 / scale, cy - screen[1] / 2 / scale, scale)
            i += 1
    return out


def _look(
    out: np.ndarray,
    i: int,
    rng: np.random.Generator,
    bounds: tuple[float, float, float, float],
    places: np.ndarray,
    camera: tuple[float, float, float],
    base: float,
    screen: tuple[float, float],
) -> tuple[int, float, float, float]:
    """Frames from ``i`` on (as many as ``out`` holds) of a look at the whole document from
    ``camera`` (centre x, y, scale): out to Fit, a rest with a nudge, a dive into a place. The
    frame after, and the camera there."""
    fit = fit_scale(bounds, screen)
    middle = ((bounds[0] + bounds[2]) / 2, (bounds[1] + bounds[3]) / 2)
    to = places[rng.integers(len(places))] if len(places) else middle
    deep = float(np.clip(base * rng.uniform(0.5, 2.0), base / 8, base * 4))
    out_s = 0.0 if rng.random() < FIT_KEY else rng.uniform(*ZOOM_OUT)
    look, nudge_s = rng.uniform(*LOOK), rng.uniform(*NUDGE_S)
    angle, reach = rng.uniform(0, 2 * np.pi), rng.uniform(*NUDGE) / fit
    nudged = (
        float(np.clip(middle[0] + reach * np.cos(angle), bounds[0], bounds[2])),
        float(np.clip(middle[1] + reach * np.sin(angle), bounds[1], bounds[3])),
    )
    steps = [
        (camera[:2], camera[2], middle, fit, out_s),
        (middle, fit, middle, fit, look / 2),
        (middle, fit, nudged, fit, nudge_s),
        (nudged, fit, nudged, fit, max(look / 2 - nudge_s, 0.1)),
        (nudged, fit, (float(to[0]), float(to[1])), deep, rng.uniform(*DIVE)),
    ]
    cx, cy, scale = camera
    for start, s0, end, s1, seconds in steps:
        frames = max(1, round(seconds * FPS))
        for k in range(frames):
            if i >= len(out):
                return i, cx, cy, scale
            t = (k + 1) / frames
            scale = s0 * (s1 / s0) ** t
            # The centre moves as the view's size changes: a zoom around one point fixed on the
            # screen, which ends at ``end`` (and a rest, s0 == s1, stays put).
            w = t if s0 == s1 else (1 / scale - 1 / s0) / (1 / s1 - 1 / s0)
            cx, cy = start[0] + (end[0] - start[0]) * w, start[1] + (end[1] - start[1]) * w
            out[i] = (cx - screen[0] / 2 / scale, cy - screen[1] / 2 / scale, scale)
            i += 1
    return i, cx, cy, scale

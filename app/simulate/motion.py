"""How people pan: seeded camera paths of steady scrolls, flings that decay, pauses, zooms
around a point, and jumps to an item ("go to search result"), one camera per 60 Hz frame."""

from __future__ import annotations

import numpy as np

__all__ = ["FPS", "screen_rect", "user_path"]

FPS = 60
# behaviour: (share of segments, seconds it lasts: low, high)
BEHAVIOURS = {
    "scroll": (0.40, 0.6, 2.5),  # steady, 300-1500 px/s, mostly down
    "fling": (0.20, 0.8, 1.6),  # 2,000-8,000 px/s, decaying with a 0.35 s time constant
    "pause": (0.20, 0.3, 1.5),
    "zoom": (0.12, 0.3, 0.7),  # 0.5x-2x around a point on screen
    "jump": (0.08, 0.2, 0.2),  # to a random item, then a short rest
}


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
) -> np.ndarray:
    """Cameras ``(x, y, scale)`` for each frame of ``seconds`` at 60 Hz, over a document with
    these ``bounds``; jumps land on one of ``anchors`` ((k, 2) item centres).

    The start is a random anchor at a scale where the document's width fits the screen, or at
    1 px per unit for documents wider than ten screens; zooms stay within 1/8x-4x of it.
    """
    rng = np.random.default_rng(seed)
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

"""Seeded synthetic scenes and panning paths, shared by the tests, the benchmarks and the demo.

Every generator returns ``(boxes, kinds)``: boxes (n, 4) float64 ``x0, y0, x1, y1`` and kinds
(n,) uint8 indexing :data:`KINDS`. Same seed, same scene, on every machine.
"""

import numpy as np

__all__ = [
    "KINDS",
    "PAGE_GAP",
    "PAGE_HEIGHT",
    "PAGE_WIDTH",
    "long_document",
    "panning_path",
    "uniform",
    "whiteboard",
]

KINDS = ("page", "text", "image", "note", "frame", "box")
PAGE, TEXT, IMAGE, NOTE, FRAME, BOX = range(len(KINDS))

PAGE_WIDTH, PAGE_HEIGHT, PAGE_GAP = 612.0, 792.0, 24.0  # US letter in points
_MARGIN, _LINE_HEIGHT, _LINES = 72.0, 13.0, 46


def long_document(pages: int = 2000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Letter pages stacked in one column: a frame, ~46 lines of word boxes and an image each.

    About 520 items a page (2000 pages: ~1M items). Every page spans the same x range, the
    case where one global x-sorted list is useless.
    """
    rng = np.random.default_rng(seed)
    tops = np.arange(pages) * (PAGE_HEIGHT + PAGE_GAP)
    frames = np.column_stack([np.zeros(pages), tops, np.full(pages, PAGE_WIDTH), tops + PAGE_HEIGHT])

    # An image per page, somewhere in the text column, covering a band of lines.
    image_line = rng.integers(0, _LINES - 12, pages)
    image_lines = rng.integers(6, 12, pages)
    image_w = rng.uniform(200, PAGE_WIDTH - 2 * _MARGIN, pages)
    image_x = _MARGIN + rng.uniform(0, 1, pages) * (PAGE_WIDTH - 2 * _MARGIN - image_w)
    image_y = tops + _MARGIN + image_line * _LINE_HEIGHT
    images = np.column_stack([image_x, image_y, image_x + image_w, image_y + image_lines * _LINE_HEIGHT])

    # Words: each line is filled left to right with log-normal widths until the right margin.
    line_page = np.repeat(np.arange(pages), _LINES)
    line_no = np.tile(np.arange(_LINES), pages)
    covered = (line_no >= image_line[line_page]) & (line_no < (image_line + image_lines)[line_page])
    line_page, line_no = line_page[~covered], line_no[~covered]
    per_line = 16
    widths = np.clip(rng.lognormal(3.3, 0.45, (line_page.size, per_line)), 6, 160)
    gaps = 4.0
    x1 = _MARGIN + np.cumsum(widths + gaps, axis=1) - gaps
    x0 = x1 - widths
    keep = x1 <= PAGE_WIDTH - _MARGIN
    y0 = (tops[line_page] + _MARGIN + line_no * _LINE_HEIGHT)[:, None] + np.zeros((1, per_line))
    words = np.column_stack([x0[keep], y0[keep] + 2.0, x1[keep], y0[keep] + _LINE_HEIGHT - 2.0])

    boxes = np.concatenate([frames, images, words])
    kinds = np.concatenate([np.full(pages, PAGE), np.full(pages, IMAGE), np.full(len(words), TEXT)])
    return boxes, kinds.astype(np.uint8)


def whiteboard(n: int = 1_000_000, seed: int = 0, clusters: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """Sticky notes of log-normal size in a few hundred clusters, plus rare huge frames."""
    rng = np.random.default_rng(seed)
    extent = 400_000.0
    centres = rng.uniform(0, extent, (clusters, 2))
    spread = rng.lognormal(7.4, 0.6, clusters)  # cluster radius ~ 1600 units
    n_frames = max(1, n // 10_000)
    n_notes = n - n_frames
    owner = rng.integers(0, clusters, n_notes)
    xy = centres[owner] + rng.normal(0, 1, (n_notes, 2)) * spread[owner, None]
    wh = np.clip(rng.lognormal(4.2, 0.5, (n_notes, 2)), 8, 2000)
    notes = np.column_stack([xy, xy + wh])
    frame_xy = rng.uniform(0, extent, (n_frames, 2))
    frame_wh = rng.uniform(5_000, 60_000, (n_frames, 2))
    frames = np.column_stack([frame_xy, frame_xy + frame_wh])
    boxes = np.concatenate([notes, frames])
    kinds = np.concatenate([np.full(n_notes, NOTE), np.full(n_frames, FRAME)])
    return boxes, kinds.astype(np.uint8)


def uniform(n: int = 1_000_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Boxes of 1..50 units spread uniformly, ~1000 per 1920x1080 viewport at n = 1M."""
    rng = np.random.default_rng(seed)
    extent = float(np.sqrt(n * 1920 * 1080 / 1000))
    xy = rng.uniform(0, extent, (n, 2))
    wh = rng.uniform(1, 50, (n, 2))
    return np.column_stack([xy, xy + wh]), np.full(n, BOX, np.uint8)


def panning_path(
    boxes: np.ndarray,
    steps: int = 2000,
    seed: int = 0,
    screen: tuple[float, float] = (1920.0, 1080.0),
    step: float = 60.0,
) -> np.ndarray:
    """Viewports (steps, 4) of a person reading: mostly small vertical scrolls, some jumps and zooms.

    Per step: 84% a scroll of ``step`` screen pixels (mostly down), 6% sideways, 5% a jump
    to a random item, 5% a zoom between 0.25x and 2x around the centre.
    """
    rng = np.random.default_rng(seed)
    centres = (boxes[:, :2] + boxes[:, 2:]) * 0.5
    cx, cy = centres[rng.integers(len(boxes))] if len(boxes) else (0.0, 0.0)
    zoom = 1.0
    out = np.empty((steps, 4))
    for i in range(steps):
        r = rng.random()
        if r < 0.84:
            cy += step / zoom * (1 if rng.random() < 0.85 else -1)
        elif r < 0.90:
            cx += step / zoom * rng.choice((-1, 1))
        elif r < 0.95:
            cx, cy = centres[rng.integers(len(boxes))]
        else:
            zoom = float(np.clip(zoom * 2 ** rng.uniform(-1, 1), 0.25, 2.0))
        half_w, half_h = screen[0] / zoom / 2, screen[1] / zoom / 2
        out[i] = cx - half_w, cy - half_h, cx + half_w, cy + half_h
    return out

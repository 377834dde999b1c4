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
    "clustered_board",
    "long_document",
    "panning_path",
    "pdf_pages",
    "sparse",
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


def clustered_board(n: int = 200_000, seed: int = 0, clusters: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """Notes in ``clusters`` round Gaussian clusters over a 1e6-unit square: spreads (standard
    deviations) log-uniform in 500..20,000 units, sides log-normal around 55 units, and one note
    in a thousand 200x larger. A busy board zoomed out: dense cores, sparse tails, empty between."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(0, 1_000_000.0, (clusters, 2))
    spread = np.exp(rng.uniform(np.log(500.0), np.log(20_000.0), clusters))
    owner = rng.integers(0, clusters, n)
    xy = centres[owner] + rng.normal(0, 1, (n, 2)) * spread[owner, None]
    wh = rng.lognormal(np.log(55.0), 0.4, (n, 2))
    wh[rng.random(n) < 0.001] *= 200
    return np.column_stack([xy, xy + wh]), np.full(n, NOTE, np.uint8)


def uniform(n: int = 1_000_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Boxes of 1..50 units spread uniformly, ~1000 per 1920x1080 viewport at n = 1M."""
    rng = np.random.default_rng(seed)
    extent = float(np.sqrt(n * 1920 * 1080 / 1000))
    xy = rng.uniform(0, extent, (n, 2))
    wh = rng.uniform(1, 50, (n, 2))
    return np.column_stack([xy, xy + wh]), np.full(n, BOX, np.uint8)


def pdf_pages(pages: int = 2500, columns: int = 1, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Pages as a PDF's extracted layout: boxes nested page > block > line > word, plus figures.

    Each letter page holds its frame, a running header and footer, and one or two text
    columns filled top to bottom with headings, paragraphs (every line's box and its words'
    boxes, a ragged last line, some first lines indented) and figures with a caption below;
    fonts of 9-12 pt, word widths log-normal. About 400 boxes a page (2500 pages: ~1M
    items). Pages are laid out ``columns`` to a row, left to right and then down:
    ``columns=1`` is one long column, ``columns=25`` a wall of pages side by side. Every
    block, line and word lies inside its page and every word inside its line, so node boxes
    over them overlap as a real document's do.
    """
    rng = np.random.default_rng(seed)
    columns = max(1, int(columns))
    page_x = (np.arange(pages) % columns) * (PAGE_WIDTH + PAGE_GAP)
    page_y = (np.arange(pages) // columns) * (PAGE_HEIGHT + PAGE_GAP)
    frames = np.column_stack([page_x, page_y, page_x + PAGE_WIDTH, page_y + PAGE_HEIGHT])
    # Lines as (x0, y0, width available, font size, block number), block by block.
    line_xs, line_ys, line_rooms, line_fonts, line_blocks = [], [], [], [], []
    blocks_so_far, figures = 0, []
    for p in range(pages):
        px, py = page_x[p], page_y[p]
        margin = float(rng.uniform(54, 80))
        body = float(rng.choice((9.5, 10.0, 10.5, 11.0, 12.0)))
        cols = 2 if rng.random() < 0.35 else 1
        gutter = 18.0
        col_w = (PAGE_WIDTH - 2 * margin - (cols - 1) * gutter) / cols
        # running header and footer: one short line each
        for y, room in ((py + margin * 0.5, col_w * 0.6), (py + PAGE_HEIGHT - margin * 0.6, 40.0)):
            line_xs.append(px + margin)
            line_ys.append(y)
            line_rooms.append(room)
            line_fonts.append(8.0)
            line_blocks.append(blocks_so_far)
            blocks_so_far += 1
        bottom = py + PAGE_HEIGHT - margin - 12.0
        if rng.random() < 0.15:  # a chapter's last page: the text stops part way down
            bottom = py + margin + float(rng.uniform(0.2, 0.8)) * (bottom - py - margin)
        for c in range(cols):
            x = px + margin + c * (col_w + gutter)
            y = py + margin + 10.0
            while True:
                r = rng.random()
                if r < 0.1:  # a heading: one or two lines in a bigger font
                    font, count, last = body * float(rng.uniform(1.2, 1.6)), int(rng.integers(1, 3)), 0.6
                elif r < 0.3:  # a figure with a caption
                    height = float(rng.uniform(0.15, 0.4)) * (bottom - py)
                    width = col_w * float(rng.uniform(0.6, 1.0))
                    if y + height + 3 * body * 1.2 > bottom:
                        break
                    fx = x + (col_w - width) / 2
                    figures.append((fx, y, fx + width, y + height))
                    y += height + 6.0
                    font, count, last = body * 0.9, int(rng.integers(1, 4)), float(rng.uniform(0.3, 1.0))
                else:  # a paragraph
                    font, count, last = body, int(rng.integers(3, 13)), float(rng.uniform(0.15, 0.95))
                leading = font * 1.2
                count = min(count, int((bottom - y) // leading))
                if count < 1:
                    break
                indent = font * 1.5 if r >= 0.3 and rng.random() < 0.5 else 0.0
                for k in range(count):
                    first = indent if k == 0 else 0.0
                    line_xs.append(x + first)
                    line_ys.append(y + k * leading)
                    line_rooms.append((col_w - first) * (last if k == count - 1 else 1.0))
                    line_fonts.append(font)
                    line_blocks.append(blocks_so_far)
                blocks_so_far += 1
                y += count * leading + body * float(rng.uniform(0.5, 1.2))
    line_x, line_y, line_room = np.array(line_xs), np.array(line_ys), np.array(line_rooms)
    line_font, line_block = np.array(line_fonts), np.array(line_blocks, np.int64)

    # Words: each line filled left to right with log-normal widths while they fit its room; a
    # justified line ends at its room, so its last word is stretched to the edge.
    per_line = 24
    widths = np.clip(rng.lognormal(1.55, 0.5, (line_x.size, per_line)), 1, 14) * line_font[:, None] * 0.5
    space = line_font[:, None] * 0.28
    ends = np.cumsum(widths + space, axis=1) - space
    fits = ends <= line_room[:, None]
    fits[:, 0] = True  # a line holds at least one word, cut to its room
    ends = np.minimum(ends, line_room[:, None])
    starts = np.maximum(ends - widths, 0.0)
    x0 = line_x[:, None] + starts
    x1 = line_x[:, None] + ends
    top = line_y[:, None] + np.zeros((1, per_line))
    asc = (line_y + line_font * 0.05)[:, None] + np.zeros((1, per_line))
    words = np.column_stack([x0[fits], asc[fits], x1[fits], (top + line_font[:, None])[fits]])
    last = per_line - 1 - np.argmax(fits[:, ::-1], axis=1)
    lines = np.column_stack(
        [line_x + starts[:, 0], line_y, line_x + ends[np.arange(line_x.size), last], line_y + line_font * 1.2]
    )
    # Blocks: the union of their lines (lines are grouped by block, blocks by page).
    block_first = np.flatnonzero(np.r_[True, line_block[1:] != line_block[:-1]])
    blocks = np.column_stack(
        [
            np.minimum.reduceat(lines[:, 0], block_first),
            np.minimum.reduceat(lines[:, 1], block_first),
            np.maximum.reduceat(lines[:, 2], block_first),
            np.maximum.reduceat(lines[:, 3], block_first),
        ]
    )
    images = np.array(figures, np.float64).reshape(-1, 4)
    boxes = np.concatenate([frames, blocks, lines, words, images])
    kinds = np.concatenate(
        [
            np.full(pages, PAGE),
            np.full(len(blocks) + len(lines), BOX),
            np.full(len(words), TEXT),
            np.full(len(images), IMAGE),
        ]
    )
    return boxes, kinds.astype(np.uint8)


def sparse(n: int = 1_000_000, seed: int = 0, per_view: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Small markers (4..40 units) spread uniformly, ``per_view`` per 1920x1080 viewport on average.

    The case where an answer is a handful of ids and a query's fixed cost is all there is.
    """
    rng = np.random.default_rng(seed)
    extent = float(np.sqrt(n * 1920 * 1080 / per_view))
    xy = rng.uniform(0, extent, (n, 2))
    wh = rng.uniform(4, 40, (n, 2))
    return np.column_stack([xy, xy + wh]), np.full(n, NOTE, np.uint8)


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

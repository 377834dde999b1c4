"""The benchmark scenes have the shapes they claim: nested PDF-like pages, a sparse field."""

import numpy as np

from spatial import QuadTree, scenes


def inside(inner: np.ndarray, outer: np.ndarray) -> np.ndarray:
    """(len(inner), len(outer)) mask: inner box i lies within outer box j (closed)."""
    return (
        (outer[None, :, 0] <= inner[:, None, 0])
        & (outer[None, :, 1] <= inner[:, None, 1])
        & (inner[:, None, 2] <= outer[None, :, 2])
        & (inner[:, None, 3] <= outer[None, :, 3])
    )


def test_pdf_pages_nest_page_block_line_word():
    boxes, kinds = scenes.pdf_pages(pages=6, columns=3, seed=1)
    page, text, image, box = (scenes.KINDS.index(k) for k in ("page", "text", "image", "box"))
    frames, words, figures, frames_of_text = (boxes[kinds == k] for k in (page, text, image, box))
    assert len(frames) == 6 and len(figures) and set(np.unique(kinds)) == {page, text, image, box}
    assert 300 <= len(boxes) / 6 <= 500, "about 400 boxes a page"
    # blocks and lines (kind "box"): a line is one line of text tall (fonts up to 12 pt x 1.6,
    # leading 1.2), a block is the union of its lines, so tall boxes hold whole lines
    height = frames_of_text[:, 3] - frames_of_text[:, 1]
    lines, tall = frames_of_text[height <= 12 * 1.6 * 1.2], frames_of_text[height > 12 * 1.6 * 1.2]
    assert len(lines) > 10 * 6 and len(tall) >= 3 * 6 and len(words) > 5 * len(lines)
    assert inside(words, lines).any(axis=1).all(), "a word outside every line"
    assert inside(lines, frames_of_text).sum(axis=1).min() >= 1
    assert (inside(lines, tall).sum(axis=0) >= 2).all(), "a tall block holding fewer than two lines"
    assert inside(frames_of_text, frames).sum(axis=1).tolist() == [1] * len(frames_of_text), (
        "a block off its page"
    )
    assert inside(figures, frames).any(axis=1).all() and inside(words, frames).any(axis=1).all()
    # pages 3 to a row, side by side, then down
    assert np.unique(frames[:, 0]).size == 3 and np.unique(frames[:, 1]).size == 2


def test_pdf_pages_are_seeded():
    a, _ = scenes.pdf_pages(pages=4, columns=1, seed=7)
    b, _ = scenes.pdf_pages(pages=4, columns=1, seed=7)
    c, _ = scenes.pdf_pages(pages=4, columns=1, seed=8)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert (a[:, :2] <= a[:, 2:]).all() and np.isfinite(a).all()


def test_sparse_viewports_hold_a_handful():
    boxes, _ = scenes.sparse(50_000, seed=3)
    tree = QuadTree.bulk_load(boxes)
    rng = np.random.default_rng(4)
    corner = rng.uniform(boxes[:, :2].min(axis=0), boxes[:, 2:].max(axis=0), (300, 2))
    hits = [len(tree.query((x, y, x + 1920, y + 1080))) for x, y in corner]
    assert np.mean(hits) <= 4 and np.percentile(hits, 99) <= 10


def test_the_clustered_board_is_round_clusters_with_rare_large_notes():
    boxes, kinds = scenes.clustered_board(n=50_000, seed=3, clusters=20)
    again, _ = scenes.clustered_board(n=50_000, seed=3, clusters=20)
    assert np.array_equal(boxes, again) and (kinds == scenes.KINDS.index("note")).all()
    sides = np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])
    assert 40 < np.median(sides) < 90 and 0.0005 < (sides > 2000).mean() < 0.002
    # clustered: the occupied 10,000-unit cells are a small share of the board's
    cells = np.unique((boxes[:, :2] // 10_000).astype(np.int64), axis=0)
    assert len(cells) < 0.1 * 100 * 100

"""Accuracy against cost: the knobs of vantage's viewport index, each measured against the exact answer.

Run from the repository root (seeded; rewrites the report and its plots)::

    python -m benchmarks.tradeoffs                                       # ~1M items per scene (minutes)
    python -m benchmarks.tradeoffs --scale 0.05 --out /tmp/tradeoffs.md  # a quick look (under a minute)
    python -m benchmarks.tradeoffs --trades aggregates --update          # one trade, into the report

Six trades, each a table and a plot (written next to the report as tradeoffs-<trade>.png):

  exact     tree.query(rect, exact=False): the touched leaves' items untested, a superset
  lod       tree.query(rect, min_size=min_px/scale): items under min_px on screen left out
  float32   QuadTree(coords="float32"): boxes in half the memory, rounded outward (false hits)
  shape     leaf_size, max_depth and x_order: build time, memory, query time
  overscan  the panning simulator's margin: requests/s, bytes/s and blank screen
  aggregates  zoomed out: every item, drop-only LOD, or the overview's aggregates against the
            exact picture, entries per screen and server time, from page level to the whole
            scene; Overview.build against QuadTree.bulk_load (and docs/zoom-out.png)

The exact answer is brute force over the float64 boxes with closed intervals (touching counts).
Query times are medians of calls interleaved step by step in a seeded shuffled order, so a
noisy neighbour slows every variant alike and the ratios hold.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from spatial import Rect, scenes
from spatial.quadtree import QuadTree

from .machine import cpu_model, versions
from .spatial_bench import source_hash

TRADES = ("exact", "lod", "float32", "shape", "overscan", "aggregates")
SCENE_KEYS = ("doc", "whiteboard", "uniform")

BYTES_PER_ITEM = 100  # ~ one item as JSON: id, four coordinates, a kind
LINK_BITS_PER_S = 100e6  # to put bytes next to microseconds: a 100 Mbit/s link
WARMUP = 5  # untimed calls first: numba loads its cache (and compiles for float32 boxes) on the first
CHECKS = 30  # viewports per tree-shape variant compared with brute force before timing

SCREEN = (1920, 1080)  # pixels of the rasterised pictures (level of detail)
LOD_MIN_PX = (0.0, 0.5, 1.0, 2.0, 3.0, 4.0)
LOD_ZOOM = {"doc": 0.03, "whiteboard": 0.02, "uniform": 0.04}  # screen pixels per canvas unit
LOD_VIEWS = 16  # zoomed-out viewports per scene, centred on random items
LOD_REPEAT = 5  # timed passes over them
LOD_BUDGET = 0.05  # the recommendation's bound on pixels that change (share of the drawn pixels)
Z_ORDER = ("page", "frame", "image", "note", "box", "text")  # kinds painted bottom to top

MAGNITUDES = (1e2, 1e4, 1e6, 1e8, 1e10, 1e12, 1e15)
MAG_SIDE = 1e4  # the boxes' square, translated to each magnitude
MAG_BOX = (1.0, 20.0)  # box sides, units
MAG_QUERY = (400.0, 225.0)  # query window, units
MAG_QUERIES = 300

LEAF_SIZES = (8, 16, 32, 64, 128)
DEPTHS = (8, 16, 31)
DEFAULT_SHAPE = (32, 31, True)  # QuadTree's defaults: leaf_size, max_depth, x_order

OVERSCANS = (0.0, 0.1, 0.25, 0.5, 1.0)
SIM_PAGES, SIM_USERS, SIM_SECONDS = 200, 4, 4.0
BYTES_SLACK = 0.10  # the recommended margin may cost this much more bytes/s than none ...
BLANK_SLACK = 0.005  # ... and show blank in this many more frames than the best such margin


# -- scenes and shared helpers -------------------------------------------------------------


@dataclass
class Scene:
    key: str
    title: str
    boxes: np.ndarray  # (n, 4) float64
    kinds: np.ndarray  # (n,) uint8 into scenes.KINDS
    cols: tuple[np.ndarray, ...]  # contiguous x0, y0, x1, y1: brute force streams them
    views: list[Rect]  # the panning path
    tree: QuadTree  # default options


def load_scene(key: str, scale: float, seed: int, steps: int) -> Scene:
    if key == "doc":
        pages = max(1, round(2000 * scale))
        boxes, kinds = scenes.long_document(pages=pages, seed=seed)
        title = f"long document ({pages:,} pages)"
    else:
        n = max(1000, round(1_000_000 * scale))
        maker = scenes.whiteboard if key == "whiteboard" else scenes.uniform
        boxes, kinds = maker(n=n, seed=seed)
        title = key
    views = [as_rect(r) for r in scenes.panning_path(boxes, steps, seed)]
    return Scene(key, title, boxes, kinds, columns(boxes), views, QuadTree.bulk_load(boxes))


def columns(boxes: np.ndarray) -> tuple[np.ndarray, ...]:
    return tuple(np.ascontiguousarray(boxes[:, i]) for i in range(4))


def as_rect(r: Sequence[float]) -> Rect:
    return float(r[0]), float(r[1]), float(r[2]), float(r[3])


def brute(cols: tuple[np.ndarray, ...], r: Rect) -> np.ndarray:
    """The exact answer: every box intersecting or touching ``r`` (closed intervals)."""
    x0, y0, x1, y1 = cols
    return np.flatnonzero((x0 <= r[2]) & (x1 >= r[0]) & (y0 <= r[3]) & (y1 >= r[1]))


def compare(truth: np.ndarray, got: np.ndarray, mark: np.ndarray) -> tuple[int, int]:
    """(misses, false hits) of ``got`` against ``truth``; ``mark`` is an all-False scratch mask."""
    mark[got] = True
    found = int(np.count_nonzero(mark[truth]))
    mark[got] = False
    return truth.size - found, got.size - found


def same(got: np.ndarray, truth: np.ndarray) -> bool:
    return got.size == truth.size and np.array_equal(np.sort(got), truth)


def interleaved(calls: Sequence[Callable[[int], object]], steps: int, seed: int) -> np.ndarray:
    """Nanoseconds (calls, steps): at step i every call runs once, in a seeded shuffled order.

    A call that runs right after a heavy one finds the caches cold; shuffling spreads that over
    all of them. gc is off so a collection never lands inside one call.
    """
    ns = np.zeros((len(calls), steps), np.int64)
    rng = np.random.default_rng(seed)
    gc.collect()
    gc.disable()
    try:
        for i in range(steps):
            for k in rng.permutation(len(calls)):
                t0 = time.perf_counter_ns()
                calls[k](i)
                ns[k, i] = time.perf_counter_ns() - t0
    finally:
        gc.enable()
    return ns


def querying(tree: QuadTree, views: Sequence[Rect], **options: Any) -> Callable[[int], object]:
    """A timed call: step i queries ``views[i % len(views)]``."""
    return lambda i: tree.query(views[i % len(views)], **options)


def p50_us(ns: np.ndarray) -> float:
    return float(np.median(ns)) / 1e3


def md_table(header: Sequence[str], rows: Sequence[Sequence[str]], align: str) -> list[str]:
    """Markdown table; ``align`` has one ``l`` or ``r`` per column."""
    rule = ["---:" if a == "r" else "---" for a in align]
    return ["| " + " | ".join(header) + " |", "|" + "|".join(rule) + "|"] + [
        "| " + " | ".join(r) + " |" for r in rows
    ]


def pct(share: float, digits: int = 1) -> str:
    return f"{100 * share:.{digits}f}%"


def kb(nbytes: float) -> str:
    return f"{nbytes / 1e3:,.1f}"


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig: Any, path: Path) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    pyplot().close(fig)


SCENE_COLOURS = {"doc": "tab:blue", "whiteboard": "tab:orange", "uniform": "tab:green"}


# -- 1. exact vs candidates ----------------------------------------------------------------


@dataclass
class ExactRow:
    scene: Scene
    hits: float  # mean items per viewport, exact
    candidates: float  # mean items per viewport, exact=False
    precision: float  # all true hits / all candidates over the path
    precision_p50: float  # median of the per-viewport precision
    exact_us: float
    candidates_us: float


def trade_exact(scene: Scene, seed: int) -> ExactRow:
    """Exact queries against leaf candidates over the scene's panning path."""
    tree, views = scene.tree, scene.views
    for r in views[:WARMUP]:
        tree.query(r)
        tree.query(r, exact=False)
    ns = interleaved([querying(tree, views), querying(tree, views, exact=False)], len(views), seed)
    mark = np.zeros(len(scene.boxes), np.bool_)
    hits, cands = np.zeros(len(views)), np.zeros(len(views))
    for i, r in enumerate(views):
        truth = brute(scene.cols, r)
        if not same(tree.query(r), truth):
            raise SystemExit(f"FATAL: {scene.title}: exact query {i} disagrees with brute force")
        got = tree.query(r, exact=False)
        misses, _ = compare(truth, got, mark)
        if misses:
            raise SystemExit(f"FATAL: {scene.title}: candidates of query {i} miss {misses} true hits")
        hits[i], cands[i] = truth.size, got.size
    per_view = np.divide(hits, cands, out=np.ones_like(hits), where=cands > 0)
    precision = float(hits.sum() / cands.sum()) if cands.sum() else 1.0
    return ExactRow(
        scene,
        float(hits.mean()),
        float(cands.mean()),
        precision,
        float(np.median(per_view)),
        p50_us(ns[0]),
        p50_us(ns[1]),
    )


def transfer_us(items: float) -> float:
    return items * BYTES_PER_ITEM * 8 / LINK_BITS_PER_S * 1e6


def section_exact(rows: list[ExactRow], plot: str) -> list[str]:
    table = md_table(
        [
            "scene",
            "viewports",
            "items exact",
            "items candidates",
            "precision (all)",
            "precision p50",
            "query p50 us exact",
            "query p50 us candidates",
            "candidates / exact time",
            "KB exact",
            "KB candidates",
            "extra transfer us at 100 Mbit/s",
        ],
        [
            [
                r.scene.title,
                f"{len(r.scene.views):,}",
                f"{r.hits:,.0f}",
                f"{r.candidates:,.0f}",
                pct(r.precision),
                pct(r.precision_p50),
                f"{r.exact_us:,.1f}",
                f"{r.candidates_us:,.1f}",
                f"{r.candidates_us / r.exact_us:.2f}x",
                kb(r.hits * BYTES_PER_ITEM),
                kb(r.candidates * BYTES_PER_ITEM),
                f"{transfer_us(r.candidates - r.hits):,.0f}",
            ]
            for r in rows
        ],
        "lrrrrrrrrrrr",
    )
    return [
        "## 1. Exact answers vs leaf candidates",
        "",
        "`tree.query(rect, exact=False)` skips the per-item test in the leaves the viewport touches "
        "and returns their whole ranges: a superset, never a miss (checked on every viewport). "
        "Each scene's panning path is queried both ways, exact and candidate calls interleaved step "
        "by step. Items are means per viewport; precision is the share of returned items that truly "
        "intersect (over all returned items, and the median viewport's). Bytes assume "
        f"~{BYTES_PER_ITEM} bytes of JSON per item (an id, four coordinates, a kind); the last "
        "column is what the extra items take on a 100 Mbit/s link, to set against the query time saved.",
        "",
        *table,
        "",
        f"![exact vs candidates]({plot})",
        "",
    ]


def plot_exact(rows: list[ExactRow], path: Path) -> None:
    plt = pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2))
    for r in rows:
        c = SCENE_COLOURS[r.scene.key]
        xs = [100.0, 100 * r.precision]
        sent = [r.hits * BYTES_PER_ITEM / 1e3, r.candidates * BYTES_PER_ITEM / 1e3]
        for ax, ys in ((left, (r.exact_us, r.candidates_us)), (right, sent)):
            ax.plot(xs, ys, "-", color=c, label=r.scene.title)
            ax.plot(xs[0], ys[0], "o", color=c)
            ax.plot(xs[1], ys[1], "x", color=c, markersize=9)
    left.set_ylabel("query p50 (us)")
    right.set_ylabel(f"KB sent per viewport (~{BYTES_PER_ITEM} B per item)")
    for ax in (left, right):
        ax.set_xlabel("precision: share of returned items that intersect (%)")
        ax.set_yscale("log")
        ax.invert_xaxis()
        ax.grid(alpha=0.3)
        ax.legend(title="o exact, x candidates", fontsize=8)
    fig.suptitle("Exact answers vs leaf candidates: cost against precision")
    save(fig, path)


# -- 2. level of detail --------------------------------------------------------------------


@dataclass
class LodRow:
    scene: Scene
    min_px: float
    min_units: float
    items: float  # median per viewport
    kept: float  # median share of the exact answer's items
    query_us: float
    screen_error: float  # median share of the screen's pixels that differ from the exact picture
    drawn_error: float  # ... of the pixels drawn in either picture
    coverage_error: float  # ... of the screen where "covered or not" differs


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


def lod_views(scene: Scene, zoom: float, seed: int) -> list[Rect]:
    """Zoomed-out viewports of SCREEN pixels at ``zoom``, centred on random items."""
    rng = np.random.default_rng(seed)
    half_w, half_h = SCREEN[0] / zoom / 2, SCREEN[1] / zoom / 2
    picks = rng.integers(len(scene.boxes), size=LOD_VIEWS)
    centres = (scene.boxes[picks, :2] + scene.boxes[picks, 2:]) / 2
    return [(cx - half_w, cy - half_h, cx + half_w, cy + half_h) for cx, cy in centres.tolist()]


def trade_lod(scene: Scene, seed: int) -> list[LodRow]:
    tree, zoom = scene.tree, LOD_ZOOM[scene.key]
    views = lod_views(scene, zoom, seed)
    sizes = [px / zoom for px in LOD_MIN_PX]
    for r in views[:WARMUP]:
        for s in sizes:
            tree.query(r, min_size=s)
    ns = interleaved([querying(tree, views, min_size=s) for s in sizes], LOD_VIEWS * LOD_REPEAT, seed)
    box_size = np.maximum(scene.boxes[:, 2] - scene.boxes[:, 0], scene.boxes[:, 3] - scene.boxes[:, 1])
    stats = np.zeros((len(sizes), len(views), 5))  # items, kept, screen, drawn, coverage errors
    for v, view in enumerate(views):
        truth = brute(scene.cols, view)
        exact = None
        for k, s in enumerate(sizes):
            got = tree.query(view, min_size=s)
            if not same(got, truth[box_size[truth] >= s]):
                raise SystemExit(f"FATAL: {scene.title}: min_size={s:g} query disagrees with brute force")
            picture = render(scene.boxes[got], scene.kinds[got], view, zoom)
            if exact is None:  # min_px 0 comes first: the exact picture
                exact = picture
            differ = picture != exact
            drawn = np.count_nonzero((picture > 0) | (exact > 0))
            stats[k, v] = (
                got.size,
                got.size / max(truth.size, 1),
                differ.mean(),
                np.count_nonzero(differ) / max(drawn, 1),
                ((picture > 0) != (exact > 0)).mean(),
            )
    med = np.median(stats, axis=1)
    return [
        LodRow(scene, px, s, *med[k, :2], p50_us(ns[k]), *med[k, 2:])
        for k, (px, s) in enumerate(zip(LOD_MIN_PX, sizes, strict=True))
    ]


def section_lod(rows: list[LodRow], plot: str) -> list[str]:
    zooms = ", ".join(
        f"{t} {LOD_ZOOM[k]:g} px/unit" for k, t in {r.scene.key: r.scene.title for r in rows}.items()
    )
    table = md_table(
        [
            "scene",
            "min_px",
            "min size (units)",
            "items",
            "share of exact items",
            "KB sent",
            "query p50 us",
            "pixels differ (screen)",
            "pixels differ (drawn)",
            "coverage differs (screen)",
        ],
        [
            [
                r.scene.title,
                f"{r.min_px:g}",
                f"{r.min_units:,.1f}",
                f"{r.items:,.0f}",
                pct(r.kept),
                kb(r.items * BYTES_PER_ITEM),
                f"{r.query_us:,.1f}",
                pct(r.screen_error, 2),
                pct(r.drawn_error, 2),
                pct(r.coverage_error, 2),
            ]
            for r in rows
        ],
        "lrrrrrrrrr",
    )
    return [
        "## 2. Level of detail",
        "",
        "`tree.query(rect, min_size=min_px / scale)` leaves out items whose larger side is under "
        f"`min_px` screen pixels. Each scene is viewed zoomed out on a {SCREEN[0]}x{SCREEN[1]} screen "
        f"({zooms}), where most words, notes or boxes are a pixel or less, at {LOD_VIEWS} viewports "
        "centred on random items. Every answer is checked against brute force with the same size "
        "filter. The picture: each item fills the pixels its box touches (at least one), kinds "
        "painted bottom to top (page, frame, image, note, box, text), each pixel showing the topmost "
        "kind; the error is the share of pixels whose kind differs from the exact picture's, over "
        "the whole screen and over the pixels either picture draws (the fairer figure for the "
        "document, whose page column fills a sliver of a zoomed-out screen). *Coverage* counts only "
        "covered/blank changes, as a single-colour renderer would see them. All figures are medians "
        f"over the viewports; query times over {LOD_REPEAT} interleaved passes; bytes at "
        f"~{BYTES_PER_ITEM} B per item.",
        "",
        "The size filter is not free on the server: a node lying inside the viewport is copied "
        "whole only when its smallest item passes the size test; otherwise its items are tested "
        "one by one. So an LOD query can take longer than the exact one, which copies whole "
        "ranges, while returning far fewer items: what it saves is bytes on the wire and the "
        "client's work.",
        "",
        *table,
        "",
        f"![level of detail]({plot})",
        "",
    ]


def plot_lod(rows: list[LodRow], path: Path) -> None:
    plt = pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.4))
    for key in dict.fromkeys(r.scene.key for r in rows):
        mine = [r for r in rows if r.scene.key == key]
        c, label = SCENE_COLOURS[key], mine[0].scene.title
        sent = [r.items * BYTES_PER_ITEM / 1e3 for r in mine]
        left.plot(sent, [100 * r.drawn_error for r in mine], "o-", color=c, label=label)
        for r, x in zip(mine, sent, strict=True):
            left.annotate(
                f"{r.min_px:g}",
                (x, 100 * r.drawn_error),
                textcoords="offset points",
                xytext=(4, 4),
                fontsize=7,
                color=c,
            )
        right.plot([r.min_px for r in mine], [r.query_us for r in mine], "o-", color=c, label=label)
    left.set_xscale("log")
    left.set_xlabel("KB sent per viewport (log; labels: min_px; empty answers off the axis)")
    left.set_ylabel("pixels differing from the exact picture\n(% of the pixels either picture draws)")
    left.set_title("picture error against bytes sent")
    right.set_yscale("log")
    right.set_xlabel("min_px (screen pixels)")
    right.set_ylabel("query p50 (us, log)")
    right.set_title("query time")
    for ax in (left, right):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"Level of detail on zoomed-out {SCREEN[0]}x{SCREEN[1]} viewports")
    save(fig, path)


# -- 3. float64 vs float32 coordinates -----------------------------------------------------


@dataclass
class CoordRow:
    magnitude: float
    step32: float  # float32 spacing at the magnitude
    bytes64: float  # per item: tree.nbytes + boxes
    bytes32: float
    us64: float
    us32: float
    hits: float  # true hits per query
    misses64: int
    misses32: int  # total over the queries: must be 0
    false32: float  # per query
    plain_misses: float  # per query, float32 rounded to nearest
    plain_missing_queries: int  # queries with at least one miss
    plain_false: float


def float32_tree(boxes: np.ndarray) -> tuple[QuadTree, bool]:
    """``QuadTree(coords="float32")``, or a float64 tree (and False) where the option is missing."""
    try:
        return QuadTree.bulk_load(boxes, coords="float32"), True
    except TypeError:
        return QuadTree.bulk_load(boxes), False


def magnitude_scene(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Boxes of 1..20 units over a 1e4-unit square, and query windows in it, both at offset 0."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, MAG_SIDE, (n, 2))
    boxes = np.column_stack([xy, xy + rng.uniform(*MAG_BOX, (n, 2))])
    corner = rng.uniform(0, MAG_SIDE - np.array(MAG_QUERY), (MAG_QUERIES, 2))
    return boxes, np.column_stack([corner, corner + np.array(MAG_QUERY)])


def tree_bytes(tree: QuadTree) -> int:
    return tree.nbytes + tree._boxes.nbytes


def trade_float32(
    base: np.ndarray, windows: np.ndarray, magnitude: float, seed: int
) -> tuple[CoordRow, bool]:
    boxes = base + magnitude  # the float64 truth is these rounded sums
    views = [as_rect(r) for r in windows + magnitude]
    tree64 = QuadTree.bulk_load(boxes)
    tree32, native = float32_tree(boxes)
    for r in views[:WARMUP]:
        tree64.query(r)
        tree32.query(r)
    ns = interleaved([querying(tree64, views), querying(tree32, views)], len(views), seed)
    cols, plain = columns(boxes), columns(boxes.astype(np.float32).astype(np.float64))
    mark = np.zeros(len(boxes), np.bool_)
    counts = np.zeros((len(views), 7))  # hits, misses64, misses32, false32, plain misses, plain false
    for i, r in enumerate(views):
        truth = brute(cols, r)
        m64, f64 = compare(truth, tree64.query(r), mark)
        m32, f32 = compare(truth, tree32.query(r), mark)
        pm, pf = compare(truth, brute(plain, r), mark)
        counts[i] = truth.size, m64 + f64, m32, f32, pm, pf, pm > 0
    if counts[:, 1].any():
        raise SystemExit(f"FATAL: the float64 tree disagrees with brute force at magnitude {magnitude:g}")
    n = len(boxes)
    mean = counts.mean(axis=0)
    row = CoordRow(
        magnitude,
        float(np.spacing(np.float32(magnitude))),
        tree_bytes(tree64) / n,
        tree_bytes(tree32) / n,
        p50_us(ns[0]),
        p50_us(ns[1]),
        mean[0],
        int(counts[:, 1].sum()),
        int(counts[:, 2].sum()),
        mean[3],
        mean[4],
        int(counts[:, 6].sum()),
        mean[5],
    )
    return row, native


@dataclass
class SceneCoordRow:
    scene: Scene
    reach: float  # largest |coordinate|
    exact32: float  # share of the coordinates float32 holds exactly (no rounding at all)
    bytes64: float
    bytes32: float
    us64: float
    us32: float
    hits: float  # per viewport
    misses: int  # over the path: must be 0
    false_hits: float  # per viewport


def trade_float32_scene(scene: Scene, seed: int) -> SceneCoordRow:
    """The same comparison on a real scene's panning path: what float32 costs there."""
    tree64, views = scene.tree, scene.views
    tree32, _ = float32_tree(scene.boxes)
    for r in views[:WARMUP]:
        tree64.query(r)
        tree32.query(r)
    ns = interleaved([querying(tree64, views), querying(tree32, views)], len(views), seed)
    mark = np.zeros(len(scene.boxes), np.bool_)
    counts = np.array(
        [(t.size, *compare(t, tree32.query(r), mark)) for r in views for t in [brute(scene.cols, r)]]
    )
    n = len(scene.boxes)
    exact32 = float(np.mean(scene.boxes.astype(np.float32) == scene.boxes))
    return SceneCoordRow(
        scene,
        float(np.abs(scene.boxes).max()),
        exact32,
        tree_bytes(tree64) / n,
        tree_bytes(tree32) / n,
        p50_us(ns[0]),
        p50_us(ns[1]),
        float(counts[:, 0].mean()),
        int(counts[:, 1].sum()),
        float(counts[:, 2].mean()),
    )


def section_float32(
    rows: list[CoordRow], scene_rows: list[SceneCoordRow], n: int, native: bool, plot: str
) -> list[str]:
    table = md_table(
        [
            "magnitude",
            "float32 step",
            "B/item float64",
            "B/item float32",
            "query p50 us float64",
            "query p50 us float32",
            "true hits / query",
            "float32 misses (all queries)",
            "float32 false hits / query",
            "plain float32 misses / query",
            "plain float32 queries missing",
            "plain float32 false hits / query",
        ],
        [
            [
                f"{r.magnitude:.0e}",
                f"{r.step32:.3g}",
                f"{r.bytes64:.1f}",
                f"{r.bytes32:.1f}",
                f"{r.us64:,.1f}",
                f"{r.us32:,.1f}",
                f"{r.hits:,.0f}",
                f"{r.misses32:,}",
                f"{r.false32:,.2f}",
                f"{r.plain_misses:,.2f}",
                f"{r.plain_missing_queries}/{MAG_QUERIES}",
                f"{r.plain_false:,.2f}",
            ]
            for r in rows
        ],
        "lrrrrrrrrrrr",
    )
    first_miss = next((r for r in rows if r.plain_misses > 0), None)
    contrast = (
        f"Plain float32 (each coordinate rounded to nearest, then brute force) first misses at "
        f"**{first_miss.magnitude:.0e}** ({first_miss.plain_missing_queries} of {MAG_QUERIES} queries "
        f"miss, {first_miss.plain_misses:.2f} items per query), where the float32 step is "
        f"{first_miss.step32:.3g} units."
        if first_miss
        else "Plain float32 (rounded to nearest) missed nothing at these magnitudes on these queries."
    )
    onset = next((r for r in rows if r.false32 >= 0.01 * max(r.hits, 1)), None)
    if onset:
        contrast += (
            f" Rounded outward, float32 never missed; its false hits pass 1% of the true hits at "
            f"**{onset.magnitude:.0e}** ({onset.false32:,.2f} per query, float32 step {onset.step32:.3g} "
            f"units against boxes of {MAG_BOX[0]:g}..{MAG_BOX[1]:g})."
        )
    collapsed = next((r for r in rows if r.step32 > MAG_SIDE), None)
    if collapsed:
        contrast += (
            f" From {collapsed.magnitude:.0e} the step outgrows the whole {MAG_SIDE:.0e}-unit square: "
            "the boxes collapse onto a few float32 values and every query returns nearly every item."
        )
    status = (
        ""
        if native
        else '**`QuadTree(coords="float32")` is not available in this build: the float32 columns were '
        "measured with a float64 tree and only show the harness working.**\n\n"
    )
    return [
        "## 3. Coordinate storage: float64 vs float32",
        "",
        status + f'`QuadTree(coords="float32")` stores the built boxes as float32, each side rounded '
        "outward to the next float32, so a box only grows and a query never misses; node boxes "
        f"stay float64. The scene: {n:,} boxes of {MAG_BOX[0]:g}..{MAG_BOX[1]:g} units over a "
        f"{MAG_SIDE:.0e}-unit square, translated to each magnitude; {MAG_QUERIES} query windows of "
        f"{MAG_QUERY[0]:g}x{MAG_QUERY[1]:g} units inside it, both trees queried interleaved. Truth is brute "
        "force on the float64 boxes. Memory is `tree.nbytes` + the stored boxes (ids, 8 B/item, "
        "left out: the same for both). A false hit is a returned item whose float64 box does not "
        "touch the query (its rounded box does); *float32 step* is the float32 spacing at the "
        "magnitude, the width of the rounding.",
        "",
        *table,
        "",
        contrast,
        "",
        *scene_table(scene_rows),
        f"![float64 vs float32]({plot})",
        "",
    ]


def scene_table(rows: list[SceneCoordRow]) -> list[str]:
    if not rows:
        return []
    return [
        "The same comparison on the three scenes, over their panning paths (float64 tree against "
        "float32 tree, interleaved; every viewport checked against brute force):",
        "",
        *md_table(
            [
                "scene",
                "largest coordinate",
                "float32 step there",
                "coordinates exact in float32",
                "B/item float64",
                "B/item float32",
                "query p50 us float64",
                "query p50 us float32",
                "true hits / viewport",
                "float32 misses (all)",
                "float32 false hits / viewport",
                "false hits / true hits",
            ],
            [
                [
                    r.scene.title,
                    f"{r.reach:.3g}",
                    f"{np.spacing(np.float32(r.reach)):.3g}",
                    pct(r.exact32),
                    f"{r.bytes64:.1f}",
                    f"{r.bytes32:.1f}",
                    f"{r.us64:,.1f}",
                    f"{r.us32:,.1f}",
                    f"{r.hits:,.0f}",
                    f"{r.misses:,}",
                    f"{r.false_hits:,.2f}",
                    pct(r.false_hits / max(r.hits, 1), 3),
                ]
                for r in rows
            ],
            "lrrrrrrrrrrr",
        ),
        "",
    ]


def plot_float32(rows: list[CoordRow], path: Path) -> None:
    plt = pyplot()
    fig, (acc, mem, speed) = plt.subplots(1, 3, figsize=(14, 4.2))
    mags = [r.magnitude for r in rows]
    acc.plot(mags, [r.false32 for r in rows], "o-", color="tab:blue", label="float32 outward: false hits")
    acc.plot(mags, [r.plain_misses for r in rows], "x--", color="tab:red", label="plain float32: misses")
    acc.plot(mags, [r.plain_false for r in rows], "+:", color="tab:red", label="plain float32: false hits")
    acc.plot(
        mags,
        [r.misses32 / MAG_QUERIES for r in rows],
        "s",
        color="tab:blue",
        markerfacecolor="none",
        label="float32 outward: misses",
    )
    acc.set_yscale("symlog", linthresh=0.01)
    acc.set_ylabel("items per query (symlog)")
    acc.set_title("accuracy against brute force in float64")
    mem.plot(mags, [r.bytes64 for r in rows], "o-", color="tab:gray", label="float64")
    mem.plot(mags, [r.bytes32 for r in rows], "o-", color="tab:blue", label="float32")
    mem.set_ylim(bottom=0)
    mem.set_ylabel("bytes per item (index + boxes)")
    mem.set_title("memory")
    speed.plot(mags, [r.us64 for r in rows], "o-", color="tab:gray", label="float64")
    speed.plot(mags, [r.us32 for r in rows], "o-", color="tab:blue", label="float32")
    speed.set_yscale("log")
    speed.set_ylabel("query p50 (us, log)")
    speed.set_title("query time")
    for ax in (acc, mem, speed):
        ax.set_xscale("log")
        ax.set_xlabel("coordinate magnitude (units)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("Coordinate storage: float64 vs float32 rounded outward")
    save(fig, path)


# -- 4. tree shape -------------------------------------------------------------------------


@dataclass
class ShapeRow:
    scene: Scene
    leaf_size: int
    max_depth: int
    x_order: bool
    build_ms: float
    depth: int
    nodes: int
    bytes_item: float
    query_us: float = float("nan")


def shapes() -> list[tuple[int, int, bool]]:
    """Two cross-sections through the default: leaf sizes at full depth, depth caps at leaf 32,
    each with x-order on and off."""
    leaf, depth, _ = DEFAULT_SHAPE
    grid = [(s, depth, x) for s in LEAF_SIZES for x in (True, False)]
    return grid + [(leaf, d, x) for d in DEPTHS if d != depth for x in (True, False)]


def timed_build(boxes: np.ndarray, repeat: int, **options: Any) -> tuple[QuadTree, float]:
    """The tree and the median build time (ms) over ``repeat`` builds."""
    times, tree = [], None
    for _ in range(repeat):
        tree = None  # free the previous build before timing the next
        t0 = time.perf_counter()
        tree = QuadTree.bulk_load(boxes, **options)
        times.append(time.perf_counter() - t0)
    return tree, float(np.median(times)) * 1e3


def build_shape(scene: Scene, shape: tuple[int, int, bool], repeat: int) -> tuple[QuadTree, ShapeRow]:
    leaf, depth, x_order = shape
    tree, ms = timed_build(scene.boxes, repeat, leaf_size=leaf, max_depth=depth, x_order=x_order)
    picks = np.linspace(0, len(scene.views) - 1, min(CHECKS, len(scene.views))).astype(int)
    for i in picks:
        if not same(tree.query(scene.views[i]), brute(scene.cols, scene.views[i])):
            raise SystemExit(
                f"FATAL: {scene.title}: leaf_size={leaf} max_depth={depth} x_order={x_order} is wrong"
            )
    row = ShapeRow(
        scene, leaf, depth, x_order, ms, tree.depth, tree._nodes.shape[0], tree.nbytes / len(scene.boxes)
    )
    return tree, row


def time_shapes(scene: Scene, trees: list[QuadTree], rows: list[ShapeRow], seed: int) -> None:
    for tree in trees:
        for r in scene.views[:WARMUP]:
            tree.query(r)
    ns = interleaved([querying(t, scene.views) for t in trees], len(scene.views), seed)
    for row, times in zip(rows, ns, strict=True):
        row.query_us = p50_us(times)


def section_shape(rows: list[ShapeRow], repeat: int, plot: str) -> list[str]:
    lines = [
        "## 4. Tree shape",
        "",
        "Two cross-sections through the default (leaf_size 32, max_depth 31, x-order on): every "
        "leaf size at full depth, and every depth cap at leaf size 32, each with the x-order (leaves "
        "sorted by x0, so a leaf scan stops at the viewport's right edge) on and off. Build time is "
        f"the median of {repeat} builds; memory is `tree.nbytes` (nodes and tombstones; the "
        "reordered boxes and ids, 40 B/item, are the same for every shape); query p50 is over each "
        "scene's panning path, all variants interleaved step by step, every variant first checked "
        f"against brute force on {CHECKS} viewports. *depth* is the levels the tree reached. There is "
        "no loose factor to tune: a node keeps the exact union of its items' boxes, not a padded "
        "cell, so nothing trades looseness against precision here.",
        "",
    ]
    for key in dict.fromkeys(r.scene.key for r in rows):
        mine = [r for r in rows if r.scene.key == key]
        base = next(r for r in mine if (r.leaf_size, r.max_depth, r.x_order) == DEFAULT_SHAPE)
        lines += [
            f"### {mine[0].scene.title}: {len(mine[0].scene.boxes):,} items, "
            f"{len(mine[0].scene.views):,} viewports",
            "",
        ]
        lines += md_table(
            [
                "leaf_size",
                "max_depth",
                "x-order",
                "build ms",
                "depth",
                "nodes",
                "index B/item",
                "query p50 us",
                "p50 / default",
            ],
            [
                [
                    str(r.leaf_size),
                    str(r.max_depth),
                    "on" if r.x_order else "off",
                    f"{r.build_ms:,.0f}",
                    str(r.depth),
                    f"{r.nodes:,}",
                    f"{r.bytes_item:.1f}",
                    f"{r.query_us:,.1f}",
                    f"{r.query_us / base.query_us:.2f}x",
                ]
                for r in mine
            ],
            "rrlrrrrrr",
        )
        lines.append("")
    return [*lines, f"![tree shape]({plot})", ""]


def plot_shape(rows: list[ShapeRow], path: Path) -> None:
    plt = pyplot()
    keys = list(dict.fromkeys(r.scene.key for r in rows))
    fig, axes = plt.subplots(1, len(keys), figsize=(5 * len(keys), 4.4), squeeze=False)
    markers = dict(zip(LEAF_SIZES, "v<o>^", strict=True))
    colours = {8: "tab:red", 16: "tab:purple", 31: "tab:blue"}
    for ax, key in zip(axes[0], keys, strict=True):
        mine = [r for r in rows if r.scene.key == key]
        for r in mine:
            ax.plot(
                r.bytes_item,
                r.query_us,
                markers[r.leaf_size],
                color=colours.get(r.max_depth, "k"),
                markerfacecolor=colours.get(r.max_depth, "k") if r.x_order else "none",
                markersize=8,
            )
            ax.annotate(
                f"{r.leaf_size}",
                (r.bytes_item, r.query_us),
                textcoords="offset points",
                xytext=(5, -3),
                fontsize=7,
            )
        ax.set_xlabel("index bytes per item (tree.nbytes / n)")
        ax.set_ylabel("query p50 (us)")
        ax.set_title(mine[0].scene.title)
        ax.grid(alpha=0.3)
    handles = [
        plt.Line2D([], [], color=c, marker="o", linestyle="", label=f"max_depth {d}")
        for d, c in colours.items()
    ]
    handles += [
        plt.Line2D([], [], color="k", marker=m, linestyle="", markerfacecolor="none", label=f"leaf {s}")
        for s, m in markers.items()
    ]
    handles += [
        plt.Line2D([], [], color="k", marker="o", linestyle="", label="filled: x-order on"),
        plt.Line2D(
            [], [], color="k", marker="o", linestyle="", markerfacecolor="none", label="hollow: x-order off"
        ),
    ]
    axes[0][0].legend(handles=handles, fontsize=7, loc="upper right")
    fig.suptitle("Tree shape: query time against index memory (all exact)")
    save(fig, path)


# -- 5. overscan margin (the panning simulator) --------------------------------------------


def simulate_command(out: str, seconds: float, seed: int) -> list[str]:
    return [
        sys.executable,
        "-m",
        "app.simulate",
        "--spawn",
        "--pages",
        str(SIM_PAGES),
        "--seconds",
        f"{seconds:g}",
        "--users",
        str(SIM_USERS),
        "--modes",
        "stream",
        "--lod",
        "on",
        "--overscan",
        ",".join(f"{m:g}" for m in OVERSCANS),
        "--seed",
        str(seed),
        "--out",
        out,
    ]


def trade_overscan(seconds: float, seed: int) -> tuple[list[dict[str, Any]], str]:
    """The simulator's per-mode summaries (see app/simulate/report.py) and the command line run."""
    with tempfile.TemporaryDirectory(prefix="tradeoffs-sim-") as tmp:
        cmd = simulate_command(tmp, seconds, seed)
        shown = shlex.join([".venv/bin/python", *cmd[1:-1], "<tmp>"])
        done = subprocess.run(cmd, capture_output=True, text=True, cwd=Path(__file__).resolve().parent.parent)
        if done.returncode:
            raise SystemExit(f"FATAL: the simulator failed ({done.returncode}):\n{done.stderr[-3000:]}")
        result = json.loads((Path(tmp) / "result.json").read_text())
    return sorted(result["modes"], key=lambda m: m["overscan"]), shown


def section_overscan(modes: list[dict[str, Any]], command: str, seconds: float, plot: str) -> list[str]:
    def ms(value: float | None) -> str:
        return "–" if value is None else f"{value:,.1f}"

    table = md_table(
        [
            "overscan",
            "requests/s",
            "bytes/request",
            "KB/s",
            "latency p50 ms",
            "latency p95 ms",
            "entered/request",
            "blank mean",
            "blank p95",
            "frames with blank",
            "errors",
        ],
        [
            [
                f"{m['overscan']:g}",
                f"{m['requests_per_s']:,.1f}",
                f"{m['bytes_per_request'] or 0:,.0f}",
                kb(m["bytes_per_s"]),
                ms(m["latency_ms"]["p50"]),
                ms(m["latency_ms"]["p95"]),
                f"{m['entered_mean'] or 0:,.1f}",
                pct(m["blank_mean"] or 0, 2),
                pct(m["blank_p95"] or 0),
                pct(m["frames_with_blank"] or 0),
                str(m["errors"]),
            ]
            for m in modes
        ],
        "rrrrrrrrrrr",
    )
    return [
        "## 5. Overscan margin",
        "",
        "The client asks for the screen grown by a margin on each side (a share of the screen) and asks "
        "again only when the screen nears the margin's edge; a bigger margin means fewer, larger "
        "requests and less blank screen while an answer is on its way. Measured end to end with the "
        f"panning simulator: a spawned server with a generated {SIM_PAGES}-page document, {SIM_USERS} "
        f"virtual users scrolling, flinging, zooming and jumping at 60 frames/s for {seconds:g} s per "
        "margin, over the WebSocket stream with level of detail on (min_px 1):",
        "",
        f"    {command}",
        "",
        "Blank is the share of the screen outside the last rect the client received, per frame; "
        "*frames with blank* is the share of frames showing any. What stays blank at large margins "
        "is the first frames before the first answer and jumps to a far item, which no margin "
        "covers. Bytes are the stream's actual JSON; the simulator's screen is 1280x800.",
        "",
        *table,
        "",
        f"![overscan margin]({plot})",
        "",
    ]


def plot_overscan(modes: list[dict[str, Any]], path: Path) -> None:
    plt = pyplot()
    fig, (req, traffic, blank) = plt.subplots(1, 3, figsize=(14, 4.2))
    margins = [m["overscan"] for m in modes]
    req.plot(margins, [m["requests_per_s"] for m in modes], "o-", color="tab:blue")
    req.set_ylabel("requests per second (all users)")
    req.set_title("requests")
    traffic.plot(margins, [m["bytes_per_s"] / 1e3 for m in modes], "o-", color="tab:green", label="KB/s")
    traffic.set_ylabel("KB per second (all users)")
    traffic.set_ylim(bottom=0)
    per_request = traffic.twinx()
    per_request.plot(
        margins,
        [(m["bytes_per_request"] or 0) / 1e3 for m in modes],
        "s--",
        color="tab:gray",
        label="KB per request",
    )
    per_request.set_ylabel("KB per request")
    per_request.set_ylim(bottom=0)
    traffic.legend(handles=traffic.lines + per_request.lines, fontsize=8)
    traffic.set_title("bytes")
    blank.plot(
        margins,
        [100 * (m["blank_mean"] or 0) for m in modes],
        "o-",
        color="tab:red",
        label="blank share of the screen (mean)",
    )
    blank.set_ylabel("blank share of the screen, mean over frames (%)")
    blank.set_ylim(bottom=0)
    frames = blank.twinx()
    frames.plot(
        margins,
        [100 * (m["frames_with_blank"] or 0) for m in modes],
        "s--",
        color="tab:orange",
        label="frames showing any blank",
    )
    frames.set_ylabel("frames showing any blank (%)")
    frames.set_ylim(bottom=0)
    blank.legend(handles=blank.lines + frames.lines, fontsize=8)
    blank.set_title("blank screen")
    for ax in (req, traffic, blank):
        ax.set_xlabel("overscan margin (share of the screen per side)")
        ax.grid(alpha=0.3)
    fig.suptitle("Overscan margin: requests and bytes against blank screen (stream, LOD on)")
    save(fig, path)


# -- 6. aggregates: what stands in for items too small to draw -----------------------------


AGG_MIN_PX = 1.0  # the level of detail compared: an item under a screen pixel is too small to draw
AGG_SCALE_STEP = 4  # screen scales 1, 1/4, 1/16, ... down to the one fitting the whole scene
AGG_VIEWS = 8  # full-HD viewports per scale, centred on random items (at the fit scale: one, all)
AGG_REPEAT = 5  # timed passes over them
AGG_GOAL = (0.01, 5000)  # the goal: at most 1% of the pixels differ, with at most 5,000 entries
AGG_ZOOM_OUT = "zoom-out.png"  # the README's picture: the long document at the fit scale and 1/64
AGG_CROP_PX = (80, 240)  # its panels: a crop of the screen (w, h pixels) around the document's column
PAGE_COLOURS = {  # static/app.js COLOURS: fill (stroke where a kind has no fill), and the canvas
    "page": "#ffffff",
    "text": "#5b6270",
    "image": "#8fb3d9",
    "note": "#ffd866",
    "frame": "#7a5cff",
    "box": "#5aa469",
}
PAGE_STROKE, CANVAS = "#b9bec8", "#e9ebee"
ANSWERS = ("a", "b", "c")  # every item; drop-only LOD; the band's items plus its aggregates


def service_budget() -> tuple[int, int]:
    """The service's default entries per full-HD screen (VANTAGE_LOD_BUDGET) and its default limit."""
    from app.config import Settings

    fields = Settings.model_fields
    return int(fields["lod_budget"].default), int(fields["default_limit"].default)


@dataclass
class AggRow:
    scene: Scene
    scale: float  # screen pixels per canvas unit
    fit: bool  # the scale fitting the whole scene on the screen (one viewport: all of it)
    natural: np.ndarray  # (views,) the band min_px asks for
    band: np.ndarray  # (views,) the band the budget chose
    entries: np.ndarray  # (3, views): items for (a) and (b), items + aggregates for (c)
    nbytes: np.ndarray  # (3, views)
    screen_error: np.ndarray  # (3, views): share of the screen's pixels differing from the exact picture
    drawn_error: np.ndarray  # (3, views): ... of the pixels either picture draws
    overdrawn: np.ndarray  # (3, views): share of the screen blank in the exact picture, painted here
    us: tuple[float, float, float]  # server p50 per answer


@dataclass
class BuildCost:
    scene: Scene
    tree_ms: float
    overview_ms: float
    tree_bytes: int  # held: tree.nbytes + its boxes + its ids
    overview_bytes: int  # held: every band's columns and tree (nbytes, boxes, ids), per-item links
    tree_peak: int  # tracemalloc peak while building
    overview_peak: int
    aggregates: int  # over all bands
    bands: int


@dataclass
class AggResult:
    rows: list[AggRow]
    builds: list[BuildCost]
    pictures: dict[str, Any]  # the zoom-out picture's panels, when the document was run
    seconds: float = 0.0
    rules: list[RuleRow] = field(default_factory=list)


@dataclass
class RuleRow:
    """One merge rule on one scene, over every scale: how close its answers draw."""

    scene: Scene
    rule: str
    aggregates: int  # built, over all bands
    build_ms: float
    worst_error: float  # the largest median share of screen pixels that differ, over the scales
    worst_scale: float
    mean_error: float  # the mean over the scales of the median
    max_entries: int


def trade_rules(scene: Scene, seed: int) -> list[RuleRow]:
    """Each merge rule's answers (c) against the exact picture, at every scale of the trade."""
    from spatial.overview import RULES, Overview

    budget, cap = service_budget()
    z = np.zeros(len(scene.boxes), np.int64)
    rows = []
    for rule in RULES:
        t0 = time.perf_counter()
        view = Overview.build(scene.boxes, scene.kinds, z, rule=rule)
        build_ms = (time.perf_counter() - t0) * 1e3
        answers = Answers(scene, view, min(cap, budget))
        errors, most = [], 0
        for scale, fit in agg_scales(scene.boxes):
            per_view = []
            for rect in agg_views(scene, scale, fit, seed):
                pics, entries, _, _, _ = answers.pictures(rect, scale)
                per_view.append(float((pics[2] != pics[0]).mean()))
                most = max(most, entries[2])
            errors.append((float(np.median(per_view)), scale))
        worst = max(errors)
        built = sum(len(b.count) for b in view._bands.values())
        mean = float(np.mean([e for e, _ in errors]))
        rows.append(RuleRow(scene, rule, built, build_ms, worst[0], worst[1], mean, most))
    return rows


def section_rules(rows: list[RuleRow]) -> list[str]:
    table = md_table(
        [
            "scene",
            "rule",
            "aggregates built",
            "build ms",
            "worst median error (scale)",
            "mean error",
            "most entries",
        ],
        [
            [
                r.scene.title,
                f"**{r.rule}**" if r.rule == "rectangles" else r.rule,
                f"{r.aggregates:,}",
                f"{r.build_ms:,.0f}",
                f"{pct(r.worst_error, 2)} (1/{1 / r.worst_scale:,.0f})",
                pct(r.mean_error, 2),
                f"{r.max_entries:,}",
            ]
            for r in rows
        ],
        "llrrrrr",
    )
    return [
        "",
        "### Which occupied cells make one aggregate",
        "",
        "The same answers (c), built by each merge rule of `Overview.build(rule=...)`: *cells* (each "
        "occupied cell), *rows* (runs of occupied cells in a row), *rectangles* (runs, and runs over "
        "the same columns in consecutive rows: the default) and *blobs* (runs joined wherever they "
        "overlap in consecutive rows). Error: the share of screen pixels that differ from the exact "
        "picture, the median over the viewports of a scale; the worst and the mean over the scales.",
        "",
        *table,
        "",
    ]


def tree_held(tree: QuadTree) -> int:
    return tree.nbytes + tree._boxes.nbytes + tree._ids.nbytes


def overview_held(view: Any) -> int:
    total = view._first.nbytes + view._agg.nbytes
    for band in view._bands.values():
        columns = (band.boxes, band.count, band.area, band.z, band.kind, band.parent)
        total += sum(a.nbytes for a in columns) + tree_held(band.tree)
    return total


def traced_peak(build: Callable[[], object]) -> int:
    import tracemalloc

    gc.collect()
    tracemalloc.start()
    try:
        build()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def build_overview(scene: Scene, repeat: int) -> tuple[Any, BuildCost]:
    """The scene's Overview (kinds as scenes.KINDS codes, z 0), and what it costs next to the tree."""
    from spatial.overview import Overview

    z = np.zeros(len(scene.boxes), np.int64)
    tree, tree_ms = timed_build(scene.boxes, repeat)
    times, view = [], None
    for _ in range(repeat):
        view = None
        t0 = time.perf_counter()
        view = Overview.build(scene.boxes, scene.kinds, z)
        times.append(time.perf_counter() - t0)
    cost = BuildCost(
        scene,
        tree_ms,
        float(np.median(times)) * 1e3,
        tree_held(tree),
        overview_held(view),
        traced_peak(lambda: QuadTree.bulk_load(scene.boxes)),
        traced_peak(lambda: Overview.build(scene.boxes, scene.kinds, z)),
        sum(len(b.count) for b in view._bands.values()),
        len(view._bands),
    )
    return view, cost


def extent(boxes: np.ndarray) -> Rect:
    return (
        float(boxes[:, 0].min()),
        float(boxes[:, 1].min()),
        float(boxes[:, 2].max()),
        float(boxes[:, 3].max()),
    )


def agg_scales(boxes: np.ndarray) -> list[tuple[float, bool]]:
    """Powers of 1/AGG_SCALE_STEP from 1 while the scene is bigger than the screen, then the scale
    that fits it whole (a power within 1.25x of that one is left out)."""
    x0, y0, x1, y1 = extent(boxes)
    fit = min(SCREEN[0] / max(x1 - x0, 1e-300), SCREEN[1] / max(y1 - y0, 1e-300))
    scales, s = [], 1.0
    while s > 1.25 * fit:
        scales.append((s, False))
        s /= AGG_SCALE_STEP
    return [*scales, (fit, True)]


def screen_at(centre: tuple[float, float], scale: float) -> Rect:
    half_w, half_h = SCREEN[0] / scale / 2, SCREEN[1] / scale / 2
    return centre[0] - half_w, centre[1] - half_h, centre[0] + half_w, centre[1] + half_h


def agg_views(scene: Scene, scale: float, fit: bool, seed: int) -> list[Rect]:
    if fit:
        x0, y0, x1, y1 = extent(scene.boxes)
        return [screen_at(((x0 + x1) / 2, (y0 + y1) / 2), scale)]
    rng = np.random.default_rng([seed, round(-np.log2(scale))])
    picks = rng.integers(len(scene.boxes), size=AGG_VIEWS)
    centres = (scene.boxes[picks, :2] + scene.boxes[picks, 2:]) / 2
    return [screen_at((cx, cy), scale) for cx, cy in centres.tolist()]


class Answers:
    """The three answers for one scene, as the service would compute them."""

    def __init__(self, scene: Scene, view: Any, most: float) -> None:
        from app.looks import agg_json

        self.scene, self.view, self.most, self.agg_json = scene, view, most, agg_json

    def band(self, rect: Rect, min_size: float) -> int:
        band = self.view.band_within(self.scene.tree, rect, min_size, self.most)
        if band is None:
            raise SystemExit(f"FATAL: {self.scene.title}: no band for {rect}")
        return band

    def timed(self, views: list[Rect], min_size: float) -> list[Callable[[int], object]]:
        tree, view = self.scene.tree, self.view

        def aggregates(i: int) -> object:
            r = views[i % len(views)]
            band = view.band_within(tree, r, min_size, self.most)
            return tree.query(r, min_size=view.threshold(band)), view.query(band, r)

        return [querying(tree, views), querying(tree, views, min_size=min_size), aggregates]

    def pictures(self, rect: Rect, scale: float) -> tuple[list[np.ndarray], list[int], list[int], int, int]:
        """(pictures a, b, c; entries; bytes; natural band; chosen band) for one viewport."""
        tree, view, boxes, kinds = self.scene.tree, self.view, self.scene.boxes, self.scene.kinds
        min_size = AGG_MIN_PX / scale
        every = tree.query(rect)
        dropped = tree.query(rect, min_size=min_size)
        band = self.band(rect, min_size)
        drawn = tree.query(rect, min_size=view.threshold(band))
        aggs = view.query(band, rect)
        agg_boxes, count, _, agg_kinds, _ = view.rows(band, aggs)
        if len(drawn) + int(count.sum()) < len(every):
            raise SystemExit(f"FATAL: {self.scene.title}: band {band} stands for fewer items than in {rect}")
        agg_bytes = sum(len(j) + 1 for j in self.agg_json(view, scenes.KINDS, band, aggs))
        c_boxes = np.concatenate([boxes[drawn], agg_boxes])
        c_kinds = np.concatenate([kinds[drawn], agg_kinds.astype(np.uint8)])
        pics = [
            render(boxes[every], kinds[every], rect, scale),
            render(boxes[dropped], kinds[dropped], rect, scale),
            render(c_boxes, c_kinds, rect, scale),
        ]
        if np.any((pics[0] > 0) & (pics[2] == 0)):
            raise SystemExit(f"FATAL: {self.scene.title}: aggregates leave drawn pixels blank in {rect}")
        entries = [len(every), len(dropped), len(drawn) + len(aggs)]
        nbytes = [
            len(every) * BYTES_PER_ITEM,
            len(dropped) * BYTES_PER_ITEM,
            len(drawn) * BYTES_PER_ITEM + agg_bytes,
        ]
        return pics, entries, nbytes, view.band(min_size), band


def trade_aggregates(scene: Scene, repeat: int, seed: int) -> tuple[list[AggRow], BuildCost, dict[str, Any]]:
    view, cost = build_overview(scene, repeat)
    budget, cap = service_budget()
    answers = Answers(scene, view, min(cap, budget))  # a full-HD screen: the whole budget
    rows, pictures = [], {}
    for scale, fit in agg_scales(scene.boxes):
        views = agg_views(scene, scale, fit, seed)
        min_size = AGG_MIN_PX / scale
        calls = answers.timed(views, min_size)
        for i in range(WARMUP):
            for call in calls:
                call(i)
        ns = interleaved(calls, max(len(views), 4) * AGG_REPEAT, seed)
        stats = np.zeros((5, 3, len(views)))  # entries, bytes, screen error, drawn error, overdrawn
        bands = np.zeros((2, len(views)), np.int64)
        for v, rect in enumerate(views):
            pics, entries, nbytes, natural, band = answers.pictures(rect, scale)
            exact = pics[0]
            for k, pic in enumerate(pics):
                differ = np.count_nonzero(pic != exact)
                drawn = np.count_nonzero((pic > 0) | (exact > 0))
                over = np.count_nonzero((exact == 0) & (pic > 0))
                stats[:, k, v] = (
                    entries[k],
                    nbytes[k],
                    differ / exact.size,
                    differ / max(drawn, 1),
                    over / exact.size,
                )
            bands[:, v] = natural, band
        rows.append(AggRow(scene, scale, fit, bands[0], bands[1], *stats, tuple(p50_us(t) for t in ns)))
    if scene.key == "doc":
        x0, y0, x1, y1 = extent(scene.boxes)
        middle = ((x0 + x1) / 2, (y0 + y1) / 2)
        fit = agg_scales(scene.boxes)[-1][0]
        for name, scale in (("fit", fit), ("1/64", 1 / 64)):
            if scale >= fit:
                pics, entries, _, _, band = answers.pictures(screen_at(middle, scale), scale)
                pictures[name] = (scale, pics, entries, band)
    del answers, view
    gc.collect()
    return rows, cost, pictures


def spread(values: np.ndarray) -> str:
    lo, hi = int(values.min()), int(values.max())
    return f"{lo}" if lo == hi else f"{lo}–{hi}"


def scale_name(scale: float, fit: bool) -> str:
    name = f"1/{1 / scale:,.0f}" if scale < 1 else f"{scale:g}"
    return f"{name} (fit)" if fit else name


def meets(row: AggRow) -> bool:
    return row.screen_error[2].max() <= AGG_GOAL[0] and row.entries[2].max() <= AGG_GOAL[1]


def triple(values: Sequence[str]) -> str:
    return " / ".join(values)


def section_aggregates(
    res: AggResult, command: str, repeat: int, plot: str, picture: str | None
) -> list[str]:
    budget, cap = service_budget()
    table = md_table(
        [
            "scene",
            "scale",
            "views",
            "band: LOD → chosen",
            "entries p50 a / b / c",
            "entries max a / b / c",
            "KB p50 a / b / c",
            "screen px differ p50 b / c",
            "screen px differ max b / c",
            "drawn px differ p50 b / c",
            "c: blank painted p50",
            "server p50 us a / b / c",
            "goal (c)",
        ],
        [
            [
                r.scene.title,
                scale_name(r.scale, r.fit),
                str(r.entries.shape[1]),
                f"{spread(r.natural)} → {spread(r.band)}",
                triple([f"{x:,.0f}" for x in np.median(r.entries, axis=1)]),
                triple([f"{x:,.0f}" for x in r.entries.max(axis=1)]),
                triple([kb(x) for x in np.median(r.nbytes, axis=1)]),
                triple([pct(x, 2) for x in np.median(r.screen_error[1:], axis=1)]),
                triple([pct(x, 2) for x in r.screen_error[1:].max(axis=1)]),
                triple([pct(x, 1) for x in np.median(r.drawn_error[1:], axis=1)]),
                pct(np.median(r.overdrawn[2]), 2),
                triple([f"{x:,.0f}" for x in r.us]),
                "yes" if meets(r) else "**no**",
            ]
            for r in res.rows
        ],
        "llrlrrrrrrrrl",
    )
    build = md_table(
        [
            "scene",
            "items",
            "QuadTree.bulk_load ms",
            "Overview.build ms",
            "build ratio",
            "tree MB held",
            "overview MB held",
            "held ratio",
            "tree MB peak",
            "overview MB peak",
            "peak ratio",
            "aggregates (bands)",
        ],
        [
            [
                b.scene.title,
                f"{len(b.scene.boxes):,}",
                f"{b.tree_ms:,.0f}",
                f"{b.overview_ms:,.0f}",
                f"{b.overview_ms / b.tree_ms:.1f}x",
                f"{b.tree_bytes / 1e6:,.1f}",
                f"{b.overview_bytes / 1e6:,.1f}",
                f"{b.overview_bytes / b.tree_bytes:.2f}x",
                f"{b.tree_peak / 1e6:,.1f}",
                f"{b.overview_peak / 1e6:,.1f}",
                f"{b.overview_peak / b.tree_peak:.2f}x",
                f"{b.aggregates:,} ({b.bands})",
            ]
            for b in res.builds
        ],
        "lrrrrrrrrrrr",
    )
    lines = [
        "## 6. Aggregates: what stands in for items too small to draw",
        "",
        f"Measured by `{command}` in {res.seconds / 60:.1f} min (spatial sources sha256 {source_hash()}).",
        "",
        "Zoomed out, a client drawing items of at least `min_px` screen pixels can be answered three "
        f"ways, each compared with the exact picture of every item in the viewport ({SCREEN[0]}x{SCREEN[1]}, "
        "drawn as in trade 2: each box fills every pixel it touches, the topmost kind wins): "
        "**(a)** no level of detail, every item; **(b)** drop-only, `tree.query(rect, min_size=1 / scale)` "
        "(min_px 1); **(c)** aggregates, as the service answers at min_px 1: the items of at least "
        "`2**band` units plus the band's aggregates, `band = overview.band_within(tree, rect, 1 / scale, "
        f"most)` with `most = min({cap:,}, {budget:,})` entries (the default VANTAGE_LOD_BUDGET for a "
        "full-HD screen, within the default limit); each aggregate is drawn as a box of its kind (that "
        "of its largest element) and solid: the picture cannot show an aggregate's cover, which the "
        "page draws as the density of its box, so where an aggregate's members leave much of its box "
        "empty the solid box overstates them (*c: blank painted*: the share of the screen blank in "
        "the exact picture that (c) paints; the rest of its error is a wrong kind). Scales go from 1 (page level) down by 4x to the scale fitting the "
        f"whole scene on the screen; {AGG_VIEWS} viewports per scale centred on random items, one "
        "(the whole scene) at the fit scale. *band: LOD → chosen*: the band min_px 1 asks for and the "
        "one the budget settled on (a range over the viewports). Bytes: items at "
        f"~{BYTES_PER_ITEM} B each, aggregates as encoded by `app.looks.agg_json`. Server time is "
        f"the p50 of {AGG_REPEAT} interleaved passes per answer: (a) and (b) one tree query, (c) "
        "`band_within` plus the tree query and the band's query (not the JSON). *goal (c)*: every "
        f"viewport at that scale within {pct(AGG_GOAL[0], 0)} of the screen's pixels and "
        f"{AGG_GOAL[1]:,} entries.",
        "",
        *table,
        "",
        *aggregate_findings(res),
        "",
        f"Building the overview, against the tree on the same items (median of {repeat} "
        "builds; *held* is what stays: every band's columns and its tree's nodes, boxes and ids, plus "
        "two int64 per item linking it to its first aggregate; *peak* is tracemalloc's peak "
        "while building):"
        if res.builds
        else "",
        "",
        *build,
        "",
        f"![aggregates]({plot})",
        "",
    ]
    if picture:
        lines += [
            f"![the long document zoomed out, three ways]({picture})",
            "",
            "The long document at the fit scale and at 1/64, centred on its middle: a "
            f"{AGG_CROP_PX[0]}x{AGG_CROP_PX[1]}-pixel crop of the {SCREEN[0]}x{SCREEN[1]} screen around "
            "the page column, magnified, in the page's colours (a page's edge pixels in its stroke "
            "colour); the percentages are over the whole screen's picture.",
            "",
        ]
    return lines


def aggregate_findings(res: AggResult) -> list[str]:
    """A summary, then a line per scene: where the goal holds, and (c)'s worst scale next to
    (a) and (b) there, and drop-only's worst."""
    failing = [r for r in res.rows if not meets(r)]
    titles = list(dict.fromkeys(r.scene.title for r in res.rows))
    holds = [t for t in titles if all(meets(r) for r in res.rows if r.scene.title == t)]
    fails = {}
    for r in failing:
        fails.setdefault(r.scene.title, scale_name(r.scale, r.fit))
    summary = (
        f"The goal ({pct(AGG_GOAL[0], 0)} of the pixels, {AGG_GOAL[1]:,} entries per screen) holds with "
        f"aggregates at every scale on {' and '.join(holds) or 'no scene'}"
    )
    if fails:
        coarser = sum(bool(np.any(r.band > r.natural)) for r in failing)
        painted = np.median(
            [np.median(r.overdrawn[2]) / max(np.median(r.screen_error[2]), 1e-12) for r in failing]
        )
        summary += (
            f"; it fails on {', '.join(f'{t} from {s}' for t, s in fails.items())}. In "
            f"{'all' if coarser == len(failing) else f'{coarser} of'} those {len(failing)} rows the budget took a coarser band than min_px 1 asks "
            f"for, and blank canvas painted by solid aggregate boxes makes {pct(painted, 0)} of (c)'s "
            "differing pixels (median over the rows)"
        )
        over = [r for r in failing if r.entries[2].max() > AGG_GOAL[1]]
        summary += (
            f"; {len(over)} of them also pass {AGG_GOAL[1]:,} entries"
            if over
            else ": every one stays within the entries; what fails is the pixels, solid boxes "
            "overstating members that cover part of them"
        )
    out = [summary + ".", ""]
    for key in dict.fromkeys(r.scene.key for r in res.rows):
        mine = [r for r in res.rows if r.scene.key == key]
        good = [scale_name(r.scale, r.fit) for r in mine if meets(r)]
        bad = [scale_name(r.scale, r.fit) for r in mine if not meets(r)]
        held = (
            "at every scale"
            if not bad
            else "at no scale"
            if not good
            else f"at {', '.join(good)} but not at {', '.join(bad)}"
        )
        w = max(mine, key=lambda r: (r.screen_error[2].max(), r.entries[2].max()))
        most = max(mine, key=lambda r: r.entries[2].max())
        drop = max(mine, key=lambda r: (np.median(r.screen_error[1]), np.median(r.drawn_error[1])))
        med = np.median(w.entries, axis=1)
        out.append(
            f"- **{mine[0].scene.title}**: the goal holds {held}. Worst for aggregates: "
            f"{scale_name(w.scale, w.fit)}, where (c) differs in {pct(np.median(w.screen_error[2]), 2)} "
            f"of the screen (max {pct(w.screen_error[2].max(), 2)}; "
            f"{pct(np.median(w.drawn_error[2]))} of the drawn pixels; blank canvas painted by its "
            f"solid boxes: {pct(np.median(w.overdrawn[2]), 2)} of the screen) with {med[2]:,.0f} entries, "
            f"against (b)'s {pct(np.median(w.screen_error[1]), 2)} "
            f"({pct(np.median(w.drawn_error[1]))} of the drawn pixels) with {med[1]:,.0f} entries "
            f"and (a)'s {med[0]:,.0f} entries. The most entries (c) sends to one screen: "
            f"{most.entries[2].max():,.0f} (at {scale_name(most.scale, most.fit)}). Drop-only at its "
            f"worst ({scale_name(drop.scale, drop.fit)}): {pct(np.median(drop.screen_error[1]), 2)} of "
            f"the screen, {pct(np.median(drop.drawn_error[1]))} of the drawn pixels, with "
            f"{np.median(drop.entries[1]):,.0f} entries (aggregates there: "
            f"{pct(np.median(drop.screen_error[2]), 2)}, {pct(np.median(drop.drawn_error[2]))}, "
            f"{np.median(drop.entries[2]):,.0f})."
        )
    return out


def plot_aggregates(res: AggResult, path: Path) -> None:
    plt = pyplot()
    keys = list(dict.fromkeys(r.scene.key for r in res.rows))
    fig, axes = plt.subplots(2, len(keys), figsize=(5 * len(keys), 7.5), squeeze=False)
    styles = {
        "a": ("tab:gray", "every item (a)"),
        "b": ("tab:red", "drop < 1 px (b)"),
        "c": ("tab:blue", "aggregates (c)"),
    }
    for col, key in enumerate(keys):
        mine = [r for r in res.rows if r.scene.key == key]
        xs = [r.scale for r in mine]
        err, ent = axes[0][col], axes[1][col]
        for k, name in enumerate(ANSWERS):
            colour, label = styles[name]
            if k:
                err.plot(
                    xs, [100 * np.median(r.screen_error[k]) for r in mine], "o-", color=colour, label=label
                )
                err.plot(xs, [100 * r.screen_error[k].max() for r in mine], "v:", color=colour, alpha=0.6)
            ent.plot(xs, [np.median(r.entries[k]) for r in mine], "o-", color=colour, label=label)
            ent.plot(xs, [r.entries[k].max() for r in mine], "v:", color=colour, alpha=0.6)
        err.axhline(100 * AGG_GOAL[0], color="k", linewidth=0.8, linestyle="--", label="goal")
        ent.axhline(AGG_GOAL[1], color="k", linewidth=0.8, linestyle="--", label="goal")
        err.set_yscale("symlog", linthresh=0.01)
        err.set_ylim(bottom=0)
        err.set_ylabel("screen pixels differing (%, symlog)")
        err.set_title(mine[0].scene.title)
        ent.set_yscale("symlog", linthresh=1)
        ent.set_ylim(bottom=0)
        ent.set_ylabel("entries per screen (symlog)")
        for ax in (err, ent):
            ax.set_xscale("log")
            ax.invert_xaxis()
            ax.set_xlabel("screen scale (px per unit; the last: whole scene)")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, title="o median, v max", title_fontsize=7)
    fig.suptitle(f"Zoomed out at min_px {AGG_MIN_PX:g}: picture error and entries, three answers")
    save(fig, path)


def colour_picture(picture: np.ndarray) -> np.ndarray:
    """RGB of a kind picture in the page's colours: a page's pixels next to another kind's or
    the canvas in its stroke colour."""
    from matplotlib.colors import to_rgb

    table = np.array([to_rgb(CANVAS)] + [to_rgb(PAGE_COLOURS[k]) for k in Z_ORDER])
    rgb = table[picture]
    page = picture == Z_ORDER.index("page") + 1
    inner = page.copy()
    inner[1:, :] &= page[:-1, :]
    inner[:-1, :] &= page[1:, :]
    inner[:, 1:] &= page[:, :-1]
    inner[:, :-1] &= page[:, 1:]
    rgb[page & ~inner] = to_rgb(PAGE_STROKE)
    return rgb


def plot_zoom_out(pictures: dict[str, Any], path: Path) -> None:
    """Per scale, the three answers' pictures side by side: a crop of the screen around the
    document's column (AGG_CROP_PX screen pixels), magnified, in the page's colours."""
    plt = pyplot()
    cw, ch = AGG_CROP_PX
    cx, cy = SCREEN[0] // 2, SCREEN[1] // 2
    fig, axes = plt.subplots(1, 3 * len(pictures), figsize=(5.4 * len(pictures), 6.2), layout="constrained")
    names = ("(a) every item", f"(b) drop < {AGG_MIN_PX:g} px", "(c) aggregates")
    for trio, (name, (scale, pics, entries, band)) in zip(
        np.reshape(axes, (-1, 3)), pictures.items(), strict=True
    ):
        exact = pics[0]
        where = f"{'whole doc, ' if name == 'fit' else ''}scale 1/{1 / scale:,.0f}"
        for k, (ax, pic) in enumerate(zip(trio, pics, strict=True)):
            crop = pic[cy - ch // 2 : cy + ch // 2, cx - cw // 2 : cx + cw // 2]
            ax.imshow(colour_picture(crop), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            drawn = np.count_nonzero((pic > 0) | (exact > 0))
            differ = np.count_nonzero(pic != exact)
            ax.set_title(
                f"{where}\n{names[k]}\n{entries[k]:,} entr{'y' if entries[k] == 1 else 'ies'}"
                f"{f', band {band}' if k == 2 else ''}\n"
                f"differ: {pct(differ / max(drawn, 1))} of drawn,\n{pct(differ / exact.size, 2)} of all pixels",
                fontsize=9,
            )
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


# -- recommendations -----------------------------------------------------------------------


@dataclass
class Results:
    scenes: list[Scene]
    exact: list[ExactRow]
    lod: list[LodRow]
    coords: list[CoordRow]
    coords_scenes: list[SceneCoordRow]
    shape: list[ShapeRow]
    overscan: list[dict[str, Any]]


def advise_exact(r: ExactRow) -> str:
    saved = r.exact_us - r.candidates_us
    extra = transfer_us(r.candidates - r.hits)
    verdict = "candidates pay off" if r.precision >= 0.95 and saved > extra else "keep exact queries"
    return (
        f"**{verdict}**: candidates return {r.candidates / max(r.hits, 1):.2f}x the items (precision "
        f"{pct(r.precision)}) and take {r.candidates_us / r.exact_us:.2f}x the query time "
        f"({saved:+,.1f} us saved per viewport) while the extra "
        f"{kb((r.candidates - r.hits) * BYTES_PER_ITEM)} KB take ~{extra:,.0f} us at 100 Mbit/s."
    )


def advise_lod(rows: list[LodRow]) -> str:
    fine = [r for r in rows if r.min_px > 0 and r.drawn_error <= LOD_BUDGET]
    exact = rows[0]
    if not fine:
        r = rows[1]
        return (
            f"even min_px {r.min_px:g} changes {pct(r.drawn_error)} of the drawn pixels at "
            f"{LOD_ZOOM[r.scene.key]:g} px/unit: use LOD only further out, or accept the change."
        )
    r = max(fine, key=lambda row: row.min_px)
    one = next((x for x in rows if x.min_px == 1.0), None)
    also = (
        f"; min_px 1 would send {pct(one.kept)} of the items and change {pct(one.drawn_error)} of the "
        "drawn pixels"
        if one is not None and one is not r
        else ""
    )
    return (
        f"**min_px {r.min_px:g}** is the largest that changes at most {pct(LOD_BUDGET, 0)} of the drawn "
        f"pixels ({pct(r.drawn_error)}; {pct(r.screen_error, 2)} of the screen) while sending "
        f"{pct(r.kept)} of the items ({kb(exact.items * BYTES_PER_ITEM)} -> {kb(r.items * BYTES_PER_ITEM)} KB "
        f"per zoomed-out view; query {exact.query_us:,.0f} -> {r.query_us:,.0f} us){also}."
    )


def advise_coords(row: SceneCoordRow, sweep: list[CoordRow]) -> str:
    share = row.false_hits / max(row.hits, 1)
    verdict = "take float32" if share < 0.01 and row.misses == 0 else "keep float64"
    slower = row.us32 / row.us64
    return (
        f"**{verdict}**: on this scene (coordinates up to {row.reach:.2g}, float32 step "
        f"{np.spacing(np.float32(row.reach)):.3g}) float32 boxes cut memory from {row.bytes64:.1f} to "
        f"{row.bytes32:.1f} B/item ({pct(1 - row.bytes32 / row.bytes64, 0)} less) for {row.false_hits:,.2f} false "
        f"hits per viewport ({pct(share, 3)} of the hits), {row.misses} misses, and {slower:.2f}x the query "
        f"time.{headroom(sweep)}"
    )


def headroom(sweep: list[CoordRow]) -> str:
    cheap = [r for r in sweep if r.false32 < 0.01 * max(r.hits, 1)]
    if not cheap:
        return ""
    return (
        f" In the magnitude sweep false hits stay under 1% of the hits up to {cheap[-1].magnitude:.0e} "
        f"(float32 step {cheap[-1].step32:.3g} against boxes of {MAG_BOX[0]:g}..{MAG_BOX[1]:g} units): "
        "the bound to watch as a canvas grows."
    )


def advise_shape(rows: list[ShapeRow]) -> str:
    base = next(r for r in rows if (r.leaf_size, r.max_depth, r.x_order) == DEFAULT_SHAPE)
    best = min(rows, key=lambda r: r.query_us)
    no_x = next(r for r in rows if (r.leaf_size, r.max_depth) == DEFAULT_SHAPE[:2] and not r.x_order)
    name = f"leaf {best.leaf_size}, depth {best.max_depth}, x-order {'on' if best.x_order else 'off'}"
    ratio = best.query_us / base.query_us
    if best is base or ratio >= 0.9:
        gap = (
            "it is the fastest shape measured"
            if best is base
            else f"no shape is measurably faster (best: {name}, {ratio:.2f}x)"
            if ratio >= 0.97
            else f"the fastest shape ({name}) is only {1 - ratio:.0%} faster"
        )
        head = f"**keep the default** (leaf 32, depth 31, x-order on): {base.query_us:,.1f} us p50; {gap}"
    else:
        head = (
            f"**leaf {best.leaf_size}, depth {best.max_depth}, x-order {'on' if best.x_order else 'off'}** "
            f"answers in {best.query_us:,.1f} us p50 against the default's {base.query_us:,.1f} us "
            f"({best.query_us / base.query_us:.2f}x) at {best.bytes_item:.1f} vs {base.bytes_item:.1f} index B/item"
        )
    big = max((r for r in rows if r.max_depth == DEFAULT_SHAPE[1]), key=lambda r: r.leaf_size)
    capped = min(
        (r for r in rows if r.leaf_size == DEFAULT_SHAPE[0] and r.x_order), key=lambda r: r.max_depth
    )
    return (
        f"{head}. With the x-order off: {no_x.query_us / base.query_us:.2f}x the time; leaf "
        f"{big.leaf_size} saves {base.bytes_item - big.bytes_item:.1f} index B/item for "
        f"{big.query_us / base.query_us:.2f}x the time; a depth cap of {capped.max_depth}: "
        f"{capped.query_us / base.query_us:.2f}x."
    )


def pick_overscan(modes: list[dict[str, Any]]) -> dict[str, Any]:
    """The smallest margin within BLANK_SLACK of the fewest blank frames, among those whose bytes/s
    stay within BYTES_SLACK of no margin's: blank is what a person sees, bytes/s what it costs."""
    zero = modes[0]
    cheap = [m for m in modes if m["bytes_per_s"] <= (1 + BYTES_SLACK) * zero["bytes_per_s"]] or [zero]
    fewest = min(m["frames_with_blank"] or 0 for m in cheap)
    return next(m for m in cheap if (m["frames_with_blank"] or 0) <= fewest + BLANK_SLACK)


def advise_overscan(modes: list[dict[str, Any]]) -> str:
    m, zero = pick_overscan(modes), modes[0]
    return (
        f"**overscan {m['overscan']:g}**: the smallest margin within {pct(BLANK_SLACK)} of the fewest frames "
        f"with blank among margins costing at most {pct(BYTES_SLACK, 0)} more bytes/s than none: "
        f"{pct(m['frames_with_blank'] or 0)} of frames show blank (vs {pct(zero['frames_with_blank'] or 0)} with "
        f"no margin), {m['requests_per_s']:,.0f} requests/s instead of {zero['requests_per_s']:,.0f}, "
        f"{kb(m['bytes_per_s'])} KB/s instead of {kb(zero['bytes_per_s'])}, but {kb(m['bytes_per_request'] or 0)} "
        f"KB per request instead of {kb(zero['bytes_per_request'] or 0)} (measured on a long document)."
    )


def overscan_elsewhere(modes: list[dict[str, Any]]) -> str:
    zero, last = modes[0], modes[-1]
    area = (1 + 2 * last["overscan"]) ** 2
    return (
        f"On the document, bytes/s go from {kb(zero['bytes_per_s'])} KB/s at margin 0 to "
        f"{kb(last['bytes_per_s'])} at {last['overscan']:g} ({last['bytes_per_s'] / zero['bytes_per_s']:.2f}x), "
        f"far less than the {area:g}x area each request covers: the stream sends each item once, as it enters. "
        f"What grows is the burst: a jump or a zoom fetches the whole grown rect, (1 + 2 x margin)^2 "
        f"screens of items ({kb(zero['bytes_per_request'] or 0)} -> {kb(last['bytes_per_request'] or 0)} KB "
        "per request here). The simulator runs a long document only; on a whiteboard or a dense canvas, "
        "with more items per screen (trade 2's exact column), those bursts grow in proportion, so "
        "prefer the smaller of the margins that clear the blank there."
    )


def section_recommendations(res: Results) -> list[str]:
    names = {"doc": "Long document", "whiteboard": "Whiteboard", "uniform": "Uniform / dense"}
    lines = [
        "## Recommendations",
        "",
        "Rules of thumb from the tables above, per scene type; rerun this script after changing "
        "the index and they follow the new numbers.",
        "",
    ]
    for scene in res.scenes:
        lines.append(f"**{names[scene.key]}** ({scene.title}, {len(scene.boxes):,} items)")
        lines.append("")
        exact = next((r for r in res.exact if r.scene is scene), None)
        lod = [r for r in res.lod if r.scene is scene]
        shape = [r for r in res.shape if r.scene is scene]
        if exact:
            lines.append(f"- exact vs candidates: {advise_exact(exact)}")
        if lod:
            lines.append(f"- level of detail: {advise_lod(lod)}")
        coords = next((r for r in res.coords_scenes if r.scene is scene), None)
        if coords:
            lines.append(f"- coordinates: {advise_coords(coords, res.coords)}")
        if shape:
            lines.append(f"- tree shape: {advise_shape(shape)}")
        if res.overscan and scene.key == "doc":
            lines.append(f"- overscan: {advise_overscan(res.overscan)}")
        lines.append("")
    if res.overscan and any(s.key != "doc" for s in res.scenes):
        lines += [overscan_elsewhere(res.overscan), ""]
    return lines


# -- the report ----------------------------------------------------------------------------


def header(args: argparse.Namespace, argv: list[str], seconds: float, native32: bool | None) -> list[str]:
    u = platform.uname()
    pkgs = versions(("numpy", "numba", "matplotlib"))
    coords = {None: "not measured", True: "available", False: "NOT available (measured float64 for both)"}
    return [
        "# Vantage trade-offs: accuracy against cost",
        "",
        f"- command: `{shlex.join(['python', '-m', 'benchmarks.tradeoffs', *argv])}`",
        f"- machine: {u.system} {u.release} {u.machine}, CPU {cpu_model()}, nproc {len(os.sched_getaffinity(0))}",
        f"- python {platform.python_version()}; {pkgs}",
        f'- spatial sources sha256 {source_hash()}; `QuadTree(coords="float32")` {coords[native32]}',
        f"- seed {args.seed}, scale {args.scale:g} (1 = 2000 pages / 1M items per scene), "
        f"steps {args.steps}, build repeats {args.repeat}; run time {seconds / 60:.1f} min",
        "",
        "Every accuracy figure is against the exact answer: brute force over the float64 boxes, "
        "`x0 <= qx1 and x1 >= qx0 and y0 <= qy1 and y1 >= qy0` (touching counts). Times are medians "
        "(p50) of calls interleaved step by step in a seeded shuffled order, on a shared 2-core "
        "machine: read the ratios more than the absolute microseconds.",
        "",
    ]


def splice(old: list[str], new: list[str]) -> list[str]:
    """``old`` report lines with each of ``new``'s sections (from a '## ' heading to the next)
    in place of the old section of the same number, or before the recommendations if it had none."""

    def sections(lines: list[str]) -> tuple[list[str], list[list[str]]]:
        head: list[str] = []
        parts: list[list[str]] = []
        for line in lines:
            if line.startswith("## "):
                parts.append([])
            (parts[-1] if parts else head).append(line)
        return head, parts

    def key(part: list[str]) -> str:
        return part[0].split()[1] if part[0].split()[1][:1].isdigit() else part[0]

    head, parts = sections(old)
    for part in sections(new)[1]:
        at = next((i for i, p in enumerate(parts) if key(p) == key(part)), None)
        if at is None:
            at = next((i for i, p in enumerate(parts) if not key(p)[:1].isdigit()), len(parts))
            parts.insert(at, part)
        else:
            parts[at] = part
    return head + [line for part in parts for line in part]


def plot_path(out: Path, trade: str) -> Path:
    return out.parent / f"tradeoffs-{trade}.png"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.tradeoffs",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help="scene size factor: 1.0 is 2000 pages / 1M items per scene (default %(default)s); "
        "below 1 the simulator also runs shorter",
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="scenes, paths and shuffles (default %(default)s)"
    )
    parser.add_argument(
        "--steps",
        type=int,
        default=2000,
        help="panning path steps per scene (trades exact, float32, shape; default %(default)s)",
    )
    parser.add_argument("--repeat", type=int, default=3, help="builds per tree shape; the median is reported")
    parser.add_argument("--trades", default=",".join(TRADES), help=f"comma list of {', '.join(TRADES)}")
    parser.add_argument(
        "--scenes", default=",".join(SCENE_KEYS), help=f"comma list of {', '.join(SCENE_KEYS)}"
    )
    parser.add_argument(
        "--out",
        default="docs/TRADEOFFS.md",
        help="the report; plots go next to it as tradeoffs-<trade>.png (default %(default)s)",
    )
    parser.add_argument(
        "--update",
        action="store_true",
        help="replace only the sections of the trades run in the existing report, keeping its header, "
        "other sections and recommendations",
    )
    parser.add_argument(
        "--rules",
        action="store_true",
        help="with the aggregates trade, also compare the overview's merge rules (minutes more)",
    )
    args = parser.parse_args(argv)
    args.trade_list = [t.strip() for t in args.trades.split(",") if t.strip()]
    args.scene_list = [s.strip() for s in args.scenes.split(",") if s.strip()]
    if not set(args.trade_list) <= set(TRADES) or not set(args.scene_list) <= set(SCENE_KEYS):
        parser.error(f"--trades takes {', '.join(TRADES)}; --scenes takes {', '.join(SCENE_KEYS)}")
    if args.scale <= 0 or args.steps < 2 or args.repeat < 1:
        parser.error("--scale must be > 0, --steps >= 2, --repeat >= 1")
    return args


def main(argv: list[str] | None = None) -> None:
    started = time.perf_counter()
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    trades = args.trade_list
    needs_scenes = {"exact", "lod", "float32", "shape", "aggregates"} & set(trades)
    keys = args.scene_list if needs_scenes else []
    sim_seconds = SIM_SECONDS if args.scale >= 1 else max(1.0, round(SIM_SECONDS * args.scale * 5) / 5)
    n32 = max(1000, round(1_000_000 * args.scale))
    total = (
        len(keys)
        + len(keys) * ("exact" in trades)
        + len(keys) * ("lod" in trades)
        + (len(MAGNITUDES) + len(keys)) * ("float32" in trades)
        + len(keys) * len(shapes()) * ("shape" in trades)
        + ("overscan" in trades)
        + len(keys) * ("aggregates" in trades)
    )
    bar = tqdm(total=total, desc="tradeoffs", unit="task", file=sys.stderr)
    res = Results([], [], [], [], [], [], [])
    native32: bool | None = None
    body: list[str] = []
    sim_command = ""
    aggs = AggResult([], [], {})
    for key in keys:
        bar.set_description(f"scene {key}")
        res.scenes.append(load_scene(key, args.scale, args.seed, args.steps))
        bar.update()
    if "exact" in trades:
        for scene in res.scenes:
            bar.set_description(f"exact: {scene.key}")
            res.exact.append(trade_exact(scene, args.seed))
            bar.update()
    if "lod" in trades:
        for scene in res.scenes:
            bar.set_description(f"lod: {scene.key}")
            res.lod += trade_lod(scene, args.seed)
            bar.update()
    if "float32" in trades:
        base, windows = magnitude_scene(n32, args.seed)
        for magnitude in MAGNITUDES:
            bar.set_description(f"float32: {magnitude:.0e}")
            row, native32 = trade_float32(base, windows, magnitude, args.seed)
            res.coords.append(row)
            gc.collect()
            bar.update()
        for scene in res.scenes:
            bar.set_description(f"float32: {scene.key}")
            res.coords_scenes.append(trade_float32_scene(scene, args.seed))
            gc.collect()
            bar.update()
    if "shape" in trades:
        for scene in res.scenes:
            trees, rows = [], []
            for shape in shapes():
                bar.set_description(f"shape: {scene.key} leaf {shape[0]} depth {shape[1]}")
                tree, row = build_shape(scene, shape, args.repeat)
                trees.append(tree)
                rows.append(row)
                bar.update()
            bar.set_description(f"shape: {scene.key} timing")
            time_shapes(scene, trees, rows, args.seed)
            res.shape += rows
            del trees
            gc.collect()
    if "overscan" in trades:
        bar.set_description("overscan: simulator")
        res.overscan, sim_command = trade_overscan(sim_seconds, args.seed)
        bar.update()
    if "aggregates" in trades:
        t0 = time.perf_counter()
        for scene in res.scenes:
            bar.set_description(f"aggregates: {scene.key}")
            rows, cost, pictures = trade_aggregates(scene, args.repeat, args.seed)
            if args.rules:
                aggs.rules += trade_rules(scene, args.seed)
            aggs.rows += rows
            aggs.builds.append(cost)
            aggs.pictures.update(pictures)
            bar.update()
        aggs.seconds = time.perf_counter() - t0
    bar.close()

    def plot(trade: str, draw: Callable[[Any, Path], None], data: Any) -> str:
        path = plot_path(out, trade)
        draw(data, path)
        return path.name

    if res.exact:
        body += section_exact(res.exact, plot("exact", plot_exact, res.exact))
    if res.lod:
        body += section_lod(res.lod, plot("lod", plot_lod, res.lod))
    if res.coords:
        body += section_float32(
            res.coords, res.coords_scenes, n32, bool(native32), plot("float32", plot_float32, res.coords)
        )
    if res.shape:
        body += section_shape(res.shape, args.repeat, plot("shape", plot_shape, res.shape))
    if res.overscan:
        body += section_overscan(
            res.overscan, sim_command, sim_seconds, plot("overscan", plot_overscan, res.overscan)
        )
    if aggs.rows:
        picture = None
        if aggs.pictures:
            plot_zoom_out(aggs.pictures, out.parent / AGG_ZOOM_OUT)
            picture = AGG_ZOOM_OUT
        command = shlex.join(["python", "-m", "benchmarks.tradeoffs", *argv])
        body += section_aggregates(
            aggs, command, args.repeat, plot("aggregates", plot_aggregates, aggs), picture
        )
        if aggs.rules:
            body += section_rules(aggs.rules)
    if args.update and out.exists():
        report = splice(out.read_text().splitlines(), body)
    else:
        body += section_recommendations(res)
        report = header(args, argv, time.perf_counter() - started, native32) + body
    out.write_text("\n".join(report).rstrip() + "\n")
    print(f"wrote {out} and its plots in {time.perf_counter() - started:.0f} s", file=sys.stderr)


if __name__ == "__main__":
    main()

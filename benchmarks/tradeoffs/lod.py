"""Trade 2: level of detail, ``tree.query(rect, min_size=min_px / scale)``, against the exact picture."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spatial import Rect

from .measure import BYTES_PER_ITEM, WARMUP, brute, interleaved, p50_us, querying, same
from .render import SCREEN, render
from .report import SCENE_COLOURS, kb, md_table, pct, pyplot, save
from .scene import Scene

LOD_MIN_PX = (0.0, 0.5, 1.0, 2.0, 3.0, 4.0)
LOD_ZOOM = {
    "doc": 0.03,
    "whiteboard": 0.02,
    "clustered": 0.005,
    "uniform": 0.04,
}  # screen pixels per canvas unit
LOD_VIEWS = 16  # zoomed-out viewports per scene, centred on random items
LOD_REPEAT = 5  # timed passes over them
LOD_BUDGET = 0.05  # the recommendation's bound on pixels that change (share of the drawn pixels)


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

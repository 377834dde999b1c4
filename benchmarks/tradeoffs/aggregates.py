"""Trade 6, zoomed out: every item, drop-only LOD or the overview's aggregates against the exact
picture; the overview's merge rules (--rules), its build cost, and docs/zoom-out.png."""

from __future__ import annotations

import gc
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.masks import grid_of, mask_json
from spatial import Rect, scenes
from spatial.quadtree import QuadTree

from ..spatial_bench import source_hash
from .measure import BYTES_PER_ITEM, WARMUP, interleaved, p50_us, querying, timed_build
from .render import SCREEN, Z_ORDER, ink, paint_masks, render
from .report import kb, md_table, pct, pyplot, save
from .scene import Scene

AGG_MIN_PX = 1.0  # the level of detail compared: an item under a screen pixel is too small to draw
AGG_SCALE_STEP = 4  # screen scales 1, 1/4, 1/16, ... down to the one fitting the whole scene
AGG_VIEWS = 8  # full-HD viewports per scale, centred on random items (at the fit scale: one, all)
AGG_REPEAT = 5  # timed passes over them
AGG_GOAL = (0.01, 5000)  # the goal: at most 1% of the pixels differ, with at most 5,000 entries
INK_GOAL = (0.01, 0.05)  # drawn as the page draws: cover-weighted, and binary, share of the screen
AGG_ZOOM_OUT = "zoom-out.png"  # docs/performance.md's picture: the long document at the fit scale and 1/64
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
    # (c) drawn as the page draws it, items solid and aggregates at opacity cover, against every
    # item solid: (2, views) the mean |opacity difference| per pixel, and the share of pixels
    # inked in one picture and not the other
    ink_error: np.ndarray = field(default_factory=lambda: np.zeros((2, 0)))


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
    tiles: list[Any] = field(default_factory=list)  # tiles.TileRow: masks from tiles against per screen


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
                pics, entries, *_ = answers.pictures(rect, scale)
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
    return sum(a.nbytes for a in tree.to_arrays().values())


def overview_held(view: Any) -> int:
    """What a built overview holds: every array it would write to a file (its bands' columns
    and trees, the items' homes)."""
    return sum(a.nbytes for a in view.to_arrays().values())


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

        boxes = self.scene.boxes

        def aggregates(i: int) -> object:
            r = views[i % len(views)]
            band = view.band_within(tree, r, min_size, self.most)
            aggs = view.query(band, r)
            shapes = view.masks(band, aggs, r[:2], AGG_MIN_PX / min_size, tree, lambda ids: boxes[ids])
            return tree.query(r, min_size=view.threshold(band)), aggs, shapes

        return [querying(tree, views), querying(tree, views, min_size=min_size), aggregates]

    def pictures(
        self, rect: Rect, scale: float
    ) -> tuple[list[np.ndarray], list[int], list[int], int, int, tuple[float, float]]:
        """(pictures a, b, c; entries; bytes; natural band; chosen band; (c)'s ink error:
        cover-weighted, binary) for one viewport."""
        tree, view, boxes, kinds = self.scene.tree, self.view, self.scene.boxes, self.scene.kinds
        min_size = AGG_MIN_PX / scale
        every = tree.query(rect)
        dropped = tree.query(rect, min_size=min_size)
        band = self.band(rect, min_size)
        drawn = tree.query(rect, min_size=view.threshold(band))
        aggs = view.query(band, rect)
        agg_boxes, count, cover, agg_kinds, _ = view.rows(band, aggs)
        if len(drawn) + int(count.sum()) < len(every):
            raise SystemExit(f"FATAL: {self.scene.title}: band {band} stands for fewer items than in {rect}")
        # each aggregate's mask, as the service answers it: the screen's pixels its members touch
        grid = grid_of((rect[0], rect[1]), scale)
        windows, bits = view.masks(band, aggs, (rect[0], rect[1]), scale, tree, lambda ids: boxes[ids])
        shapes = [mask_json(w, b, grid) for w, b in zip(windows, bits, strict=True)]
        agg_bytes = sum(
            len(j) + len(m) + 2
            for j, m in zip(self.agg_json(view, scenes.KINDS, band, aggs), shapes, strict=True)
        )
        boxed = np.array([not m for m in shapes], bool)  # no mask (too big): drawn as its box
        c_boxes = np.concatenate([boxes[drawn], agg_boxes[boxed]])
        c_kinds = np.concatenate([kinds[drawn], agg_kinds[boxed].astype(np.uint8)])
        masked = [
            (w, b, k) for w, b, k, m in zip(windows, bits, agg_kinds.tolist(), shapes, strict=True) if m
        ]
        pics = [
            render(boxes[every], kinds[every], rect, scale),
            render(boxes[dropped], kinds[dropped], rect, scale),
            paint_masks(render(c_boxes, c_kinds, rect, scale), masked),
        ]
        if np.any((pics[0] > 0) & (pics[2] == 0)):
            raise SystemExit(f"FATAL: {self.scene.title}: aggregates leave drawn pixels blank in {rect}")
        exact_ink = (pics[0] > 0).astype(np.float64)
        c_ink = ink(c_boxes, np.concatenate([np.ones(len(drawn)), cover[boxed]]), rect, scale)
        np.maximum(
            c_ink, paint_masks(np.zeros_like(pics[0]), [(w, b, 0) for w, b, _ in masked]) > 0, out=c_ink
        )
        ink_error = (float(np.abs(c_ink - exact_ink).mean()), float(((c_ink > 0) != (exact_ink > 0)).mean()))
        entries = [len(every), len(dropped), len(drawn) + len(aggs)]
        nbytes = [
            len(every) * BYTES_PER_ITEM,
            len(dropped) * BYTES_PER_ITEM,
            len(drawn) * BYTES_PER_ITEM + agg_bytes,
        ]
        return pics, entries, nbytes, view.band(min_size), band, ink_error


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
        ink_error = np.zeros((2, len(views)))
        for v, rect in enumerate(views):
            pics, entries, nbytes, natural, band, ink_error[:, v] = answers.pictures(rect, scale)
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
        us = tuple(p50_us(t) for t in ns)
        rows.append(AggRow(scene, scale, fit, bands[0], bands[1], *stats, us, ink_error))
    if scene.key == "doc":
        x0, y0, x1, y1 = extent(scene.boxes)
        middle = ((x0 + x1) / 2, (y0 + y1) / 2)
        fit = agg_scales(scene.boxes)[-1][0]
        for name, scale in (("fit", fit), ("1/64", 1 / 64)):
            if scale >= fit:
                pics, entries, _, _, band, _ = answers.pictures(screen_at(middle, scale), scale)
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


def ink_meets(row: AggRow) -> bool:
    return row.ink_error[0].max() <= INK_GOAL[0] and row.ink_error[1].max() <= INK_GOAL[1]


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
    drawn_as_page = md_table(
        [
            "scene",
            "scale",
            "entries p50 (c)",
            "KB p50 (c)",
            "cover-weighted px differ p50 / max",
            "binary px differ p50 / max",
            f"within {pct(INK_GOAL[0], 0)} / {pct(INK_GOAL[1], 0)}",
        ],
        [
            [
                r.scene.title,
                scale_name(r.scale, r.fit),
                f"{np.median(r.entries[2]):,.0f}",
                kb(np.median(r.nbytes[2])),
                triple([pct(np.median(r.ink_error[0]), 2), pct(r.ink_error[0].max(), 2)]),
                triple([pct(np.median(r.ink_error[1]), 2), pct(r.ink_error[1].max(), 2)]),
                "yes" if ink_meets(r) else "**no**",
            ]
            for r in res.rows
        ],
        "llrrrrl",
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
        "full-HD screen, within the default limit); each aggregate is drawn as the service sends it and "
        "the page draws it: its mask (the screen's pixels its members touch, one bit each) in its "
        "kind (that of its largest element), or its box where it has none (*c: blank painted*: the "
        "share of the screen blank in the exact picture that (c) paints; the rest of its error is a "
        "wrong kind). Scales go from 1 (page level) down by 4x to the scale fitting the "
        f"whole scene on the screen; {AGG_VIEWS} viewports per scale centred on random items, one "
        "(the whole scene) at the fit scale. *band: LOD → chosen*: the band min_px 1 asks for and the "
        "one the budget settled on (a range over the viewports). Bytes: items at "
        f"~{BYTES_PER_ITEM} B each, aggregates as encoded by `app.looks.agg_json`, with their masks "
        "(`app.masks`; before the answer's gzip). Server time is "
        f"the p50 of {AGG_REPEAT} interleaved passes per answer: (a) and (b) one tree query, (c) "
        "`band_within` plus the tree query, the band's query and its aggregates' masks (not the JSON). *goal (c)*: every "
        f"viewport at that scale within {pct(AGG_GOAL[0], 0)} of the screen's pixels and "
        f"{AGG_GOAL[1]:,} entries.",
        "",
        *table,
        "",
        *aggregate_findings(res),
        "",
        "Drawn as the page draws them: items solid, each aggregate's mask solid (and an aggregate "
        "without one, too big for it, as its box at opacity `cover`: its members' summed area over "
        "its box's area), against every item solid; both pictures fill every pixel a box touches, "
        "at least one. *Cover-weighted*: the mean over the screen of the "
        "difference in opacity per pixel; *binary*: the share of the screen's pixels inked in one "
        "picture and not in the other (blank canvas painted, or inked pixels left blank). The goal: "
        f"within {pct(INK_GOAL[0], 0)} and {pct(INK_GOAL[1], 0)} of the screen in every viewport.",
        "",
        *drawn_as_page,
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

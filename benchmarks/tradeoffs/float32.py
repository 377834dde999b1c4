"""Trade 3: coordinate storage, float64 against ``QuadTree(coords="float32")`` rounded outward."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spatial.quadtree import QuadTree

from .measure import WARMUP, brute, compare, interleaved, p50_us, querying
from .report import md_table, pct, pyplot, save
from .scene import Scene, as_rect, columns

MAGNITUDES = (1e2, 1e4, 1e6, 1e8, 1e10, 1e12, 1e15)
MAG_SIDE = 1e4  # the boxes' square, translated to each magnitude
MAG_BOX = (1.0, 20.0)  # box sides, units
MAG_QUERY = (400.0, 225.0)  # query window, units
MAG_QUERIES = 300


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

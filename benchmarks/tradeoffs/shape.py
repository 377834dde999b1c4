"""Trade 4: tree shape, leaf_size, max_depth and x_order against build time, memory and query time."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spatial.quadtree import QuadTree

from .measure import WARMUP, brute, interleaved, p50_us, querying, same, timed_build
from .report import md_table, pyplot, save
from .scene import Scene

CHECKS = 30  # viewports per tree-shape variant compared with brute force before timing

LEAF_SIZES = (8, 16, 32, 64, 128)
DEPTHS = (8, 16, 31)
DEFAULT_SHAPE = (32, 31, True)  # QuadTree's defaults: leaf_size, max_depth, x_order


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

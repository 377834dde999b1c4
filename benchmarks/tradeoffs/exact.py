"""Trade 1: exact answers against leaf candidates, ``tree.query(rect, exact=False)``."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .measure import BYTES_PER_ITEM, WARMUP, brute, compare, interleaved, p50_us, querying, same
from .report import SCENE_COLOURS, kb, md_table, pct, pyplot, save
from .scene import Scene

LINK_BITS_PER_S = 100e6  # to put bytes next to microseconds: a 100 Mbit/s link


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

"""Viewport indexes side by side: vantage's QuadTree against the usual Python peers.

Run from the repository root (a seeded plain script, not a test)::

    python -m benchmarks.spatial_bench                       # all scenes, full scale (minutes)
    python -m benchmarks.spatial_bench --scale 0.1 --steps 300 --out /tmp/bench.md
    python -m benchmarks.spatial_bench --scenes pdf,grid,sparse --indexes vantage,geoindex,strtree

Per scene, every index is built, checked against a brute-force mask and then timed on the
same panning path in one process, so the numbers share a machine state and the ratios
survive a noisy neighbour. Two cache states, each its own table (``--caches``):

- cold: the indexes are interleaved step by step in a shuffled order, so each call finds the
  caches holding the other indexes' data (a server with many documents, one request each);
- warm: each index runs the whole path in turn, several rounds in a shuffled order after an
  untimed one, so its working set is cache-hot (a server with a few hot documents).

Times are what a caller pays: the query call plus turning its result into a numpy array of
indices. Ratios are to the best peer (the faster of geoindex-rs and shapely's STRtree).
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import hashlib
import os
import platform
import shlex
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from spatial import Rect, scenes
from spatial.quadtree import QuadTree

from .machine import cpu_model, versions

try:
    from tqdm import tqdm
except ImportError:  # progress then goes to stderr as plain lines
    tqdm = None

PAN_LIMIT = 200.0  # a step is a "pure pan" if the size is unchanged and it moved less than this
CHECKS = 50  # viewports compared with brute force before timing
WARMUP = 5  # untimed queries first: numba's cache still has to be loaded on the first call
SLOW_BUILD_S = 20.0  # a build slower than this is timed once, not --repeat times
PAGE = os.sysconf("SC_PAGE_SIZE")
GEOINDEX = "geoindex-rs"
STRTREE = "shapely STRtree"
PEERS = (GEOINDEX, STRTREE)  # the ratio columns divide by the faster of these rows
WARM_ROUNDS = 3  # timed rounds of the whole path per index in the warm mode (after one untimed)


@dataclass
class Index:
    """How to build and query one index; the harness does all timing and checking."""

    name: str
    build: Callable[[Any], Any]
    query: Callable[[Any, Rect], np.ndarray]
    diff: Callable[[Any, Rect, Rect], tuple[np.ndarray, np.ndarray]] | None = None  # None: 2 queries
    size: Callable[[Any, int], tuple[float, str] | None] | None = None  # None: ~RSS growth
    prepare: Callable[[np.ndarray], Any] | None = None  # input work timed apart from build
    exact: bool = True  # False: a mismatch is reported, not fatal
    scans: bool = False  # reads much of the data per query: timed in its own group (see main)


@dataclass
class Row:
    name: str
    build_ms: float
    builds: int
    q50: float
    q99: float
    qpan50: float  # query p50 over the pure pans' viewports: what a pan's diff is compared with
    pan50: float
    diff_mean: float
    bytes_item: float
    bytes_label: str
    notes: list[str] = field(default_factory=list)


# -- the indexes ---------------------------------------------------------------------------


def vantage(x_order: bool = True) -> Index:
    return Index(
        "vantage" if x_order else "vantage (no x-order)",
        build=lambda boxes: QuadTree.bulk_load(boxes, x_order=x_order),
        query=lambda tree, r: tree.query(r),
        diff=lambda tree, old, new: tree.diff(old, new),
        size=lambda tree, n: (tree.nbytes / n, "index"),
    )


def geoindex() -> Index:
    from geoindex_rs import rtree as rt

    def build(boxes: np.ndarray) -> Any:
        builder = rt.RTreeBuilder(len(boxes))
        builder.add(*(np.ascontiguousarray(boxes[:, i]) for i in range(4)))  # it wants columns
        return builder.finish()

    def size(tree: Any, n: int) -> tuple[float, str] | None:
        try:  # the packed tree is one buffer, boxes included
            return tree.metadata.num_bytes / n, "buffer"
        except AttributeError:
            return len(memoryview(tree)) / n, "buffer"

    return Index(GEOINDEX, build, lambda tree, r: np.asarray(rt.search(tree, *r)), size=size)


def shapely_strtree() -> Index:
    import shapely

    return Index(
        STRTREE,
        prepare=lambda b: shapely.box(b[:, 0], b[:, 1], b[:, 2], b[:, 3]),  # STRtree needs geometries
        build=shapely.STRtree,
        query=lambda tree, r: tree.query(shapely.box(*r)),  # envelope test, no predicate
    )


def fast_quadtree() -> Index:
    from fastquadtree import RectQuadTree

    def build(boxes: np.ndarray) -> Any:
        lo, hi = boxes[:, :2].min(axis=0), boxes[:, 2:].max(axis=0)
        pad = 1e-3 * float((hi - lo).max()) + 1.0  # it rejects items on or outside its bounds
        tree = RectQuadTree((lo[0] - pad, lo[1] - pad, hi[0] + pad, hi[1] + pad), capacity=16, dtype="f64")
        tree.insert_many_np(boxes)  # ids 0..n-1 in row order
        return tree

    return Index("fastquadtree", build, lambda tree, r: tree.query_np(r)[0])


def rtree_index() -> Index:
    from rtree import index

    def build(boxes: np.ndarray) -> Any:
        # The numpy bulk constructor (libspatialindex >= 2.1): ~100x faster than a Python stream.
        ids = np.arange(len(boxes), dtype=np.int64)
        return index.Index((ids, np.ascontiguousarray(boxes[:, :2]), np.ascontiguousarray(boxes[:, 2:])))

    def query(idx: Any, r: Rect) -> np.ndarray:
        # intersection_v returns an int64 array; a bit faster than np.fromiter(intersection(r)).
        return idx.intersection_v(np.array([r[:2]]), np.array([r[2:]]))[0]

    return Index("rtree", build, query, scans=True)


def brute_force() -> Index:
    def query(cols: tuple[np.ndarray, ...], r: Rect) -> np.ndarray:
        x0, y0, x1, y1 = cols
        return np.flatnonzero((x0 <= r[2]) & (x1 >= r[0]) & (y0 <= r[3]) & (y1 >= r[1]))

    # "build" = contiguous column copies, which make the four comparisons stream memory.
    return Index(
        "numpy brute force",
        lambda b: tuple(np.ascontiguousarray(b[:, i]) for i in range(4)),
        query,
        scans=True,
    )


def sorted_x() -> Index:
    """The naive design-notes idea: one list sorted by x0, searchsorted, filter the slice."""

    def build(boxes: np.ndarray) -> Any:
        order = np.argsort(boxes[:, 0], kind="stable")
        ordered = boxes[order]
        cols = tuple(np.ascontiguousarray(ordered[:, i]) for i in range(4))
        return order, cols, float((boxes[:, 2] - boxes[:, 0]).max())

    def query(state: Any, r: Rect) -> np.ndarray:
        order, (x0, y0, x1, y1), max_w = state
        # Any hit starts in [r.x0 - widest item, r.x1]: on a page column that is every item.
        lo, hi = np.searchsorted(x0, r[0] - max_w, "left"), np.searchsorted(x0, r[2], "right")
        keep = (x1[lo:hi] >= r[0]) & (y0[lo:hi] <= r[3]) & (y1[lo:hi] >= r[1])
        return order[lo:hi][keep]

    return Index("sorted-x list", build, query, scans=True)


INDEXES = {  # --indexes names
    "vantage": vantage,
    "vantage-nox": lambda: vantage(False),
    "geoindex": geoindex,
    "strtree": shapely_strtree,
    "fastquadtree": fast_quadtree,
    "rtree": rtree_index,
    "brute": brute_force,
    "sorted-x": sorted_x,
}


# -- measuring -----------------------------------------------------------------------------


try:  # glibc keeps freed heap pages; without a trim the next build reuses them and RSS reads ~0
    _malloc_trim = ctypes.CDLL("libc.so.6").malloc_trim
except (OSError, AttributeError):
    _malloc_trim = None


def rss() -> int:
    """Resident bytes after a full collection and (on glibc) returning free heap pages to the OS."""
    gc.collect()
    if _malloc_trim is not None:
        _malloc_trim(0)
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE


def measure_build(ix: Index, boxes: np.ndarray, repeat: int) -> tuple[Any, Any, float, int, int, list[str]]:
    """(index, prepared input, median build ms, builds done, RSS growth of the first build, notes)."""
    notes, prepared = [], boxes
    ix.build(ix.prepare(boxes[:1000]) if ix.prepare else boxes[:1000])  # load code, prime allocator
    if ix.prepare:
        before, t0 = rss(), time.perf_counter()
        prepared = ix.prepare(boxes)
        prep_ms = (time.perf_counter() - t0) * 1e3
        prep_bytes = (rss() - before) / len(boxes)
        notes.append(f"input prep (not in build): {prep_ms:.0f} ms, ~{prep_bytes:.0f} B/item RSS")
    times, grown, obj = [], 0, None
    for k in range(repeat):
        obj = None  # free the previous build before timing the next one
        before = rss()
        t0 = time.perf_counter()
        obj = ix.build(prepared)
        times.append(time.perf_counter() - t0)
        if k == 0:  # one reading is enough; it is approximate anyway
            grown = rss() - before
        if times[-1] > SLOW_BUILD_S:
            notes.append(f"built once ({times[-1]:.0f} s), not {repeat}x")
            break
    return obj, prepared, float(np.median(times)) * 1e3, len(times), grown, notes


def two_queries(ix: Index) -> Callable[[Any, Rect, Rect], tuple[np.ndarray, np.ndarray]]:
    """The diff a user writes without a diff API: query both viewports, subtract both ways."""

    def diff(obj: Any, old: Rect, new: Rect) -> tuple[np.ndarray, np.ndarray]:
        a, b = ix.query(obj, old), ix.query(obj, new)
        return np.setdiff1d(b, a), np.setdiff1d(a, b)

    return diff


def timed_together(prepared: list, views: list[Rect]) -> tuple[np.ndarray, np.ndarray]:
    """Nanoseconds per query and per diff, each (indexes, steps).

    At step i every index answers query(views[i]) and diff(views[i-1], views[i]) before any
    takes step i + 1, so a noisy neighbour slows all of them alike and the ratios stay honest.
    The order of those calls is shuffled (seeded) each step: a call that runs right after a
    heavy one finds the caches cold, and a fixed order would always hand that to the same
    call. gc is off so a collection never lands inside one call.
    """
    q = np.zeros((len(prepared), len(views)), np.int64)
    d = np.zeros((len(prepared), len(views)), np.int64)
    calls = [(k, op) for k in range(len(prepared)) for op in (0, 1)]
    rng = np.random.default_rng(0)
    gc.collect()
    gc.disable()
    try:
        for i, view in enumerate(views):
            for c in rng.permutation(len(calls)):
                k, op = calls[c]
                if op and not i:
                    continue  # no diff into the first viewport
                t0 = time.perf_counter_ns()
                if op:
                    prepared[k][1](views[i - 1], view)
                else:
                    prepared[k][0](view)
                (d if op else q)[k, i] = time.perf_counter_ns() - t0
    finally:
        gc.enable()
    return q, d[:, 1:]


def timed_in_turn(prepared: list, views: list[Rect], rounds: int) -> tuple[np.ndarray, np.ndarray]:
    """Like ``timed_together`` but warm: each index runs the whole path (a query, then a diff,
    per step) before the next index starts, so its nodes and boxes stay in the caches.

    One untimed round first, then ``rounds`` timed ones, the indexes in a shuffled (seeded)
    order each round; a step's time is its median over the timed rounds.
    """
    q = np.zeros((len(prepared), rounds, len(views)), np.int64)
    d = np.zeros((len(prepared), rounds, len(views)), np.int64)
    rng = np.random.default_rng(1)
    clock = time.perf_counter_ns
    gc.collect()
    gc.disable()
    try:
        for r in range(-1, rounds):
            for k in rng.permutation(len(prepared)):
                query, diff = prepared[k][0], prepared[k][1]
                qk, dk = q[k, max(r, 0)], d[k, max(r, 0)]
                prev = views[0]
                for i, view in enumerate(views):
                    t0 = clock()
                    query(view)
                    t1 = clock()
                    if i:
                        diff(prev, view)
                    t2 = clock()
                    qk[i], dk[i] = t1 - t0, t2 - t1
                    prev = view
    finally:
        gc.enable()
    return np.median(q, axis=1), np.median(d, axis=1)[:, 1:]


def truth(b: np.ndarray, r: Rect) -> np.ndarray:
    """The reference answer, straight from the (n, 4) rows (closed intervals: touching counts)."""
    return np.flatnonzero((b[:, 0] <= r[2]) & (b[:, 2] >= r[0]) & (b[:, 1] <= r[3]) & (b[:, 3] >= r[1]))


def check(ix: Index, obj: Any, views: list[Rect], truths: dict[int, np.ndarray]) -> str | None:
    """None if every checked query (and diff, where native) matches brute force, else a summary."""
    bad, first = 0, ""
    for i in sorted(i for i in truths if i - 1 in truths):
        got = np.sort(np.asarray(ix.query(obj, views[i])).astype(np.int64))
        want = truths[i]
        ok = np.array_equal(got, want)
        if ok and ix.diff:
            entered, left = ix.diff(obj, views[i - 1], views[i])
            ok = np.array_equal(np.sort(entered), np.setdiff1d(want, truths[i - 1])) and np.array_equal(
                np.sort(left), np.setdiff1d(truths[i - 1], want)
            )
        if not ok:
            bad += 1
            first = first or (
                f"step {i}: {got.size} returned vs {want.size} true, {np.setdiff1d(want, got).size} missing"
            )
    checked = sum(1 for i in truths if i - 1 in truths)
    return f"{bad}/{checked} viewports disagree with brute force (first: {first})" if bad else None


def pure_pans(views: list[Rect]) -> np.ndarray:
    """Mask over steps 1.. : same viewport size as the step before and moved < PAN_LIMIT."""
    v = np.asarray(views)
    w, h = v[:, 2] - v[:, 0], v[:, 3] - v[:, 1]
    same = np.isclose(w[1:], w[:-1], rtol=1e-9) & np.isclose(h[1:], h[:-1], rtol=1e-9)
    return same & (np.abs(v[1:, :2] - v[:-1, :2]).max(axis=1) < PAN_LIMIT)


def prepare_index(ix: Index, boxes: np.ndarray, views: list[Rect], truths: dict, args: argparse.Namespace):
    """Build (timed), warm up and check one index; returns it with its row, times still to fill."""
    obj, prepared, build_ms, builds, grown, notes = measure_build(ix, boxes, args.repeat)
    diff = ix.diff or two_queries(ix)
    for r in views[:WARMUP]:
        ix.query(obj, r)
        diff(obj, views[0], r)
    problem = check(ix, obj, views, truths)
    if problem and ix.exact:
        raise SystemExit(f"FATAL: {ix.name} is wrong: {problem}")
    if problem:
        notes.append(f"INEXACT: {problem}")
    n = len(boxes)
    measured = ix.size(obj, n) if ix.size else None
    bytes_item, label = measured if measured else (grown / n, "~RSS")
    if ix.size:  # say what the exact figure leaves out
        notes.append(f"~RSS growth of first build: {grown / n:.0f} B/item")
    nan = float("nan")
    row = Row(ix.name, build_ms, builds, nan, nan, nan, nan, nan, bytes_item, label, notes)
    return (
        (lambda r: ix.query(obj, r)),
        (lambda old, new: diff(obj, old, new)),
        row,
        ix.scans,
        (obj, prepared),
    )


def time_indexes(prepared: list, views: list[Rect], caches: str) -> list[Row]:
    """Each index's row with its query and diff times in one cache state: "cold" (all indexes
    interleaved step by step) or "warm" (each runs the whole path in turn)."""
    if caches == "cold":
        times = timed_together(prepared, views)
    else:
        times = timed_in_turn(prepared, views, WARM_ROUNDS)
    q, d = (t / 1e3 for t in times)
    pans = pure_pans(views)
    rows = []
    for k, (_, _, row, _, _) in enumerate(prepared):
        row = replace(row, notes=list(row.notes))
        row.q50, row.q99 = float(np.percentile(q[k], 50)), float(np.percentile(q[k], 99))
        if pans.any():  # a pan's diff against a query of the same viewport, not of every viewport
            row.qpan50, row.pan50 = float(np.median(q[k][1:][pans])), float(np.median(d[k][pans]))
        else:
            row.qpan50 = row.pan50 = float("nan")
        row.diff_mean = float(d[k].mean())
        rows.append(row)
    return rows


# -- reporting -----------------------------------------------------------------------------


def ratio(value: float, base: float | None) -> str:
    return f"{value / base:.2f}x" if base else "n/a"


HOW = {
    "cold": "Indexes are timed interleaved step by step in a shuffled order (cold caches: each call "
    "follows other indexes' calls); the three that read most of the data per query (rtree, brute "
    "force, sorted-x) in a group of their own, so they do not flush the caches between the tree "
    "indexes' steps.",
    "warm": f"Each index runs the whole path in turn (warm caches), one untimed round and "
    f"{WARM_ROUNDS} timed ones in a shuffled order; a step's time is its median over the rounds.",
}


def best_peer(rows: list[Row]) -> Row | None:
    """The faster (query p50) of geoindex-rs and shapely's STRtree, whichever ran."""
    peers = [r for r in rows if r.name in PEERS]
    return min(peers, key=lambda r: r.q50) if peers else None


def table(
    scene: str, n: int, rows: list[Row], skipped: list[str], views: list[Rect], hits: float, caches: str
) -> list:
    peer = best_peer(rows)
    base = next((r for r in rows if r.name == GEOINDEX), None)
    pans = int(pure_pans(views).sum())
    lines = [
        f"### {scene}, {caches} caches: {n:,} items, {len(views)} viewports, "
        f"{hits:,.1f} hits per viewport (mean over the checked ones)",
        "",
        f"p50 / best peer is query p50 over the faster of {GEOINDEX} and {STRTREE} "
        f"({peer.name if peer else 'n/a'} here): below 1.00x is faster. Build ratios are to {GEOINDEX}. "
        f"query/pan and diff/pan p50 are over the {pans} pure-pan steps (same size, moved < "
        f"{PAN_LIMIT:.0f} units): the query of the step's viewport, the diff into it; diff mean is "
        "over all steps. Peers diff with two queries + np.setdiff1d both ways. " + HOW[caches],
        "",
        f"| index | build ms | build / {GEOINDEX} | query p50 us | p50 / best peer | query p99 us "
        "| query/pan p50 us | diff/pan p50 us | diff mean us (all steps) | bytes/item |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        once = "" if r.builds > 1 else " (1 build)"
        lines.append(
            f"| {r.name} | {r.build_ms:,.1f}{once} | {ratio(r.build_ms, base and base.build_ms)} "
            f"| {r.q50:,.1f} | {ratio(r.q50, peer and peer.q50)} | {r.q99:,.1f} | {r.qpan50:,.1f} | {r.pan50:,.1f} "
            f"| {r.diff_mean:,.1f} | {r.bytes_item:,.1f} ({r.bytes_label}) |"
        )
    lines.append("")
    lines += [f"- {r.name}: {note}" for r in rows for note in r.notes]
    lines += [f"- skipped {s}" for s in skipped]
    lines.append(
        "- vantage 'index' bytes leave out its own reordered copy of boxes + ids (40 B/item); "
        f"the {GEOINDEX} buffer includes its boxes (32 B/item) and 4-byte indices."
    )
    return [*lines, "", summary(f"{scene}, {caches}", rows), ""]


def summary(scene: str, rows: list[Row]) -> str:
    by = {r.name: r for r in rows}
    v = by.get("vantage")
    if v is None:
        return f"**{scene} bar:** vantage did not run"

    def bar(label: str, ours: float, theirs: float | None, fmt: str, strict: bool = False) -> str:
        if theirs is None:
            return f"{label}: n/a"
        ok = ours < theirs if strict else ours <= theirs
        return f"{label} {ours:{fmt}} {'<' if strict else '<='} {theirs:{fmt}}? {'PASS' if ok else 'FAIL'}"

    strt, peer = by.get(STRTREE), best_peer(rows)
    parts = [
        bar(f"query p50 us vs best peer ({peer.name if peer else 'n/a'})", v.q50, peer and peer.q50, ",.1f"),
        bar("build ms vs shapely STRtree", v.build_ms, strt and strt.build_ms, ",.0f"),
        bar("diff/pan p50 us vs own query/pan p50", v.pan50, v.qpan50, ",.1f", strict=True),
        bar("bytes/item vs 64", v.bytes_item, 64.0, ".1f"),
    ]
    return f"**{scene} bar (vantage):** " + " | ".join(parts)


def straddlers(boxes: np.ndarray) -> str:
    """What storing items at their lowest containing cell (the classic quadtree) would cost.

    An item's lowest containing cell is the common quadrant prefix of its two corners' keys.
    Items pinned near the root sit in every query's path; vantage files items by centre and
    widens its leaves' boxes instead, so none are pinned.
    """
    from spatial import _kernels, _layout

    world = _layout.world(boxes, _kernels.MAX_DEPTH)
    corner = np.ascontiguousarray(boxes[:, [0, 1, 0, 1]])
    low = _kernels.morton_keys(corner, *world)
    corner[:, :2] = boxes[:, 2:]
    corner[:, 2:] = boxes[:, 2:]
    high = _kernels.morton_keys(corner, *world)
    differ = low ^ high
    top_bit = np.where(differ > 0, np.floor(np.log2(np.maximum(differ, 1))).astype(int), -1)
    depth = np.where(differ > 0, (2 * world[3] - 1 - top_bit) // 2, world[3])  # levels shared
    counts = np.bincount(depth)
    shares = ", ".join(f"{counts[d]:,} at depth {d}" for d in range(min(3, counts.size)))
    # A query's path crosses one cell per level, and a level's pinned items are shared among
    # its occupied cells: the expected pinned items on one path.
    bits = world[3]
    per_path = sum(c / np.unique(low >> (2 * (bits - d))).size for d, c in enumerate(counts) if c)
    return (
        f"storing items at their lowest containing cell would pin {shares}: "
        f"~{per_path:,.0f} extra item tests on every query's path (vantage files items by centre: a straddler widens only its own leaf)"
    )


def source_hash() -> str:
    """A short digest of the library's .py files, so a table can be tied to the code it measured."""
    root = os.path.dirname(os.path.abspath(scenes.__file__))
    digest = hashlib.sha256()
    for name in sorted(f for f in os.listdir(root) if f.endswith(".py")):
        with open(os.path.join(root, name), "rb") as f:
            digest.update(name.encode() + f.read())
    return digest.hexdigest()[:12]


def machine_header(args: argparse.Namespace) -> list[str]:
    cpu = cpu_model()
    u = platform.uname()
    pkgs = versions(("numpy", "numba", "shapely", "geoindex-rs", "fastquadtree", "rtree"))
    return [
        "## spatial_bench",
        "",
        f"- machine: {u.system} {u.release} {u.machine}, processor '{platform.processor()}', CPU {cpu}, "
        f"nproc {len(os.sched_getaffinity(0))}",
        f"- python {platform.python_version()}; {pkgs}",
        f"- command: python -m benchmarks.spatial_bench {shlex.join(sys.argv[1:])}",
        f"- spatial sources sha256 {source_hash()} (the tree is not pinned by git here)",
        f"- seed {args.seed}, scale {args.scale}, steps {args.steps}, build repeats {args.repeat} (median)",
        "",
    ]


SCENES = {  # --scenes names: what each is
    "doc": "long document: letter pages in one column, a frame, lines of words and an image each",
    "pdf": "real-document pages in one column: page > block > line > word boxes and figures",
    "grid": "the same pages 25 to a row: pages side by side",
    "whiteboard": "sticky notes in clusters plus rare huge frames",
    "uniform": "1..50-unit boxes spread uniformly, ~1000 per viewport",
    "sparse": "4..40-unit markers spread uniformly, ~2 per viewport",
}


def make_scene(name: str, scale: float, seed: int) -> tuple[np.ndarray, str]:
    """Boxes and a title; scale 1.0 is ~1M items (2000 pages of doc, 2500 of pdf and grid)."""
    if name == "doc":
        pages = max(1, round(2000 * scale))
        return scenes.long_document(pages=pages, seed=seed)[0], f"long document ({pages} pages)"
    if name in ("pdf", "grid"):
        pages, columns = max(1, round(2500 * scale)), 1 if name == "pdf" else 25
        boxes = scenes.pdf_pages(pages=pages, columns=columns, seed=seed)[0]
        return boxes, f"{name}: PDF pages, {columns} to a row ({pages} pages)"
    n = max(1, round(1_000_000 * scale))
    maker = {"whiteboard": scenes.whiteboard, "uniform": scenes.uniform, "sparse": scenes.sparse}[name]
    return maker(n=n, seed=seed)[0], name


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.spatial_bench",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--scenes",
        default=",".join(SCENES),
        help="comma list of: " + "; ".join(f"{k} ({v})" for k, v in SCENES.items()),
    )
    parser.add_argument("--caches", default="warm,cold", help="comma list of warm, cold (see above)")
    parser.add_argument("--indexes", default=",".join(INDEXES), help="comma list of: " + ", ".join(INDEXES))
    parser.add_argument("--scale", type=float, default=1.0, help="item count factor (1.0: 2000 pages, 1M)")
    parser.add_argument("--steps", type=int, default=2000, help="panning path steps")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeat", type=int, default=3, help="builds per index; the median is reported")
    parser.add_argument("--out", help="also write the markdown report to this path")
    args = parser.parse_args(argv)
    names = [s.strip() for s in args.scenes.split(",") if s.strip()]
    modes = [s.strip() for s in args.caches.split(",") if s.strip()]
    picked = [s.strip() for s in args.indexes.split(",") if s.strip()]
    unknown = (set(names) - set(SCENES)) | (set(modes) - {"warm", "cold"}) | (set(picked) - set(INDEXES))
    if unknown or args.steps < 2 or args.scale <= 0 or args.repeat < 1 or not modes:
        parser.error(f"bad arguments (unknown scenes: {sorted(unknown)})" if unknown else "bad arguments")

    report = machine_header(args)
    print("\n".join(report), flush=True)
    for name in names:
        boxes, title = make_scene(name, args.scale, args.seed)
        views = [tuple(map(float, r)) for r in scenes.panning_path(boxes, args.steps, args.seed)]
        picks = np.unique(np.linspace(1, len(views) - 1, CHECKS).astype(int))
        truths = {int(i): truth(boxes, views[i]) for p in picks for i in (p - 1, p)}
        hits = float(np.mean([t.size for t in truths.values()]))
        prepared, skipped = [], []
        makers = [INDEXES[k] for k in picked]
        steps = tqdm(makers, desc=f"{name}: build + check", file=sys.stderr) if tqdm else makers
        for make in steps:
            try:
                ix = make()
            except ImportError as e:  # a missing peer is a note, not a crash
                skipped.append(f"{getattr(make, '__name__', make)}: {e}")
                continue
            if not tqdm:
                print(f"[{name}] {ix.name} ...", file=sys.stderr, flush=True)
            prepared.append(prepare_index(ix, boxes, views, truths, args))
        for caches in modes:
            # Indexes that read most of the data per query would flush the caches between the
            # others' steps; each group is timed within itself.
            rows = []
            for scans in (False, True):
                group = [p for p in prepared if p[3] == scans]
                print(
                    f"[{name}] timing {len(group)} indexes, {caches} caches, over {len(views)} steps ...",
                    file=sys.stderr,
                )
                rows += time_indexes(group, views, caches) if group else []
            order = {p[2].name: k for k, p in enumerate(prepared)}
            rows.sort(key=lambda r: order[r.name])
            lines = table(title, len(boxes), rows, skipped, views, hits, caches)
            lines.insert(-2, f"- {straddlers(boxes)}")
            print("\n".join(lines), flush=True)
            report += lines
        del prepared
        del boxes
        gc.collect()
    if args.out:
        with open(args.out, "w") as f:
            f.write("\n".join(report) + "\n")


if __name__ == "__main__":
    main()

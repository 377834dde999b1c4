"""Truth and timing, shared by the trades: brute force, comparing answers, interleaved calls, builds."""

from __future__ import annotations

import gc
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from spatial import Rect
from spatial.quadtree import QuadTree

BYTES_PER_ITEM = 100  # ~ one item as JSON: id, four coordinates, a kind

WARMUP = 5  # untimed calls first: numba loads its cache (and compiles for float32 boxes) on the first


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


def timed_build(boxes: np.ndarray, repeat: int, **options: Any) -> tuple[QuadTree, float]:
    """The tree and the median build time (ms) over ``repeat`` builds."""
    times, tree = [], None
    for _ in range(repeat):
        tree = None  # free the previous build before timing the next
        t0 = time.perf_counter()
        tree = QuadTree.bulk_load(boxes, **options)
        times.append(time.perf_counter() - t0)
    return tree, float(np.median(times)) * 1e3

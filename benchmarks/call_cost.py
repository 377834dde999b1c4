"""Where one query's and one diff's time goes: Python, the call into compiled code, the walk.

Run from the repository root (a seeded plain script, not a test)::

    python -m benchmarks.call_cost                          # all scenes, full scale (seconds)
    python -m benchmarks.call_cost --scenes sparse,doc --scale 0.2

Per scene, one tree is built and, over the panning path's pure pans, five calls are timed at
every step in a shuffled (seeded) order, several rounds, warm caches:

- ``QuadTree.query(view)`` and ``QuadTree.diff(prev, view)``, what a caller pays;
- the same two compiled kernels called directly, with the arguments the methods pass them:
  the methods' Python is the difference;
- an empty kernel taking the query's arguments and handing back an empty array: what any
  call into compiled code costs here (unpacking the tree's arrays, building the result).

A kernel's walk is then its time less that floor. Medians per call; read the differences.
"""

from __future__ import annotations

import argparse
import gc
import platform
import sys
import time

import numba as nb
import numpy as np

from spatial import scenes
from spatial.quadtree import QuadTree, _compiled

from .machine import cpu_model, versions
from .spatial_bench import SCENES, make_scene, pure_pans

CALLS = ("query", "query kernel", "diff", "diff kernel", "empty kernel")


@nb.njit(cache=True, nogil=True)
def _empty(arrays, flags, x0, y0, x1, y1, min_size):
    """The query kernel's arguments in, an array out, no walk."""
    return np.empty(1024, np.int64)[:0]


def calls(tree: QuadTree) -> list:
    """The five timed callables, each taking (old, new) viewports."""
    query, diff = tree._query, tree._diff  # the compiled code the methods call
    arrays, flags = tree._arrays, tree._flags
    empty = _compiled(_empty, arrays, flags, 0.0, 0.0, 0.0, 0.0, 0.0)
    return [
        lambda old, new: tree.query(new),
        lambda old, new: query(arrays, flags, *new, 0.0),
        lambda old, new: tree.diff(old, new),
        lambda old, new: diff(arrays, flags, *new, 0.0, *old, 0.0),
        lambda old, new: empty(arrays, flags, *new, 0.0),
    ]


def timed(fns: list, steps: list[tuple], rounds: int) -> np.ndarray:
    """Median nanoseconds per callable over ``steps`` ((old, new) pairs) and ``rounds``."""
    rng = np.random.default_rng(0)
    clock = time.perf_counter_ns
    ns = np.zeros((len(fns), rounds, len(steps)), np.int64)
    gc.collect()
    gc.disable()
    try:
        for r in range(-1, rounds):  # one untimed round first
            for i, (old, new) in enumerate(steps):
                for k in rng.permutation(len(fns)):
                    t0 = clock()
                    fns[k](old, new)
                    ns[k, max(r, 0), i] = clock() - t0
    finally:
        gc.enable()
    return np.median(ns.reshape(len(fns), -1), axis=1)


def row(title: str, us: np.ndarray) -> str:
    q, qk, d, dk, floor = us
    cells = [
        title,
        f"{q:.2f}",
        f"{q - qk:.2f}",
        f"{qk - floor:.2f}",
        f"{d:.2f}",
        f"{d - dk:.2f}",
        f"{dk - floor:.2f}",
        f"{floor:.2f}",
        f"{d / q:.2f}x",
        f"{d - q:+.2f}",
    ]
    return "| " + " | ".join(cells) + " |"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.call_cost",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--scenes", default=",".join(SCENES), help="comma list of: " + ", ".join(SCENES))
    parser.add_argument("--scale", type=float, default=1.0, help="item count factor (1.0: ~1M items)")
    parser.add_argument("--steps", type=int, default=2000, help="panning path steps")
    parser.add_argument("--rounds", type=int, default=5, help="timed rounds of the path")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", help="also write the markdown report to this path")
    args = parser.parse_args(argv)
    names = [s.strip() for s in args.scenes.split(",") if s.strip()]
    unknown = sorted(set(names) - set(SCENES))
    if unknown or not names or args.scale <= 0 or args.steps < 2 or args.rounds < 1:
        parser.error(f"unknown scenes: {unknown}" if unknown else "bad arguments")

    report = [
        f"Machine: {cpu_model()}, {platform.python_version()}; "
        + versions(("numpy", "numba"))
        + f". Command: python -m benchmarks.call_cost {' '.join(argv if argv is not None else sys.argv[1:])}",
        "",
        "Medians in us over the path's pure pans, warm caches. Python: the method less its kernel; "
        "walk: the kernel less the empty kernel (the floor: any call into compiled code).",
        "",
        "| scene | query | its Python | its walk | diff | its Python | its walk | floor | diff / query | diff - query |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    print("\n".join(report), flush=True)
    for name in names:
        boxes, title = make_scene(name, args.scale, args.seed)
        tree = QuadTree.bulk_load(boxes)
        views = [tuple(map(float, r)) for r in scenes.panning_path(boxes, args.steps, args.seed)]
        steps = [(views[i], views[i + 1]) for i in np.flatnonzero(pure_pans(views))]
        print(f"[{name}] {len(boxes):,} items, {len(steps)} pure pans ...", file=sys.stderr, flush=True)
        line = row(title, timed(calls(tree), steps, args.rounds) / 1e3)
        print(line, flush=True)
        report.append(line)
    if args.out:
        with open(args.out, "w") as f:
            f.write("\n".join(report) + "\n")


if __name__ == "__main__":
    main()

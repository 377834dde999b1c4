"""What one more edit costs with k edits pending since the base, in memory (no store, no HTTP).

A board of ``--items`` boxes is built as a snapshot; random moves are applied in batches of
20,000 (as a follower's catch-up applies another process's edits: their cost an edit is
printed too), up to each k; then one more edit, ``--repeats`` times, each on the snapshot the
last made (as a server's edits follow one another): their median. The tree is set not to
rebuild itself, as a document's is (its compaction, in the background, comes first).

    .venv/bin/python -m benchmarks.edit_pending
    .venv/bin/python -m benchmarks.edit_pending --items 100000 --pending 1000,10000

Prints a markdown table. No test runs it; the numbers go in docs/performance.md.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from app.snapshots import Snapshot, build
from app.table import ItemTable
from benchmarks.machine import cpu_model

BATCH = 20_000
BODY = b'{"kind":"text"}'


def moved(snap: Snapshot, ids: list[int]) -> Snapshot:
    """``snap`` with the items ``ids`` moved, one edit (one version) each, in one batch."""
    edits = [
        (f"i{k}", snap.version + 1 + e, (float(k % 90_000), 1.0, k % 90_000 + 3.0, 4.0), BODY)
        for e, k in enumerate(ids)
    ]
    return snap.with_edits(edits)[0]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.edit_pending",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--items", type=int, default=1_000_000)
    parser.add_argument(
        "--pending", default="1000,10000,100000,400000", help="edits pending, comma-separated"
    )
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--seed", type=int, default=5)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    xy = rng.uniform(0, 1e5, (args.items, 2))
    ids = [f"i{k}" for k in range(args.items)]
    snap = build(ItemTable.of(ids, np.column_stack([xy, xy + 5]), [BODY] * args.items), 1, "b")
    snap.tree.max_buffered = 10**9
    print(f"machine: {cpu_model()}; {args.items:,} items")
    print("| edits pending | one more edit, median ms | in batches of 20,000, ms an edit |")
    print("|---:|---:|---:|")
    for pending in (int(p) for p in args.pending.split(",")):
        todo = pending - snap.edits
        started = time.perf_counter()
        for lo in range(0, todo, BATCH):
            snap = moved(snap, rng.integers(0, args.items, min(BATCH, todo - lo)).tolist())
        batched = (time.perf_counter() - started) / max(todo, 1)
        times = []
        for _ in range(args.repeats):
            k = int(rng.integers(0, args.items))
            started = time.perf_counter()
            snap = snap.with_edits([(f"i{k}", snap.version + 1, (1.0, 1.0, 4.0, 4.0), BODY)])[0]
            times.append(time.perf_counter() - started)
        print(f"| {pending:,} | {statistics.median(times) * 1e3:.2f} | {batched * 1e3:.3f} |", flush=True)


if __name__ == "__main__":
    main()

"""What opening a document with k edits pending costs: every edit replayed from the store, or
the edits saved beside the base's file taken as made and only those since replayed.

A seeded board of ``--items`` boxes is imported (``vantage import``), then its items are
moved (random items to random places, 500 an edit) up to each k, at most a compaction's
threshold (past it, a server folds them into a new base). The edits are saved beside the
base's file with ``SAVE_EDITS_EVERY - 1`` still to come, as a server leaves them at worst
(each open then replays those). Each open is a process of its own, the kernels warmed first
(as a server's start-up does): the time to the document open (``Registry[doc]``), first with
the page cache dropped (when this process may), then warm, the median of ``--repeats``;
without the saved edits (the file set aside), then with them. Then the answers with those
edits pending, zoomed out: a full-HD screen at each band's scale (its aggregates and their
masks), against the same with none pending (the first row).

    .venv/bin/python -m benchmarks.open_pending
    .venv/bin/python -m benchmarks.open_pending --items 100000 --pending 2000,8000

Prints a markdown table. No test runs it; the numbers go in docs/performance.md.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from app.demo import ndjson_lines
from app.documents import SAVE_EDITS_EVERY
from app.snapshots import COMPACT_AFTER
from benchmarks.machine import cpu_model
from benchmarks.scale import ENV, SCREEN, board, drop_page_cache

BATCH = 500


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.open_pending",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--items", type=int, default=10_000_000)
    parser.add_argument(
        "--pending",
        default="4000,16000,40000",
        help="edits pending, comma-separated, each at most a compaction's threshold (1,024 + items/256)",
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--open", type=Path, help=argparse.SUPPRESS)  # an open's own process
    args = parser.parse_args(argv)
    if args.open:
        return _open(args.open)
    pending = sorted(int(p) for p in args.pending.split(","))
    if pending[-1] > COMPACT_AFTER + args.items // 256:
        parser.error(f"--pending: past {COMPACT_AFTER + args.items // 256:,} edits, a compaction folds them")
    print(f"machine: {cpu_model()}, {os.cpu_count()} cores; {args.items:,} items")
    print(
        "| edits pending | replayed, cold s | replayed, warm s | from the saved edits, cold s "
        "| from the saved edits, warm s | warm ratio | zoomed-out answer ms, median / worst band |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory(prefix="vantage-open-") as work:
        data = imported_board(Path(work), args.items, args.seed)[0]
        zoomed = _timed_open(data)[1]
        print(f"| 0 | | | | | | {zoomed[0]:.1f} / {zoomed[1]:.1f} |", flush=True)
        made = 0
        for k in pending:
            made = edit_up_to(data, made, k, args.seed)
            (saved,) = (data / "snapshots").glob("*.vedits")
            aside = saved.with_name(saved.name + ".aside")
            saved.rename(aside)
            replayed = _opens(data, args.repeats)
            aside.rename(saved)
            taken = _opens(data, args.repeats)
            zoomed = _timed_open(data)[1]
            print(
                f"| {k:,} | {replayed[0]:.2f} | {replayed[1]:.2f} | {taken[0]:.2f} | {taken[1]:.2f} "
                f"| {replayed[1] / taken[1]:.1f}x | {zoomed[0]:.1f} / {zoomed[1]:.1f} |",
                flush=True,
            )


def imported_board(work: Path, items: int, seed: int) -> tuple[Path, np.ndarray, np.ndarray]:
    """The seeded board of ``items`` imported (``vantage import``) into a store in ``work``:
    ``(its data directory, the board's lowest corner, its highest)``."""
    data, source = work / "data", work / "board.ndjson"
    boxes, kinds = board(items, seed)
    with open(source, "wb") as out:
        out.writelines(ndjson_lines(boxes, kinds))
    command = ["-m", "app.cli", "import", str(source), "--doc", "big", "--data-dir", str(data)]
    subprocess.run([sys.executable, *command], check=True, env=ENV, capture_output=True)
    source.unlink()
    return data, boxes[:, :2].min(axis=0), boxes[:, 2:].max(axis=0)


def edit_up_to(data: Path, made: int, pending: int, seed: int) -> int:
    """Edits made in ``data``'s document up to ``pending``, saved beside its base with
    ``SAVE_EDITS_EVERY - 1`` to come (the worst case of a server's); the edits made."""
    import app.documents
    from app import editfile
    from app.items import decode_item
    from app.registry import Registry
    from app.snapfile import SnapshotFiles
    from app.stores import SQLiteStore

    store = SQLiteStore(data)
    try:
        files = SnapshotFiles(data / "snapshots")
        tail = SAVE_EDITS_EVERY - 1  # the setting's, not the 10**12 set below (by an earlier call too)
        app.documents.SAVE_EDITS_EVERY = 10**12  # saved once, below, where the worst case has it
        doc = Registry(store, files, 1 << 40)[store.documents()[0]["id"]]
        rng = np.random.default_rng(seed + pending)
        n, (x0, y0, x1, y1) = len(doc.snapshot.table), doc.snapshot.bounds
        for target in (max(made, pending - tail), pending):
            while made < target:
                count = min(BATCH, target - made)
                changes = []
                for k in rng.choice(n, count, replace=False).tolist():
                    x, y = float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1))
                    fields = {"x0": x, "y0": y, "x1": x + 5, "y1": y + 5, "kind": "text"}
                    item = decode_item(msgspec.json.encode(fields), 1 << 10, f"i{k}")
                    changes.append((f"i{k}", (x, y, x + 5, y + 5), item.bodies[0]))
                doc.edit(changes)
                made += count
            if target < pending:
                snap = doc.snapshot
                editfile.save(files.edits_path(doc.id, str(snap.base_id)), snap)
    finally:
        store.close()
    return made


def _opens(data: Path, repeats: int) -> tuple[float, float]:
    """Seconds to open the document in a process of its own: cold (the page cache dropped
    first; warm if it cannot be), then the median of ``repeats`` warm."""
    drop_page_cache()
    cold = _timed_open(data)[0]
    return cold, statistics.median(_timed_open(data)[0] for _ in range(repeats))


def _timed_open(data: Path) -> tuple[float, tuple[float, float]]:
    """Seconds to open the document, and its zoomed-out answers' (``_zoomed``)."""
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.open_pending", "--open", str(data)],
        check=True,
        env=ENV,
        capture_output=True,
    )
    seconds, median, worst = map(float, out.stdout.split()[-3:])
    return seconds, (median, worst)


def _zoomed(snap: Any) -> tuple[float, float]:
    """A full-HD screen's answer at each band's scale (its top-left corner at the document's),
    each read once first, then the median of three: the median over the bands, and the worst,
    in ms."""
    from app.answers import View, viewport

    overview, (x0, y0, _, _) = snap.overview, snap.bounds
    times = []
    for band in range(overview.lo, overview.hi + 1):
        scale = 1.0 / overview.threshold(band)
        view = View.of((x0, y0, x0 + SCREEN[0] / scale, y0 + SCREEN[1] / scale), "rect", scale, 1.0)
        viewport(snap, view, cap=5000)
        each = []
        for _ in range(3):
            started = time.perf_counter()
            viewport(snap, view, cap=5000)
            each.append(time.perf_counter() - started)
        times.append(statistics.median(each) * 1e3)
    return statistics.median(times), max(times)


def _open(data: Path) -> None:
    """The open ``_timed_open`` times: the kernels warmed, then the document opened; prints
    the seconds of the open, then its zoomed-out answers' (``_zoomed``)."""
    import app.documents
    from app.housekeeping import warm_up
    from app.registry import Registry
    from app.snapfile import SnapshotFiles
    from app.stores import SQLiteStore

    warm_up(lambda _: None)
    app.documents.SAVE_EDITS_EVERY = 10**12  # an open that replayed them all saves none: the next opens alike
    store = SQLiteStore(data)
    try:
        registry = Registry(store, SnapshotFiles(data / "snapshots"), 1 << 40)
        doc_id = store.documents()[0]["id"]
        started = time.perf_counter()
        doc = registry[doc_id]
        print(time.perf_counter() - started, *_zoomed(doc.snapshot))
    finally:
        store.close()


if __name__ == "__main__":
    main()

"""How long another document's writers wait while a big document is imported, then compacted.

Seeded: the ``--items`` board is written as NDJSON; a SQLite store is made with a small
document beside it; then, each in a process of its own, ``vantage import FILE --doc big``,
and (after 1,000 edits of the big document) its compaction (``Document.compact``, as the
server runs it in the background). Meanwhile this process, another process to the store as
a second worker is, edits the small document every 20 ms and times each edit's write. On
SQLite every write takes the store's one writing turn, so what an import or a compaction
holds of it is what every other writer waits for; an edit that waits past the store's busy
timeout (60 s) fails ("database is locked") and is counted.

    .venv/bin/python -m benchmarks.write_waits --items 1e6
    .venv/bin/python -m benchmarks.write_waits --items 1e7

Prints a markdown table. No test runs it; the numbers go in docs/performance.md.
"""

from __future__ import annotations

import argparse
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from app.demo import ndjson_lines
from app.items import Item, batch_of
from app.registry import Registry
from app.snapfile import SnapshotFiles
from app.stores import SQLiteStore
from benchmarks.machine import cpu_model
from benchmarks.scale import ENV, board

EDITS = 1_000


def waits_during(command: list[str], data_dir: Path, doc_id: str) -> tuple[float, list[float], int]:
    """``command`` (Python's arguments) run in a process of its own while this one edits
    ``doc_id`` every 20 ms: (its seconds, each edit's seconds, the edits that failed)."""
    store = SQLiteStore(data_dir)
    doc = Registry(store, SnapshotFiles(data_dir / "snapshots"), 1 << 30)[doc_id]
    waits: list[float] = []
    failed, done = [0], threading.Event()

    def edit() -> None:
        k = 0
        while not done.is_set():
            start = time.perf_counter()
            try:
                doc.put(batch_of([Item(f"e{k % 10}", k, 0.0, k + 1.0, 1.0)], 4096))
                waits.append(time.perf_counter() - start)
            except sqlite3.OperationalError:
                failed[0] += 1
            k += 1
            time.sleep(0.02)

    editor = threading.Thread(target=edit)
    started = time.perf_counter()
    process = subprocess.Popen(
        [sys.executable, *command], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=ENV
    )
    editor.start()
    _, err = process.communicate()
    seconds = time.perf_counter() - started
    done.set()
    editor.join()
    store.close()
    if process.returncode:
        raise SystemExit(f"{' '.join(command)} failed:\n{err.decode()[-2000:]}")
    return seconds, waits, failed[0]


def edit_big(data_dir: Path, seed: int) -> None:
    """``EDITS`` moves of the big document's items, each an edit of its own."""
    store = SQLiteStore(data_dir)
    registry = Registry(store, SnapshotFiles(data_dir / "snapshots"), 1 << 40)
    big = registry[next(d["id"] for d in store.documents() if d["name"] == "big")]
    rng = np.random.default_rng(seed)
    for k in rng.choice(big.describe()["items"], EDITS, replace=False).tolist():
        x, y = rng.random(2) * 1000
        big.put(batch_of([Item(f"i{k}", float(x), float(y), float(x) + 5, float(y) + 5, kind="text")], 4096))
    store.close()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.write_waits",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--items", default="1e6", help="items of the big document (1e6)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--work", type=Path, default=None, help="scratch directory (default: a temporary one)"
    )
    args = parser.parse_args(argv)
    n = int(float(args.items))
    print(f"machine: {cpu_model()}; {n:,} items")
    print("| while | seconds | edits of another document | p50 wait ms | longest wait s | failed |")
    print("|---|---:|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory(prefix="vantage-waits-", dir=args.work) as work:
        path, data = Path(work) / "board.ndjson", Path(work) / "data"
        boxes, kinds = board(n, args.seed)
        with open(path, "wb") as out:
            out.writelines(ndjson_lines(boxes, kinds))
        del boxes, kinds
        store = SQLiteStore(data)
        other = Registry(store, SnapshotFiles(data / "snapshots"), 1 << 30).create("other").id
        store.close()
        runs = {
            "the import": ["-m", "app.cli", "import", str(path), "--doc", "big", "--data-dir", str(data)],
            f"the compaction after {EDITS:,} edits": ["-m", "benchmarks.scale", "--compact", str(data)],
        }
        for label, command in runs.items():
            if "compaction" in label:
                edit_big(data, args.seed)
            seconds, waits, failed = waits_during(command, data, other)
            print(
                f"| {label} | {seconds:.1f} | {len(waits)} | {statistics.median(waits or [0]) * 1e3:.1f} | "
                f"{max(waits, default=0):.2f} | {failed} |",
                flush=True,
            )


if __name__ == "__main__":
    main()

"""What edits pending cost a server's answers: viewports over HTTP with k edits pending,
while an editor moves items and the worker saves its edits beside the base, or never does.

A seeded board of ``--items`` boxes is imported (``vantage import``), then its items are
moved (random items to random places, 500 an edit) up to each k (``open_pending``'s edits),
at most a compaction's threshold. For each k a real server is started twice: saving the
edits by their age as often as it may (``VANTAGE_SAVE_EDITS_SECONDS=1``: a save each time
20 times its own cost has passed, the most a busy document sees), then never by age. In each,
this process asks for random screens (the scale benchmark's, a full-HD rectangle of the
board) back to back for ``--seconds``, while a thread of it moves an item twice a second.

    .venv/bin/python -m benchmarks.serve_pending
    .venv/bin/python -m benchmarks.serve_pending --items 1000000 --pending 4000 --seconds 20

Prints a markdown table. No test runs it; the numbers go in docs/performance.md.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

from app.launch import launch, stop
from app.snapshots import COMPACT_AFTER
from benchmarks.machine import cpu_model
from benchmarks.open_pending import edit_up_to, imported_board
from benchmarks.scale import ENV, SCREEN, screen_at

EDITS_A_SECOND = 2
NEVER = str(10**9)  # seconds: no save by age


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.serve_pending",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--items", type=int, default=10_000_000)
    parser.add_argument("--pending", default="0,4000,35000", help="edits pending, comma-separated")
    parser.add_argument("--seconds", type=float, default=40.0, help="of screens asked for, each run")
    parser.add_argument("--seed", type=int, default=5)
    args = parser.parse_args(argv)
    pending = sorted(int(p) for p in args.pending.split(","))
    limit = COMPACT_AFTER + args.items // 256
    if pending[-1] + 2 * EDITS_A_SECOND * args.seconds * len(pending) >= limit:
        parser.error(f"--pending: with the editor's moves, past {limit:,} edits a compaction folds them")
    print(f"machine: {cpu_model()}, {os.cpu_count()} cores; {args.items:,} items")
    print("| edits pending (about) | saves by age | screens | p50 ms | p99 ms | p99.9 ms | max ms |")
    print("|---:|---|---:|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory(prefix="vantage-serve-") as work:
        data, lo, hi = imported_board(Path(work), args.items, args.seed)
        made = 0
        for k in pending:
            made = edit_up_to(data, made, max(k, made), args.seed)
            for every, said in (("1", "as often as it may"), (NEVER, "none")):
                times = _served(data, lo, hi, args.seconds, every, args.seed + k)
                p = np.percentile(times, [50, 99, 99.9]) * 1e3
                print(
                    f"| {made:,} | {said} | {len(times):,} | {p[0]:.2f} | {p[1]:.2f} | {p[2]:.2f} "
                    f"| {times.max() * 1e3:.1f} |",
                    flush=True,
                )
                made += round(EDITS_A_SECOND * args.seconds)  # about: the editor's, below


def _served(data: Path, lo: np.ndarray, hi: np.ndarray, seconds: float, every: str, seed: int) -> np.ndarray:
    """Seconds each screen took, asked for back to back for ``seconds`` (after 50 unmeasured),
    while a thread moves an item ``EDITS_A_SECOND`` times a second."""
    process, url = launch(data, env={**ENV, "VANTAGE_SAVE_EDITS_SECONDS": every}, output=subprocess.DEVNULL)
    rng, moves = np.random.default_rng(seed), np.random.default_rng(seed + 1)
    done = threading.Event()

    def edit(doc: str) -> None:
        with httpx.Client(base_url=url, timeout=600) as c:
            while not done.wait(1 / EDITS_A_SECOND):
                k = int(moves.integers(0, 1000))
                x, y = (float(v) for v in moves.uniform(lo, hi))
                c.put(f"/documents/{doc}/items/i{k}", json={"x0": x, "y0": y, "x1": x + 5, "y1": y + 5})

    try:
        with httpx.Client(base_url=url, timeout=600) as c:
            doc = c.get("/documents").json()[0]["id"]
            corners = rng.uniform(lo, np.maximum(hi - SCREEN, lo + 1), (1 << 20, 2))
            for corner in corners[:50]:
                c.get(f"/documents/{doc}/viewport", params=screen_at(corner)).raise_for_status()
            editor = threading.Thread(target=edit, args=(doc,))
            editor.start()
            times, end = [], time.monotonic() + seconds
            for corner in corners[50:]:
                if time.monotonic() >= end:
                    break
                started = time.perf_counter()
                c.get(f"/documents/{doc}/viewport", params=screen_at(corner)).raise_for_status()
                times.append(time.perf_counter() - started)
            done.set()
            editor.join()
    finally:
        stop(process)
    return np.array(times)


if __name__ == "__main__":
    main()

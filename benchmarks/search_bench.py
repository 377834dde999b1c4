"""What a search costs, and that searches never hold up the rest: on the demo documents (the
2000-page report, ~1M items, and the whiteboard), against a real `vantage serve`.

Run from the repository root (a seeded plain script, not a test)::

    .venv/bin/python -m benchmarks.search_bench            # about 2 minutes
    .venv/bin/python -m benchmarks.search_bench --help

Reports, medians over the rounds (requests on one kept-alive connection):

- the text index: its build time against the whole snapshot's, and its bytes per item;
- per query, over HTTP: a one-word miss, a phrase miss, the first page of a common word, a
  phrase across words, and the attack pass's 200-character query of 32 non-ASCII words; each
  against the one-word miss;
- 40 of those 32-word queries at once (each from a thread of a separate process), while one
  client pans viewports and another asks ``/health``: their p50 and p99.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

from app.demo import create_demos
from app.launch import launch, stop
from app.snapshots import build
from app.stores import SQLiteStore
from app.text import TextIndex

from .machine import cpu_model, versions

ATTACK = " ".join(["Ééééé"] * 32)  # 32 non-ASCII words, ~200 characters
QUERIES = {
    "one-word miss": "zyzzyva",
    "phrase miss": "quarterly revenue zyzzyva",
    "common word, first 20 hits": "the",
    "phrase across words, first 20": "these first",
    "32 non-ASCII words (the attack)": ATTACK,
}


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def timed(client: httpx.Client, path: str, params: dict) -> float:
    started = time.perf_counter()
    client.get(path, params=params).raise_for_status()
    return time.perf_counter() - started


def index_cost(data: Path, doc: str) -> tuple[TextIndex, float, float, float]:
    """``(the text index, seconds to build it, seconds to build the whole snapshot, bytes/item)``."""
    store = SQLiteStore(data)
    table = store.read_items(doc)
    store.close()
    started = time.perf_counter()
    text = TextIndex.of_table(table.bodies)
    text_seconds = time.perf_counter() - started
    started = time.perf_counter()
    build(table, 1, "bench")
    return text, text_seconds, time.perf_counter() - started, text.nbytes / len(table)


def miss_at_scale(text: TextIndex, copies: int, rounds: int) -> tuple[int, float]:
    """``(text items, median seconds of a miss)`` over the report's text ``copies`` times over:
    the buffer a document of that many words would map (what a miss reads, whole)."""
    big = TextIndex(np.tile(text.text, copies), np.zeros(2, np.int64), np.zeros(1, np.int64))
    samples = []
    for _ in range(rounds):
        started = time.perf_counter()
        assert not any(True for _ in big.find(b"zyzzyva"))
        samples.append(time.perf_counter() - started)
    return len(text.positions) * copies, statistics.median(samples)


def crowd(url: str, doc: str, seconds: float, searchers: int) -> dict[str, list[float]]:
    """``searchers`` attack queries at a time from a separate process, for ``seconds``, while this
    process pans viewports and asks /health: their latencies."""
    script = (
        "import sys, threading, time, httpx\n"
        "url, doc, q, n, until = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), time.time() + float(sys.argv[5])\n"
        "def run():\n"
        "    with httpx.Client(timeout=60) as c:\n"
        "        while time.time() < until:\n"
        "            r = c.get(f'{url}/documents/{doc}/search', params={'q': q})\n"
        "            if r.status_code == 503: time.sleep(float(r.headers['retry-after']))  # as clients should\n"
        "threads = [threading.Thread(target=run) for _ in range(n)]\n"
        "[t.start() for t in threads]; [t.join() for t in threads]\n"
    )
    load = subprocess.Popen([sys.executable, "-c", script, url, doc, ATTACK, str(searchers), str(seconds)])
    time.sleep(1.0)  # the crowd at full strength
    out: dict[str, list[float]] = {"viewport": [], "health": []}
    rng = np.random.default_rng(0)

    def pan() -> None:
        with httpx.Client(base_url=url, timeout=60) as c:
            while load.poll() is None:
                y = float(rng.uniform(0, 1.5e6))
                out["viewport"].append(
                    timed(c, f"/documents/{doc}/viewport", {"x0": 0, "y0": y, "x1": 1280, "y1": y + 800})
                )
                time.sleep(0.01)

    def health() -> None:
        with httpx.Client(base_url=url, timeout=60) as c:
            while load.poll() is None:
                out["health"].append(timed(c, "/health", {}))
                time.sleep(0.05)

    workers = [threading.Thread(target=pan), threading.Thread(target=health)]
    for w in workers:
        w.start()
    load.wait()
    for w in workers:
        w.join()
    return out


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) * 1e3


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.search_bench", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--rounds", type=int, default=15, help="requests per query (default 15)")
    parser.add_argument(
        "--seconds", type=float, default=15.0, help="how long the crowd searches (default 15)"
    )
    parser.add_argument(
        "--searchers", type=int, default=40, help="searches at once in the crowd (default 40)"
    )
    parser.add_argument(
        "--scale",
        type=int,
        default=100,
        help="copies of the report's text for the miss at scale (default 100)",
    )
    args = parser.parse_args(argv)
    data = Path(tempfile.mkdtemp(prefix="vantage-search-"))
    log(f"creating the demo documents in {data} ...")
    store = SQLiteStore(data)
    create_demos(store, data / "snapshots")
    docs = {d["name"]: (d["id"], d["items"]) for d in store.documents()}
    store.close()
    report, items = next(docs[n] for n in docs if "report" in n)
    text, text_s, build_s, per_item = index_cost(data, report)
    scaled_items, scaled_miss = miss_at_scale(text, args.scale, 5)
    server, url = launch(data, "--workers", "1")
    try:
        with httpx.Client(base_url=url, timeout=60) as c:
            path = f"/documents/{report}/search"
            timed(c, path, {"q": "warm"})
            times = {
                name: [timed(c, path, {"q": q}) for _ in range(args.rounds)] for name, q in QUERIES.items()
            }
            totals = {name: c.get(path, params={"q": q}).json()["total"] for name, q in QUERIES.items()}
        crowded = crowd(url, report, args.seconds, args.searchers)
    finally:
        stop(server, timeout=30)

    print(f"machine: {cpu_model()}; {versions(('numpy', 'fastapi', 'uvicorn'))}")
    print(f"`python -m benchmarks.search_bench --rounds {args.rounds} --seconds {args.seconds:g}`\n")
    print(f"The report: {items:,} items. Text index: {per_item:.1f} B/item; built in {text_s:.2f} s of the "
          f"snapshot's {build_s:.2f} s ({text_s / build_s:.0%}).\n")  # fmt: skip
    miss = statistics.median(times["one-word miss"])
    print("| query | hits in all | p50 ms | against a one-word miss |")
    print("|---|---:|---:|---:|")
    for name, samples in times.items():
        p50 = statistics.median(samples)
        print(f"| {name} | {totals[name]:,} | {p50 * 1e3:.1f} | {p50 / miss:.2f}x |")
    print(
        f"\nA miss over the text of {scaled_items / 1e6:.0f}M text items (the report's {args.scale} times over, "
        f"{len(text.text) * args.scale / 1e9:.2f} GB): {scaled_miss * 1e3:.0f} ms (median of 5; in this process, no HTTP)."
    )
    print(f"\nWith {args.searchers} attack queries at once for {args.seconds:g} s (a separate process):\n")
    print("| request | count | p50 ms | p99 ms |")
    print("|---|---:|---:|---:|")
    for name, samples in crowded.items():
        print(f"| {name} | {len(samples)} | {pct(samples, 50):.1f} | {pct(samples, 99):.1f} |")


if __name__ == "__main__":
    main()

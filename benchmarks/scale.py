"""How each cost grows with the document: the curve from 1e5 items up, on one host.

Per scene and size (seeded): the NDJSON is written, then

- imported with ``vantage import FILE --doc big --data-dir D`` in a process of its own, timed
  end to end, its peak private memory (``Private_Clean + Private_Dirty`` of
  ``/proc/PID/smaps_rollup``, its decoding processes' added, sampled every 20 ms or more, see
  ``sampled``) recorded;
- the store's bytes on disk (SQLite and snapshot files) per item;
- a server started on the store: its first answer after start-up (the document opened cold,
  from its snapshot file, with the page cache dropped first when this process may), then the
  p50 of viewport and diff requests over HTTP (one keep-alive connection, random full-HD
  screens at scale 1 and pans of a tenth of one), twice: the first pass reads what it reads
  for the first time since the start (from disk, and each block checked), the second again;
- 1,000 edits through the server (each a move of an item already there: the p50 of the
  PUT), then a compaction in a process of its own (``Document.compact``: what the
  server does in the background past its threshold), timed, with the part of it that held
  the document's writing turn (its writers wait for that part only) and its longest write
  (its rows are written a row a transaction, which locks no document: on SQLite, every
  writer waits for one at most), its peak private memory sampled as the import's is.

Scenes: ``board`` (uniform boxes of 1-50 units, ids ``i0``..., kind text, ~1,000 a screen) and
``report`` (the 2000-page report's pages, blocks, lines and words, as many pages as it takes).

    .venv/bin/python -m benchmarks.scale --sizes 1e5,1e6,1e7
    .venv/bin/python -m benchmarks.scale --sizes 1e5,1e6 --scenes board --requests 200

Prints a markdown table (and the machine). No test runs it; the numbers go in
docs/performance.md with the command.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from app.demo import ndjson_lines
from app.launch import launch, stop
from benchmarks.machine import cpu_model
from spatial import scenes

SCREEN = (1920.0, 1080.0)
EDITS = 1000
ENV = {**os.environ, "VANTAGE_MAX_ITEMS": str(10**9)}  # the scaled report passes 10M at 1e7


def board(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    boxes, _ = scenes.uniform(n, seed=seed)
    return boxes, np.full(n, scenes.KINDS.index("text"), np.uint8)


def report(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    pages = max(1, round(n / 506))  # the report has ~506 items a page
    return scenes.long_document(pages=pages, seed=seed)


SCENES = {"board": board, "report": report}


def private_bytes(pid: int) -> int:
    """The private memory of the process and of its children now (clean and dirty pages of
    their own: an import's decoding processes count), or 0 once gone."""
    total = 0
    for each in [pid, *_descendants(pid)]:
        try:
            text = Path(f"/proc/{each}/smaps_rollup").read_text()
        except OSError:
            continue
        total += 1024 * sum(int(line.split()[1]) for line in text.splitlines() if line.startswith("Private_"))
    return total


def _descendants(pid: int) -> list[int]:
    try:
        children = [
            int(c) for t in Path(f"/proc/{pid}/task").iterdir() for c in (t / "children").read_text().split()
        ]
    except OSError:
        return []
    return [d for c in children for d in (c, *_descendants(c))]


def timed_import(path: Path, data_dir: Path) -> tuple[float, int]:
    """``vantage import`` of ``path`` into a new store: (seconds, peak private bytes)."""
    command = ["-m", "app.cli", "import", str(path), "--doc", "big", "--data-dir", str(data_dir)]
    seconds, peak, _ = sampled(command, "the import")
    return seconds, peak


def sampled(command: list[str], what: str) -> tuple[float, int, str]:
    """Python running ``command`` in a process of its own: (seconds end to end, its peak
    private bytes, what it printed). Sampled every 20 ms, or, when a reading takes longer
    (``smaps_rollup`` walks the page tables: 50-77 ms at 8 GB), after three times as long as
    it took: the sampler takes at most a quarter of a core (every 20 ms took three quarters of
    one at 8 GB), and a phase that holds more memory, being longer, is sampled as often for
    its length."""
    started = time.perf_counter()
    process = subprocess.Popen(
        [sys.executable, *command], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=ENV
    )
    peak, done = [0], threading.Event()

    def sample() -> None:
        while not done.is_set():
            began = time.perf_counter()
            peak[0] = max(peak[0], private_bytes(process.pid))
            time.sleep(max(0.02, 3 * (time.perf_counter() - began)))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    out, err = process.communicate()
    done.set()
    sampler.join()
    if process.returncode:
        raise SystemExit(f"{what} failed ({process.returncode}):\n{err.decode()[-2000:]}")
    return time.perf_counter() - started, peak[0], out.decode()


def drop_page_cache() -> bool:
    """Whether the page cache could be dropped (as root, outside a locked-down container)."""
    try:
        os.sync()
        Path("/proc/sys/vm/drop_caches").write_text("3\n")
        return True
    except OSError:
        return False


def served(data_dir: Path, lo: np.ndarray, hi: np.ndarray, requests: int, seed: int) -> dict[str, float]:
    """First answer after start-up, then p50 of viewport and diff requests (screens between
    ``lo`` and ``hi``, the scene's bounds), then the p50 of 1,000 edits."""
    cold = drop_page_cache()
    process, url = launch(data_dir, env=ENV, output=subprocess.DEVNULL)
    try:
        with httpx.Client(base_url=url, timeout=600) as c:
            doc = c.get("/documents").json()[0]["id"]
            rng = np.random.default_rng(seed)
            corners = rng.uniform(lo, np.maximum(hi - SCREEN, lo + 1), (requests, 2))
            first = corners[0]
            t0 = time.perf_counter()
            c.get(f"/documents/{doc}/viewport", params=screen_at(first)).raise_for_status()
            first_ms = (time.perf_counter() - t0) * 1e3
            pans = corners + rng.uniform(-0.1, 0.1, corners.shape) * SCREEN
            views: list[list[float]] = [[], []]  # the first pass reads its pages for the first time
            diffs: list[list[float]] = [[], []]  # since the start; the second reads them again
            for again in (0, 1):
                for corner, pan in zip(corners, pans, strict=True):
                    t0 = time.perf_counter()
                    c.get(f"/documents/{doc}/viewport", params=screen_at(corner)).raise_for_status()
                    views[again].append(time.perf_counter() - t0)
                    frm, to = ",".join(map(str, _box(corner))), ",".join(map(str, _box(pan)))
                    t0 = time.perf_counter()
                    c.get(f"/documents/{doc}/diff", params={"from": frm, "to": to}).raise_for_status()
                    diffs[again].append(time.perf_counter() - t0)
            edits = []
            for k in range(EDITS):  # moves of items already there
                x, y = (float(v) for v in rng.uniform(lo, hi))
                t0 = time.perf_counter()
                c.put(
                    f"/documents/{doc}/items/i{k}", json={"x0": x, "y0": y, "x1": x + 10, "y1": y + 10}
                ).raise_for_status()
                edits.append(time.perf_counter() - t0)
    finally:
        stop(process)
    return {
        "cold": cold,
        "first_ms": first_ms,
        "viewport_ms": [statistics.median(v) * 1e3 for v in views],
        "diff_ms": [statistics.median(d) * 1e3 for d in diffs],
        "edit_ms": statistics.median(edits) * 1e3,
    }


def compaction(data_dir: Path) -> tuple[float, float, float, int]:
    """Fold the edits into a new base, as the server does past its threshold, in a process of
    its own: (seconds, seconds of them that the document's writers waited, the longest of its
    writes (on SQLite, any writer of any document may wait that long), peak private bytes of
    that process)."""
    _, peak, out = sampled(["-m", "benchmarks.scale", "--compact", str(data_dir)], "the compaction")
    seconds, waited, longest = map(float, out.split())
    return seconds, waited, longest, peak


def _compact(data_dir: Path) -> None:
    """The compaction ``compaction`` runs: the store opened, the document's edits folded; prints
    the seconds the fold took, those it held the document's writing turn (which its writers
    wait for), and its longest write (its rows' too, which lock no document)."""
    from app.registry import Registry
    from app.snapfile import SnapshotFiles
    from app.stores import SQLiteStore

    store = SQLiteStore(data_dir)
    held: list[float] = []
    writes: list[float] = [0.0]

    def timed(opening: Callable[[str], Any], into: list[float]) -> Callable[[str], Any]:
        @contextlib.contextmanager
        def opened(doc_id: str) -> Iterator[Any]:
            start = time.perf_counter()
            with opening(doc_id) as write:
                yield write
            into.append(time.perf_counter() - start)
            writes.append(into[-1])

        return opened

    store.writing = timed(store.writing, held)  # type: ignore[method-assign]
    store._unlocked = timed(store._unlocked, [])  # type: ignore[method-assign]
    try:
        registry = Registry(store, SnapshotFiles(data_dir / "snapshots"), 1 << 40)
        doc = registry[max(store.documents(), key=lambda d: d["items"])["id"]]  # the big one
        t0 = time.perf_counter()
        doc.compact()
        print(time.perf_counter() - t0, sum(held), max(writes))
    finally:
        store.close()


def _box(corner: np.ndarray) -> tuple[float, float, float, float]:
    return float(corner[0]), float(corner[1]), float(corner[0] + SCREEN[0]), float(corner[1] + SCREEN[1])


def screen_at(corner: np.ndarray) -> dict[str, float]:
    """A viewport request's parameters: a full-HD rectangle whose lowest corner is ``corner``."""
    return dict(zip(("x0", "y0", "x1", "y1"), _box(corner), strict=True))


def disk_bytes(directory: Path) -> int:
    return sum(p.stat().st_size for p in directory.rglob("*") if p.is_file())


def measure(scene: str, n: int, requests: int, seed: int, work: Path, keep: bool = False) -> dict[str, float]:
    boxes, kinds = SCENES[scene](n, seed)
    path, data = work / f"{scene}-{n}.ndjson", work / f"{scene}-{n}"
    with open(path, "wb") as out:
        out.writelines(ndjson_lines(boxes, kinds))
    count, lo, hi = len(boxes), boxes[:, :2].min(axis=0), boxes[:, 2:].max(axis=0)
    del boxes, kinds  # only the bounds from here: the import's memory is the machine's
    os.sync()  # on disk before the import starts, as a user's file is: its writeback is not the import's
    nbytes = path.stat().st_size
    seconds, peak = timed_import(path, data)
    path.unlink()
    row = {"items": count, "ndjson_b": nbytes / count, "import_s": seconds, "peak": peak}
    row["disk_b"] = disk_bytes(data) / count
    report(scene, row)
    row |= served(data, lo, hi, requests, seed)
    report(scene, row)
    row["compact_s"], row["compact_wait_s"], row["compact_write_s"], row["compact_peak"] = compaction(data)
    if not keep:
        shutil.rmtree(data)
    return row


def report(scene: str, row: dict) -> None:
    """What one size measured so far, on stderr: a run cut short (a process out of memory, say)
    keeps it."""
    print(f"{scene}: {row}", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.scale",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--sizes", default="1e5,1e6,1e7", help="item counts, comma-separated (1e5,1e6,1e7)")
    parser.add_argument("--scenes", default="board,report", help=f"of {', '.join(SCENES)}")
    parser.add_argument("--requests", type=int, default=500, help="viewport and diff requests per size")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--work", type=Path, default=None, help="scratch directory (default: a temporary one)"
    )
    parser.add_argument(
        "--keep", action="store_true", help="keep each size's store in --work, to look at afterwards"
    )
    parser.add_argument("--compact", type=Path, help=argparse.SUPPRESS)  # the compaction's own process
    args = parser.parse_args(argv)
    if args.compact:
        return _compact(args.compact)
    try:
        sizes = [int(float(s)) for s in args.sizes.split(",")]
    except ValueError:
        parser.error(f"--sizes {args.sizes!r}: counts separated by commas, such as 1e5,1e6")
    chosen = [s.strip() for s in args.scenes.split(",")]
    if not set(chosen) <= set(SCENES) or not sizes or min(sizes) < 1000:
        parser.error(f"--scenes takes {', '.join(SCENES)}; --sizes are counts of at least 1000")
    if args.keep and args.work is None:
        parser.error("--keep needs --work")
    if args.work is not None:
        try:
            args.work.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            parser.error(f"--work {args.work}: {error.strerror}")
    print(f"machine: {cpu_model()}, {os.cpu_count()} cores; python {sys.version.split()[0]}")
    print(
        "| scene | items | NDJSON B/item | import s | items/s | import peak private MB | B/item on disk | "
        "first answer ms | cache | viewport p50 ms, first read / again | diff p50 ms, first read / again | "
        "edit p50 ms | compaction after 1,000 edits s | its writers wait s | longest write s | "
        "compaction peak private MB |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    with (
        contextlib.nullcontext(args.work)
        if args.keep
        else tempfile.TemporaryDirectory(prefix="vantage-scale-", dir=args.work) as work
    ):
        for scene in chosen:
            for n in sizes:
                r = measure(scene, n, args.requests, args.seed, Path(work), args.keep)
                print(
                    f"| {scene} | {r['items']:,} | {r['ndjson_b']:.0f} | {r['import_s']:.1f} | "
                    f"{r['items'] / r['import_s']:,.0f} | {r['peak'] / 2**20:,.0f} | {r['disk_b']:.0f} | "
                    f"{r['first_ms']:.0f} | {'cold' if r['cold'] else 'warm'} | "
                    f"{r['viewport_ms'][0]:.2f} / {r['viewport_ms'][1]:.2f} | "
                    f"{r['diff_ms'][0]:.2f} / {r['diff_ms'][1]:.2f} | "
                    f"{r['edit_ms']:.2f} | {r['compact_s']:.1f} | {r['compact_wait_s']:.2f} | {r['compact_write_s']:.2f} | "
                    f"{r['compact_peak'] / 2**20:,.0f} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()

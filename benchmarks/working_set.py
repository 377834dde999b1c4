"""The working set: documents opened from mapped snapshot files, shared by worker processes, and
a store of many documents served within a memory budget.

Run from the repository root (a seeded plain script, not a test; needs ``wrk`` on the PATH;
about 10 minutes on 2 cores, ~10 GB of disk under ``--work``, deleted at the end)::

    python -m benchmarks.working_set | tee benchmarks/results/working_set.md
    python -m benchmarks.working_set --pages 200 --docs 10 --items 20000 --seconds 2 --opens 5

Four measurements, each a markdown table:

1. Open time of a 1M-item and a 100k-item document (``spatial.scenes.long_document``, bodies as
   an import makes them): from its snapshot file with the page cache warm, cold (the file
   evicted from the page cache with ``posix_fadvise(POSIX_FADV_DONTNEED)`` before each open),
   and rebuilt from the store (``read_items`` + ``build``); in-process, ``--opens`` each.
2. Memory with 2 workers and with 1 on the same store (the 1M document and three of 100k), once
   every worker opened every document: the workers' summed PSS (``/proc/PID/smaps_rollup``).
3. Throughput of the diff route (a 60-pixel pan of a 1920x1080 view) with 2 workers and with 1,
   under the same wrk load from a separate process (which shares the cores), rounds alternating.
4. Scale: ``--docs`` documents of ``--items`` items written straight to a store, then opened once
   each (building their files); start-up with them against an empty store; one worker with
   VANTAGE_CACHE_MB=300 visited by a client document by document (RSS sampled, evictions,
   cold-open latency at the client, every answer checked against brute force); hot answers on
   that server against a server holding just the one document.
"""

from __future__ import annotations

import argparse
import gc
import os
import platform
import resource
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np

from app.documents import Document
from app.items import Item, batch_of
from app.launch import launch, stop
from app.snapfile import SnapshotFiles
from app.snapshots import build
from app.stores import SQLiteStore
from app.table import ItemTable
from spatial import scenes

from .load import run_wrk, write_wrk_script
from .machine import cpu_model, versions
from .servers import rss_bytes

SCREEN = (1920.0, 1080.0)
PAN = 60.0  # pixels a diff pans the view by
LIMIT = 100_000  # the server's most items an answer: nothing is cut
ITEMS_PER_PAGE = 505  # about, in long_document
CACHE_MB = 300  # the budget of the scale server's worker
OPEN_TARGETS = {"1M": 0.200, "100k": 0.050}  # p50 open-time targets, seconds
PSS_TARGET, THROUGHPUT_TARGET = 1.3, 1.4
MB = 1 << 20


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


# -- documents ------------------------------------------------------------------------------


def scene(pages: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    return scenes.long_document(pages=pages, seed=seed)


def item_table(boxes: np.ndarray, kinds: np.ndarray) -> ItemTable:
    """The scene as an import stores it: ids ``i0``..., kind names, z 0 for pages, bodies encoded
    by ``app.items.batch_of`` (the import path)."""
    names = scenes.KINDS
    items = [
        Item(f"i{i}", x0, y0, x1, y1, names[k], 0 if k in (scenes.PAGE, scenes.FRAME) else 1)
        for i, ((x0, y0, x1, y1), k) in enumerate(zip(boxes.tolist(), kinds.tolist(), strict=True))
    ]
    batch = batch_of(items, max_data_bytes=0)
    return ItemTable.of(batch.ids, batch.boxes, batch.bodies)


def write_document(store: SQLiteStore, name: str, boxes: np.ndarray, kinds: np.ndarray) -> str:
    """A new document holding the scene, written straight to the store (no snapshot file yet)."""
    doc = store.create_document(name)["id"]
    store.write_items(doc, item_table(boxes, kinds))
    return doc


def open_document(store: SQLiteStore, files: SnapshotFiles, doc: str) -> Document:
    """A whole document opened as a worker opens it: its base mapped (or built and saved)."""
    return Document(store, files, store.document(doc))


def snapshot_file(store: SQLiteStore, files: SnapshotFiles, doc: str) -> Path:
    """The file of the document's base, as the store names it."""
    return files.path(doc, store.document(doc)["base_id"])


def evict_from_page_cache(path: Path) -> int:
    """Drop the file's pages from the page cache; the bytes still resident after (fincore)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)
    fincore = shutil.which("fincore")
    if fincore is None:
        return -1
    out = subprocess.run(
        [fincore, "--bytes", "--raw", "--noheadings", "-o", "RES", str(path)], capture_output=True, text=True
    )
    return int(out.stdout.split()[0]) if out.returncode == 0 and out.stdout.strip() else -1


def mapped_here() -> int:
    """Snapshot files this process maps (none may be while servers' PSS is read)."""
    with open("/proc/self/maps") as maps:
        return sum(".vsnap" in line for line in maps)


def random_views(boxes: np.ndarray, count: int, seed: int, dy: float = 0.0) -> list[tuple]:
    """``count`` seeded 1920x1080 views of the page column, somewhere down the document."""
    rng = np.random.default_rng(seed)
    x0 = scenes.PAGE_WIDTH / 2 - SCREEN[0] / 2
    bottom = float(boxes[:, 3].max())
    ys = rng.uniform(0, max(1.0, bottom - SCREEN[1] - dy), count)
    return [(x0, float(y), x0 + SCREEN[0], float(y) + SCREEN[1]) for y in ys]


def truth(boxes: np.ndarray, rect: tuple) -> set[str]:
    """Ids of the items touching ``rect`` (closed intervals), by brute force (tests/oracle.py)."""
    x0, y0, x1, y1 = rect
    hit = (boxes[:, 0] <= x1) & (boxes[:, 2] >= x0) & (boxes[:, 1] <= y1) & (boxes[:, 3] >= y0)
    return {f"i{i}" for i in np.flatnonzero(hit).tolist()}


# -- numbers --------------------------------------------------------------------------------


def pct(samples: list[float], q: float) -> float:
    return float(np.percentile(samples, q))


def ms(seconds: float) -> str:
    return f"{seconds * 1e3:.1f} ms" if seconds < 10 else f"{seconds:.1f} s"


def mib(n: float) -> str:
    return f"{n / MB:,.0f} MiB"


def verdict(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


def timed(fn: Callable[[], object]) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


# -- servers --------------------------------------------------------------------------------


@contextmanager
def serving(
    data_dir: Path, workers: int, log_dir: Path, env: dict[str, str] | None = None
) -> Iterator[tuple[subprocess.Popen, str]]:
    """``vantage serve --workers N`` on a free loopback port; stopped (by its pid) on leaving."""
    log_dir.mkdir(parents=True, exist_ok=True)
    log_path = log_dir / f"server-{time.monotonic_ns()}.log"
    with open(log_path, "w") as output:
        try:
            process, url = launch(data_dir, "--workers", str(workers), env=env, output=output)
        except RuntimeError as error:
            raise RuntimeError(f"{error}\n{log_path.read_text()[-3000:]}") from None
        try:
            yield process, url
        finally:
            stop(process, timeout=30)


def fresh_get(url: str, path: str, **params: object) -> httpx.Response:
    """A request on a new connection: any worker may take it."""
    with httpx.Client(timeout=120.0) as fresh:
        return fresh.get(url + path, params=params).raise_for_status()


def children(pid: int) -> set[int]:
    found: set[int] = set()
    for task in Path(f"/proc/{pid}/task").iterdir():
        found |= {int(c) for c in (task / "children").read_text().split()}
    return found


def pss(pid: int) -> tuple[int, int]:
    """``(Pss, Pss_File)`` of a process in bytes, from /proc/PID/smaps_rollup."""
    fields = {}
    with open(f"/proc/{pid}/smaps_rollup") as f:
        for line in f:
            name, _, rest = line.partition(":")
            if name in ("Pss", "Pss_File"):
                fields[name] = int(rest.split()[0]) * 1024
    return fields["Pss"], fields.get("Pss_File", 0)


def worker_stats(url: str, workers: int, deadline: float) -> dict[int, dict]:
    """Each worker's /stats, asked on fresh connections until all ``workers`` answered."""
    seen: dict[int, dict] = {}
    while len(seen) < workers:
        if time.monotonic() > deadline:
            raise RuntimeError(f"only workers {sorted(seen)} answered /stats, {workers} expected")
        with ThreadPoolExecutor(4) as pool:
            for stats in pool.map(lambda _: fresh_get(url, "/stats").json(), range(8)):
                seen[stats["worker"]] = stats
    return seen


def open_everywhere(
    url: str, docs: dict[str, np.ndarray], workers: int, timeout: float = 120.0
) -> dict[int, dict]:
    """Viewport requests on fresh connections (concurrent, so no one worker takes them all)
    until every worker's /stats shows every document open; each worker's last /stats."""
    deadline = time.monotonic() + timeout
    views = {doc: random_views(boxes, 1, seed=7)[0] for doc, boxes in docs.items()}

    def visit(doc: str) -> None:
        x0, y0, x1, y1 = views[doc]
        fresh_get(url, f"/documents/{doc}/viewport", x0=x0, y0=y0, x1=x1, y1=y1, limit=10)

    while True:
        seen: dict[int, dict] = {}
        for _ in range(6):
            seen.update(worker_stats(url, workers, deadline))
        if len(seen) == workers and all(s["open"] == len(docs) for s in seen.values()):
            return seen
        if time.monotonic() > deadline:
            raise RuntimeError(f"not every worker opened every document: {seen}")
        with ThreadPoolExecutor(4) as pool:
            list(pool.map(visit, [doc for doc in docs for _ in range(2 * workers)]))


# -- 1. open time ---------------------------------------------------------------------------


def measure_open_times(data_dir: Path, docs: dict[str, tuple[str, np.ndarray]], opens: int) -> list[str]:
    """Warm and cold opens from the snapshot file, and rebuilds from the store, interleaved."""
    store, files = SQLiteStore(data_dir), SnapshotFiles(data_dir / "snapshots")
    rows, left_resident = [], 0
    for label, (doc, boxes) in docs.items():
        path = snapshot_file(store, files, doc)
        meta = store.document(doc)
        warm, cold, rebuilt = [], [], []
        for k in range(opens):
            left_resident = max(left_resident, evict_from_page_cache(path))
            cold.append(timed(lambda: open_document(store, files, doc)))
            gc.collect()  # the mapping goes with the document
            warm.append(timed(lambda: open_document(store, files, doc)))
            gc.collect()
            rebuilt.append(timed(lambda: build(store.read_items(doc), meta["version"], meta["base_id"])))
            gc.collect()
            log(f"open {label}: {k + 1}/{opens}")
        target = OPEN_TARGETS.get(label)
        p50 = {"warm": statistics.median(warm), "cold": statistics.median(cold)}
        rows.append(
            f"| {label} ({len(boxes):,} items, file {mib(path.stat().st_size)}) "
            f"| {ms(p50['warm'])} / {ms(pct(warm, 99))} "
            f"| {ms(p50['cold'])} / {ms(pct(cold, 99))} "
            f"| {ms(statistics.median(rebuilt))} / {ms(pct(rebuilt, 99))} "
            f"| {statistics.median(rebuilt) / p50['warm']:.0f}x / {statistics.median(rebuilt) / p50['cold']:.1f}x "
            f"| {ms(target) if target else '-'}: warm {verdict(p50['warm'] <= target) if target else '-'}, "
            f"cold {verdict(p50['cold'] <= target) if target else '-'} |"
        )
    store.close()
    gc.collect()
    return [
        f"## 1. Open time ({opens} opens each, in-process)",
        "",
        "Open: `Document(store, files, meta)` as a worker opens one (the file's header read and its "
        "sums checked, the rest mapped, the tree and overview taken as they are). Warm: the file in the page cache. Cold: "
        "the file evicted from the page cache with `os.posix_fadvise(fd, 0, 0, POSIX_FADV_DONTNEED)` "
        "just before each open"
        + (f" (fincore: at most {mib(left_resident)} left resident after it)" if left_resident >= 0 else "")
        + ". Rebuild: `build(store.read_items(doc))` with SQLite warm, what opening cost before snapshot files.",
        "",
        "| document | warm p50 / p99 | cold p50 / p99 | rebuild p50 / p99 | rebuild ÷ warm / ÷ cold (p50) | target (p50) |",
        "|---|---|---|---|---|---|",
        *rows,
        "",
    ]


# -- 2. and 3. workers: memory and throughput -----------------------------------------------


def measure_memory(
    data_dir: Path, docs: dict[str, np.ndarray], tiny: dict[str, np.ndarray], log_dir: Path
) -> list[str]:
    """Summed PSS of the workers: idle, after a first answer (``tiny``, a few items: the compiled
    code loaded), and once each opened every document; 2 workers, then 1 (one server at a time)."""
    if mapped_here():
        raise RuntimeError("this process still maps snapshot files: the servers' PSS would be off")
    results = {}
    for workers in (2, 1):
        with serving(data_dir, workers, log_dir, {"VANTAGE_CACHE_MB": "4000"}) as (process, url):
            pids = sorted(worker_stats(url, workers, time.monotonic() + 60))
            if workers > 1 and not set(pids) <= children(process.pid):
                raise RuntimeError(
                    f"workers {pids} are not the supervisor's children {children(process.pid)}"
                )
            phases = [[pss(p) for p in pids]]
            open_everywhere(url, tiny, workers)
            phases.append([pss(p) for p in pids])
            stats = open_everywhere(url, {**tiny, **docs}, workers)
            time.sleep(0.5)
            phases.append([pss(p) for p in pids])
            results[workers] = ([sum(p[0] for p in phase) for phase in phases], phases[-1], stats)
            log(f"memory, {workers} worker(s): PSS {[mib(p[0]) for p in phases[-1]]}")
    rows = []
    for workers, (sums, last, stats) in results.items():
        held = sum(s["held_bytes"] for s in stats.values()) / len(stats)
        rows.append(
            f"| {workers} | {', '.join(map(str, sorted(stats)))} | {' | '.join(mib(t) for t in sums)} "
            f"| {mib(sum(p[1] for p in last))} | {mib(sums[2] - sums[1])} | {mib(held)} |"
        )
    total = {w: r[0][2] for w, r in results.items()}
    grown = {w: r[0][2] - r[0][1] for w, r in results.items()}
    ratio = total[2] / total[1]
    return [
        f"## 2. Memory: 2 workers against 1 ({len(docs)} documents, "
        f"{sum(len(b) for b in docs.values()):,} items, every worker holding every one)",
        "",
        "PSS from `/proc/PID/smaps_rollup` of each worker (the pids `/stats` names; with 2 workers "
        "the supervisor's children, which are checked), summed over the workers. Idle: before any "
        f"request; first answer: once every worker answered on a {len(next(iter(tiny.values())))}-item "
        "document (the compiled code loaded); all open: once every worker's `/stats` showed every "
        "document open (viewport requests on fresh connections). One server up at a time.",
        "",
        "| workers | pids | PSS idle | PSS after a first answer | PSS all open | of which file-backed "
        "| growth from opening the documents | held_bytes per worker |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        f"**Summed PSS, 2 workers ÷ 1: {ratio:.2f}x** (target <= {PSS_TARGET}x: {verdict(ratio <= PSS_TARGET)}); "
        f"the growth from opening the documents, 2 ÷ 1: {grown[2] / grown[1]:.2f}x; the rest is each "
        "worker's own interpreter, libraries and compiled code.",
        "",
    ]


def diff_paths(doc: str, boxes: np.ndarray, threads: int, per_thread: int, seed: int) -> list[list[str]]:
    """Per wrk thread, seeded 60-pixel pans (down) of a 1920x1080 view at scale 1 on the document."""
    out = []
    for t in range(threads):
        paths = []
        for x0, y0, x1, y1 in random_views(boxes, per_thread, seed=seed + t, dy=PAN):
            old, new = f"{x0!r},{y0!r},{x1!r},{y1!r}", f"{x0!r},{y0 + PAN!r},{x1!r},{y1 + PAN!r}"
            paths.append(f"/documents/{doc}/diff?from={old}&to={new}&scale=1.0&min_px=1&limit={LIMIT}")
        out.append(paths)
    return out


def cpu_seconds(pids: list[int]) -> float:
    """User + system CPU seconds of processes so far (/proc/PID/stat)."""
    total = 0
    for pid in pids:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        total += int(fields[11]) + int(fields[12])  # utime, stime
    return total / os.sysconf("SC_CLK_TCK")


def machine_busy() -> float:
    """CPU seconds the whole machine spent busy so far (/proc/stat: all but idle and iowait)."""
    with open("/proc/stat") as f:
        ticks = [int(v) for v in f.readline().split()[1:9]]
    return (sum(ticks) - ticks[3] - ticks[4]) / os.sysconf("SC_CLK_TCK")


def loaded_round(url: str, pids: list[int], script: Path, args: argparse.Namespace, what: str) -> dict:
    """One wrk run, and the cores the server, wrk and every other process used meanwhile."""
    before = (
        cpu_seconds(pids),
        machine_busy(),
        resource.getrusage(resource.RUSAGE_CHILDREN),
        time.perf_counter(),
    )
    result = run_wrk(url, script, args.connections, 2, args.seconds, what)
    after = (
        cpu_seconds(pids),
        machine_busy(),
        resource.getrusage(resource.RUSAGE_CHILDREN),
        time.perf_counter(),
    )
    wall = after[3] - before[3]
    server = (after[0] - before[0]) / wall
    wrk = (after[2].ru_utime + after[2].ru_stime - before[2].ru_utime - before[2].ru_stime) / wall
    busy = (after[1] - before[1]) / wall
    return {"result": result, "server": server, "wrk": wrk, "others": max(0.0, busy - server - wrk)}


def measure_throughput(
    data_dir: Path, docs: dict[str, np.ndarray], doc: str, args: argparse.Namespace, log_dir: Path
) -> list[str]:
    """The same wrk load on a 1-worker and a 2-worker server, rounds alternating; req/s medians."""
    script = write_wrk_script(log_dir / "wrk", "diff", diff_paths(doc, docs[doc], 2, 2000, args.seed))
    runs: dict[int, list[dict]] = {1: [], 2: []}
    env = {"VANTAGE_CACHE_MB": "4000"}
    with serving(data_dir, 1, log_dir, env) as (p1, url1), serving(data_dir, 2, log_dir, env) as (p2, url2):
        servers = {1: (url1, [p1.pid]), 2: (url2, [p2.pid, *children(p2.pid)])}
        for workers, (url, _) in servers.items():
            open_everywhere(url, {doc: docs[doc]}, workers)
            run_wrk(url, script, args.connections, 2, 2, f"warm-up, {workers} worker(s)")
        for r in range(args.rounds):
            for workers in (1, 2) if r % 2 == 0 else (2, 1):
                url, pids = servers[workers]
                run = loaded_round(url, pids, script, args, f"{workers} worker(s)")
                runs[workers].append(run)
                log(
                    f"throughput round {r + 1}, {workers} worker(s): {run['result'].rps:,.0f} req/s, "
                    f"cores: server {run['server']:.2f}, wrk {run['wrk']:.2f}, others {run['others']:.2f}"
                )

    def median(rs: list[dict], key: str) -> float:
        return statistics.median(r[key] for r in rs)

    rps = {w: statistics.median(r["result"].rps for r in rs) for w, rs in runs.items()}
    rows = [
        f"| {w} | {rps[w]:,.0f} | {', '.join(format(r['result'].rps, ',.0f') for r in rs)} "
        f"| {statistics.median(r['result'].p50_us for r in rs) / 1e3:.1f} ms "
        f"| {statistics.median(r['result'].p99_us for r in rs) / 1e3:.1f} ms "
        f"| {median(rs, 'server'):.2f} | {median(rs, 'wrk'):.2f} | {median(rs, 'others'):.2f} |"
        for w, rs in runs.items()
    ]
    ratio = rps[2] / rps[1]
    paired = statistics.median(
        b["result"].rps / a["result"].rps for a, b in zip(runs[1], runs[2], strict=True)
    )
    return [
        f"## 3. Throughput: the diff route, 2 workers against 1 ({len(docs[doc]):,}-item document)",
        "",
        f"`GET /documents/{{doc}}/diff?from=..&to=..&scale=1.0&min_px=1`: a {PAN:g}-pixel pan of a "
        f"1920x1080 view, 4,000 seeded places; `wrk -t2 -c{args.connections} -d{args.seconds:g}s`, "
        f"{args.rounds} rounds alternating the servers (both up, one loaded at a time). wrk runs on "
        "the same 2 cores as the server, and so does whatever else this shared machine runs: the "
        "cores columns (medians; 1.00 is one core flat out) say what each used during the rounds.",
        "",
        "| workers | req/s (median) | each round | latency p50 | latency p99 | server cores | wrk cores "
        "| other processes' cores |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        f"**2 workers ÷ 1: {ratio:.2f}x req/s** (target >= {THROUGHPUT_TARGET}x: {verdict(ratio >= THROUGHPUT_TARGET)}); "
        f"the median of each round's ratio: {paired:.2f}x",
        "",
    ]


# -- 4. scale -------------------------------------------------------------------------------


def build_library(data_dir: Path, count: int, pages: int) -> tuple[list[str], list[float], float]:
    """``count`` documents written straight to a store, then each opened once (building and
    saving its snapshot file); (ids, first-open seconds, seconds spent writing the store)."""
    store, files = SQLiteStore(data_dir), SnapshotFiles(data_dir / "snapshots")
    ids, t0 = [], time.perf_counter()
    for k in range(count):
        ids.append(write_document(store, f"doc {k}", *scene(pages, seed=1000 + k)))
        if (k + 1) % 20 == 0:
            log(f"library: {k + 1}/{count} written")
    written = time.perf_counter() - t0
    first_opens = []
    for k, doc in enumerate(ids):
        first_opens.append(timed(lambda d=doc: open_document(store, files, d)))
        gc.collect()
        if (k + 1) % 20 == 0:
            log(f"library: {k + 1}/{count} opened once")
    store.close()
    return ids, first_opens, written


def startup_seconds(data_dir: Path, log_dir: Path) -> float:
    """From starting ``vantage serve`` (1 worker) to its first answered /health."""
    t0 = time.perf_counter()
    with serving(data_dir, 1, log_dir):
        return time.perf_counter() - t0


def sample_rss(pid: int, stop: threading.Event, samples: list[int]) -> None:
    while not stop.is_set():
        samples.append(rss_bytes(pid))
        stop.wait(0.02)


def viewport(client: httpx.Client, doc: str, rect: tuple) -> tuple[float, dict]:
    params = dict(zip(("x0", "y0", "x1", "y1"), rect, strict=True)) | {"limit": LIMIT}
    t0 = time.perf_counter()
    answer = client.get(f"/documents/{doc}/viewport", params=params).raise_for_status().json()
    return time.perf_counter() - t0, answer


def visit_library(
    url: str, pid: int, ids: list[str], pages: int, views: int, passes: int
) -> tuple[list[list[float]], list[float], list[int], int, int, dict]:
    """A client visits each document in turn (``views`` viewports each, ``passes`` times), the
    server's RSS sampled meanwhile; (each pass's first-request latencies, the other requests'
    latencies, RSS samples, answers checked, mismatches, final /stats)."""
    cold: list[list[float]] = [[] for _ in range(passes)]
    warm, samples, checked, wrong = [], [], 0, 0
    stop = threading.Event()
    sampler = threading.Thread(target=sample_rss, args=(pid, stop, samples), daemon=True)
    sampler.start()
    try:
        with httpx.Client(base_url=url, timeout=120.0) as client:
            for p in range(passes):
                for k, doc in enumerate(ids):
                    boxes = scene(pages, seed=1000 + k)[0]
                    for v, rect in enumerate(random_views(boxes, views, seed=p * 100_000 + k)):
                        seconds, answer = viewport(client, doc, rect)
                        (cold[p] if v == 0 else warm).append(seconds)
                        checked += 1
                        got = {e["id"] for e in answer["items"]}
                        wrong += got != truth(boxes, rect) or answer["truncated"]
                log(f"visit pass {p + 1}/{passes} done")
            stats = client.get("/stats").json()
    finally:
        stop.set()
        sampler.join()
    return cold, warm, samples, checked, wrong, stats


def hot_latencies(url: str, doc: str, boxes: np.ndarray, requests: int, seed: int) -> tuple[list[float], int]:
    """``requests`` viewports of one open document on one connection; (latencies, mismatches)."""
    rects = random_views(boxes, 50, seed=seed)
    out, wrong = [], 0
    with httpx.Client(base_url=url, timeout=120.0) as client:
        for i in range(requests):
            seconds, answer = viewport(client, doc, rects[i % len(rects)])
            out.append(seconds)
            if i < len(rects):
                wrong += {e["id"] for e in answer["items"]} != truth(boxes, rects[i])
    return out, wrong


def measure_scale(work: Path, args: argparse.Namespace, log_dir: Path) -> list[str]:
    pages = max(1, round(args.items / ITEMS_PER_PAGE))
    library, empty, single = work / "library", work / "empty", work / "single"
    try:
        ids, first_opens, written = build_library(library, args.docs, pages)
        snapshot_files = list((library / "snapshots").glob("*.vsnap"))
        files_bytes = sum(f.stat().st_size for f in snapshot_files)
        store_bytes = sum(f.stat().st_size for f in library.glob("vantage.sqlite3*"))
        store = SQLiteStore(library)
        total_items = sum(d["items"] for d in store.documents())
        store.close()

        # start-up: the library against an empty store, alternating
        SQLiteStore(empty).close()
        starts: dict[str, list[float]] = {"library": [], "empty": []}
        for _ in range(args.starts):
            starts["library"].append(startup_seconds(library, log_dir))
            starts["empty"].append(startup_seconds(empty, log_dir))
        log(f"start-up: {starts}")

        # one document alone in a store of its own, opened once (its file built)
        last = len(ids) - 1
        boxes = scene(pages, seed=1000 + last)[0]
        store = SQLiteStore(single)
        alone = write_document(store, "alone", *scene(pages, seed=1000 + last))
        open_document(store, SnapshotFiles(single / "snapshots"), alone)
        store.close()
        gc.collect()

        env = {"VANTAGE_CACHE_MB": str(CACHE_MB)}
        with (
            serving(library, 1, log_dir, env) as (process, url),
            serving(single, 1, log_dir, env) as (_, url1),
        ):
            for path in (library / "snapshots").glob("*.vsnap"):  # the first visit reads from disk
                evict_from_page_cache(path)
            idle_rss = rss_bytes(process.pid)
            cold, warm, samples, checked, wrong, stats = visit_library(
                url, process.pid, ids, pages, args.views, args.passes
            )
            final_rss = rss_bytes(process.pid)
            # hot answers: the last document visited is open; blocks alternate between servers
            hot: dict[str, list[float]] = {"library": [], "single": []}
            hot_wrong = 0
            for b in range(5):
                for name, u, d in (("library", url, ids[last]), ("single", url1, alone)):
                    lat, bad = hot_latencies(u, d, boxes, args.hot // 5, seed=b)
                    hot[name] += lat
                    hot_wrong += bad
            final_stats = httpx.get(f"{url}/stats").json()
        if final_stats["evictions"] != stats["evictions"]:
            log("note: evictions during the hot phase")
    finally:
        for directory in (library, empty, single):
            shutil.rmtree(directory, ignore_errors=True)
        log("scale: stores deleted")

    start_ratio = statistics.median(starts["library"]) / statistics.median(starts["empty"])
    hot_ratio = statistics.median(hot["library"]) / statistics.median(hot["single"])
    mismatches = wrong + hot_wrong
    n_checked = checked + 5 * 50
    return [
        f"## 4. Scale: {len(ids)} documents, {total_items:,} items",
        "",
        f"`long_document({pages}, seed=1000+k)` each, written straight to the store "
        f"({written:.0f} s, store {mib(store_bytes)}), then opened once in-process to build its "
        f"snapshot file: {len(snapshot_files)} files for {len(ids)} documents, {mib(files_bytes)} in all.",
        "",
        "| measurement | value |",
        "|---|---|",
        f"| first open with build (file written), p50 / p99 | {ms(statistics.median(first_opens))} / "
        f"{ms(pct(first_opens, 99))} ({ms(sum(first_opens))} for all) |",
        f"| start-up to first /health, {len(ids)} documents (median of {args.starts}) | "
        f"{ms(statistics.median(starts['library']))} |",
        f"| start-up to first /health, empty store (median of {args.starts}) | {ms(statistics.median(starts['empty']))} |",
        f"| **start-up ratio, {len(ids)} documents ÷ empty** | **{start_ratio:.2f}x** |",
        f"| RSS, 1 worker, VANTAGE_CACHE_MB={CACHE_MB}: idle / max / final "
        f"({len(samples)} samples every 20 ms) | {mib(idle_rss)} / {mib(max(samples))} / {mib(final_rss)} |",
        f"| /stats after {args.passes} passes of {len(ids)} documents: opens / evictions / open / held "
        f"| {stats['opens']} / {stats['evictions']} / {stats['open']} / {mib(stats['held_bytes'])} |",
        *(
            f"| cold open at the client, pass {p + 1}: first request to a document "
            + ("never opened, its file evicted from the page cache" if p == 0 else "closed since (evicted)")
            + f", p50 / p99 over {len(c)} | {ms(statistics.median(c))} / {ms(pct(c, 99))} |"
            for p, c in enumerate(cold)
        ),
        f"| next requests to that document, p50 / p99 over {len(warm)} | {ms(statistics.median(warm))} / "
        f"{ms(pct(warm, 99))} |",
        f"| hot answers, this server, p50 / p99 over {len(hot['library'])} | "
        f"{ms(statistics.median(hot['library']))} / {ms(pct(hot['library'], 99))} |",
        f"| hot answers, a server holding only that document, p50 / p99 | "
        f"{ms(statistics.median(hot['single']))} / {ms(pct(hot['single'], 99))} |",
        f"| **hot p50 ratio, {len(ids)}-document server ÷ 1-document server** | **{hot_ratio:.2f}x** |",
        f"| **answers checked against brute force / mismatches** | **{n_checked:,} / {mismatches}** "
        f"({verdict(mismatches == 0)}) |",
        "",
        f"Latencies are at the client (httpx, one connection, requests one after another); a "
        f"viewport is 1920x1080 with no level of detail, so every item touching it is in the "
        f"answer. The scale stores ({mib(store_bytes + files_bytes)}) were deleted at the end.",
        "",
    ]


# -- main -----------------------------------------------------------------------------------


def header(args: argparse.Namespace) -> list[str]:
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    command = shlex.join(["python", "-m", "benchmarks.working_set", *sys.argv[1:]])
    return [
        "# Working set: snapshot files, workers, many documents",
        "",
        f"- command: `{command}` (seed {args.seed})",
        f"- machine: {cpu_model()}, {os.cpu_count()} cores, {mem / 2**30:.0f} GiB, "
        f"Linux {platform.release()}; load average at start {os.getloadavg()[0]:.2f} "
        "(shared with a test run)",
        f"- Python {platform.python_version()}; {versions(('numpy', 'numba', 'fastapi', 'uvicorn', 'httpx'))}; "
        f"{subprocess.run(['wrk', '--version'], capture_output=True, text=True).stdout.splitlines()[0][:40]}",
        f"- date: {time.strftime('%Y-%m-%d %H:%M %Z')}",
        "",
    ]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--pages", type=int, default=2000, help="pages of the large document (2000: ~1M items)"
    )
    parser.add_argument("--opens", type=int, default=20, help="opens of each kind for the open times")
    parser.add_argument("--seconds", type=float, default=10.0, help="seconds of each wrk round")
    parser.add_argument("--rounds", type=int, default=5, help="wrk rounds per server")
    parser.add_argument("--connections", type=int, default=32, help="wrk connections")
    parser.add_argument("--docs", type=int, default=200, help="documents in the scale store")
    parser.add_argument("--items", type=int, default=100_000, help="items per document of the scale store")
    parser.add_argument("--starts", type=int, default=5, help="server starts per store for the start-up time")
    parser.add_argument("--views", type=int, default=3, help="viewport requests per document visited")
    parser.add_argument("--passes", type=int, default=2, help="passes over the scale store's documents")
    parser.add_argument("--hot", type=int, default=500, help="hot viewport requests per server")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--work", type=Path, default=None, help="scratch directory (default: a new one in /tmp)"
    )
    parser.add_argument("--out", type=Path, default=None, help="also write the report here")
    args = parser.parse_args(argv)
    if shutil.which("wrk") is None:
        parser.exit(2, "wrk is not on the PATH (apt-get install wrk)\n")

    work = Path(tempfile.mkdtemp(prefix="vantage-working-set-", dir=args.work))
    log_dir = work / "logs"
    report = header(args)
    started = time.perf_counter()
    try:
        data = work / "four"
        store = SQLiteStore(data)
        big = scene(args.pages, seed=1)[0]
        docs = {write_document(store, "large", *scene(args.pages, seed=1)): big}
        for k in range(3):
            boxes, kinds = scene(200, seed=2 + k)
            docs[write_document(store, f"small {k}", boxes, kinds)] = boxes
        boxes, kinds = scene(1, seed=9)
        tiny = {write_document(store, "warm-up", boxes, kinds): boxes}  # a first answer, for memory
        files = SnapshotFiles(data / "snapshots")
        for doc in [*docs, *tiny]:
            open_document(store, files, doc)  # builds the file, as a first open does
        store.close()
        del files
        gc.collect()
        large, small = list(docs)[:2]
        big_label = "1M" if args.pages == 2000 else f"{args.pages} pages"
        log("documents written")

        for measure in (
            lambda: measure_open_times(
                data, {big_label: (large, docs[large]), "100k": (small, docs[small])}, args.opens
            ),
            lambda: measure_memory(data, docs, tiny, log_dir),
            lambda: measure_throughput(data, docs, large, args, log_dir),
            lambda: measure_scale(work, args, log_dir),
        ):
            lines = measure()
            log("\n".join(lines))
            report += lines
    finally:
        shutil.rmtree(work, ignore_errors=True)
    report += [f"Total run time: {time.perf_counter() - started:.0f} s.", ""]
    text = "\n".join(report)
    print("\n\n" + text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)


if __name__ == "__main__":
    main()

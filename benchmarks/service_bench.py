"""The Vantage HTTP service side by side with the server a user would write instead, and the floor.

Run from the repository root (a seeded plain script, not a test; needs ``wrk`` on the PATH)::

    python -m benchmarks.service_bench                                # 1M-item document (minutes)
    python -m benchmarks.service_bench --scale 0.05 --seconds 3 --rounds 1 --out /tmp/service.md

One scene is written once as NDJSON, imported into a spawned Vantage server (timed, after an
untimed small first import; streamed from disk), loaded by the reference server
(benchmarks/reference_server.py: FastAPI + shapely STRtree + orjson) and into PostGIS
(benchmarks/postgis_server.py: a GiST-indexed table on a PostgreSQL server of its own, from
tests/postgres.py; timed). After a correctness check against brute force, every mode gets the
same panning load from a separate process, ``--panners`` concurrent panners each on its own
seeded path: wrk with a generated Lua script for HTTP, benchmarks/stream_load.py for the
WebSocket stream. Modes run for ``--seconds`` each, all modes once per round, ``--rounds``
rounds, so a noisy neighbour hits every mode alike; the tables give medians over rounds.

Modes: reference full viewport, PostGIS full viewport, Vantage full viewport (/viewport),
Vantage diff (/diff from the previous viewport to the current one), Vantage stream (WebSocket),
and a bare ASGI hello-world (benchmarks/hello_server.py): what uvicorn and the loopback cost
with no work at all, on uvicorn's own HTTP protocol (the floor) and again on Vantage's
(app/protocol.py, a response's head and body in one socket write). PostGIS runs when Debian's
PostgreSQL and PostGIS packages are installed
(``apt-get install postgresql postgresql-15-postgis-3``, the PostgreSQL major version
matching); otherwise, or with ``--no-postgis``, the report says it was skipped and why.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import resource
import shlex
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import zlib
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import httpx
import numpy as np
from websockets.sync.client import connect

from app.demo import ndjson_lines
from app.protocol import UVICORN_HTTP
from spatial import Rect, scenes

from .load import LoadResult, interleave, run_stream, run_wrk, write_wrk_script
from .machine import cpu_model, versions
from .servers import VANTAGE_HTTP, Server, vantage_server

try:
    from tqdm import tqdm
except ImportError:  # progress then goes to stderr as plain lines
    tqdm = None

LIMIT = 100_000  # item cap sent with every query: the server's maximum, so nothing is cut
CHECKS = 20  # viewports compared with brute force (and both servers) before timing
WARMUP_QUERIES = 5  # untimed viewport + diff queries after the restart, before the steady RSS
PAN_LIMIT = 200.0  # a step is a pure pan if the viewport kept its size and moved less than this
FULL_N = 1_000_000  # the item count the import and RSS targets are stated for
MB = 1e6


@dataclass(frozen=True)
class Mode:
    key: str
    label: str
    server: str  # "reference", "postgis", "vantage", "hello" or "hello_corked"


MODES = [
    Mode("reference", "reference: full viewport", "reference"),
    Mode("postgis", "postgis: full viewport", "postgis"),
    Mode("viewport", "vantage: full viewport", "vantage"),
    Mode("diff", "vantage: diff", "vantage"),
    Mode("stream", "vantage: stream (WebSocket)", "vantage"),
    Mode("diff_gzip", "vantage: diff, gzip", "vantage"),
    Mode("stream_deflate", "vantage: stream, permessage-deflate", "vantage"),
    Mode("hello", "hello-world (floor)", "hello"),
    # The floor again on Vantage's own HTTP protocol (app/protocol.py): head and body in one write.
    Mode("hello_corked", "hello-world, one write a response", "hello_corked"),
]
GZIP = {"Accept-Encoding": "gzip"}  # what browsers send; the server answers gzip level 1 past 1 kB


@dataclass
class Run:
    """One mode's load run, with the CPU its server and its load generator used meanwhile."""

    load: LoadResult
    server_cpu: float  # cores busy on average: 1.0 is one core flat out
    client_cpu: float


@dataclass
class Setup:
    """What the runs share, and the one-off measurements made while setting it up."""

    n: int
    title: str
    doc: str
    paths: list[np.ndarray]  # one panning path (steps, 4) per panner
    import_s: float = 0.0
    startup_health_s: float = 0.0
    startup_first_view_s: float = 0.0
    rss_import: int = 0
    rss_steady: int = 0
    rss_after_load: int = 0
    items_per_view: float = 0.0
    # mode -> (mean JSON bytes per step over the whole path, over its pure pan steps only)
    step_bytes: dict[str, tuple[float, float]] = field(default_factory=dict)
    ref_startup_s: float = 0.0
    ref_rss: int = 0
    postgis_skipped: str | None = None  # why PostGIS did not run, if it did not
    postgis_versions: str = ""
    postgis_load: dict[str, float] = field(default_factory=dict)  # postgis_server.load()'s measures
    postgis_startup_s: float = 0.0
    postgis_rss: int = 0
    postgis_db_pid: int | None = None  # the postmaster, whose CPU counts as the postgis server's
    runs: dict[str, list[Run]] = field(default_factory=dict)


# -- the scene -----------------------------------------------------------------------------


def make_scene(name: str, scale: float, seed: int) -> tuple[np.ndarray, np.ndarray, str]:
    if name == "document":
        pages = max(1, round(2000 * scale))
        boxes, kinds = scenes.long_document(pages=pages, seed=seed)
        return boxes, kinds, f"long document ({pages} pages)"
    n = max(1, round(FULL_N * scale))
    boxes, kinds = scenes.whiteboard(n=n, seed=seed)
    return boxes, kinds, f"whiteboard ({n:,} items)"


def write_ndjson(boxes: np.ndarray, kinds: np.ndarray, path: Path) -> None:
    """The scene as Vantage imports it (``app.demo.ndjson_lines``); the reference reads it too."""
    lines = ndjson_lines(boxes, kinds)
    with open(path, "wb") as f:
        f.writelines(
            tqdm(lines, desc="write NDJSON", total=len(boxes), unit=" items", file=sys.stderr)
            if tqdm
            else lines
        )


def panner_paths(boxes: np.ndarray, panners: int, steps: int, seed: int) -> list[np.ndarray]:
    return [scenes.panning_path(boxes, steps, seed=seed + k) for k in range(panners)]


def truth(boxes: np.ndarray, r: Rect) -> set[str]:
    """Ids of the items touching ``r`` (closed intervals), by brute force over the rows."""
    hit = (boxes[:, 0] <= r[2]) & (boxes[:, 2] >= r[0]) & (boxes[:, 1] <= r[3]) & (boxes[:, 3] >= r[1])
    return {f"i{i}" for i in np.flatnonzero(hit).tolist()}


# -- request paths -------------------------------------------------------------------------


def rect_param(r: Rect) -> str:
    """``x0,y0,x1,y1`` with repr floats: every server parses back the exact doubles."""
    return ",".join(repr(float(v)) for v in r)


def rect_query(r: Rect) -> str:
    return "&".join(f"{k}={float(v)!r}" for k, v in zip(("x0", "y0", "x1", "y1"), r, strict=True))


def reference_url(r: Rect) -> str:
    return f"/viewport?{rect_query(r)}"


def postgis_url(r: Rect) -> str:
    return f"/viewport?{rect_query(r)}&limit={LIMIT}"


def viewport_url(doc: str, r: Rect) -> str:
    return f"/documents/{doc}/viewport?{rect_query(r)}&limit={LIMIT}"


def diff_url(doc: str, old: Rect, new: Rect) -> str:
    return f"/documents/{doc}/diff?from={rect_param(old)}&to={rect_param(new)}&limit={LIMIT}"


def request_paths(mode: str, doc: str, path: np.ndarray) -> list[str]:
    """One panner's requests for an HTTP mode; a diff's first step comes from the path's last
    viewport, so cycling the path never asks for a diff the panner did not make."""
    views = [tuple(r) for r in path.tolist()]
    if mode == "reference":
        return [reference_url(r) for r in views]
    if mode == "postgis":
        return [postgis_url(r) for r in views]
    if mode == "viewport":
        return [viewport_url(doc, r) for r in views]
    if mode == "diff":
        return [diff_url(doc, views[i - 1], views[i]) for i in range(len(views))]
    if mode in ("hello", "hello_corked"):
        return ["/"] * len(views)
    raise ValueError(mode)


# -- setting up the servers ----------------------------------------------------------------


def import_scene(vantage: Server, ndjson: Path, n: int) -> tuple[str, float]:
    """Create a document and import the file into it, streamed from disk; (doc id, seconds)."""
    with httpx.Client(base_url=vantage.url, timeout=None) as client:
        created = client.post("/documents", json={"name": "service bench"})
        created.raise_for_status()
        doc = created.json()["id"]
        with open(ndjson, "rb") as body:  # a file object: httpx sends it in chunks
            t0 = time.perf_counter()
            answer = client.post(
                f"/documents/{doc}/items", content=body, headers={"content-type": "application/x-ndjson"}
            )
            seconds = time.perf_counter() - t0
    answer.raise_for_status()
    if answer.json()["imported"] != n:
        raise RuntimeError(f"import: {answer.json()} but the file has {n} items")
    return doc, seconds


def first_import(vantage: Server, ndjson: Path, lines: int = 1000) -> None:
    """Import the file's first ``lines`` into a document, then delete it: untimed, so that
    anything a worker does once, on its first import, is not in the timed one (numba compiling
    a kernel start-up did not: a fresh checkout's first 1M import once took 14.6 s)."""
    with open(ndjson, "rb") as f:
        chunk = list(itertools.islice(f, lines))
    head = ndjson.with_name("first-import.ndjson")  # beside the scene, in the run's scratch folder
    head.write_bytes(b"".join(chunk))
    doc, _ = import_scene(vantage, head, len(chunk))
    httpx.delete(f"{vantage.url}/documents/{doc}").raise_for_status()
    head.unlink()


def restart(vantage: Server, setup: Setup) -> None:
    """Start-up on an existing data dir: until /health answers, and until a first viewport does."""
    vantage.stop()
    vantage.start()
    setup.startup_health_s = vantage.wait_ready("/health")
    first = tuple(setup.paths[0][0])
    with httpx.Client(base_url=vantage.url, timeout=None) as client:
        client.get(viewport_url(setup.doc, first)).raise_for_status()
        setup.startup_first_view_s = time.perf_counter() - vantage.started_at
        views = [tuple(r) for r in setup.paths[0][: WARMUP_QUERIES + 1].tolist()]
        for old, new in itertools.pairwise(views):
            client.get(viewport_url(setup.doc, new)).raise_for_status()
            client.get(diff_url(setup.doc, old, new)).raise_for_status()
    setup.rss_steady = vantage.rss()


def check_correctness(boxes: np.ndarray, setup: Setup, servers: dict[str, Server]) -> None:
    """Viewport ids from every server must equal brute force; so must Vantage's diff."""
    vantage, reference, postgis = servers["vantage"], servers["reference"], servers.get("postgis")
    path = setup.paths[0]
    picks = np.unique(np.linspace(1, len(path) - 1, CHECKS).astype(int)).tolist()
    sizes, bad = [], []
    with httpx.Client(timeout=None) as client:
        for i in picks:
            old, new = tuple(path[i - 1]), tuple(path[i])
            want_old, want = truth(boxes, old), truth(boxes, new)
            sizes.append(len(want))
            ref = {
                it["id"] for it in client.get(reference.url + reference_url(new)).raise_for_status().json()
            }
            van = client.get(vantage.url + viewport_url(setup.doc, new)).raise_for_status().json()
            diff = client.get(vantage.url + diff_url(setup.doc, old, new)).raise_for_status().json()
            problems = []
            if ref != want:
                problems.append(f"reference {len(ref)} ids vs {len(want)} true ({len(want ^ ref)} differ)")
            if postgis is not None:
                pg = {it["id"] for it in client.get(postgis.url + postgis_url(new)).raise_for_status().json()}
                if pg != want:
                    problems.append(f"postgis {len(pg)} ids vs {len(want)} true ({len(want ^ pg)} differ)")
            got = {it["id"] for it in van["items"]}
            if got != want or van["truncated"]:
                problems.append(f"vantage {len(got)} ids vs {len(want)} true ({len(want ^ got)} differ)")
            entered, left = {it["id"] for it in diff["enter"]}, set(diff["leave"])
            if entered != want - want_old or left != want_old - want or diff["truncated"] or diff["reset"]:
                problems.append("vantage diff disagrees with brute force")
            if problems:
                bad.append(f"step {i} {new}: " + "; ".join(problems))
    if bad:
        raise SystemExit(f"FATAL: {len(bad)}/{len(picks)} viewports wrong:\n" + "\n".join(bad))
    setup.items_per_view = float(np.mean(sizes))
    print(
        f"correctness: {len(picks)} viewports (and diffs) of {len(servers) - 1} servers match brute force, "
        f"{setup.items_per_view:,.0f} items per viewport",
        file=sys.stderr,
    )


def measure_step_bytes(setup: Setup, servers: dict[str, Server]) -> None:
    """JSON bytes each mode sends per step of panner 0's whole path, one request at a time.

    Counted here, not from the timed runs: a faster server gets further along its path in the
    same seconds, and zooms late in a path would skew its average. Pure pan steps (same size,
    moved < PAN_LIMIT) are averaged apart from jumps and zooms, which any mode answers whole.
    """
    vantage, reference = servers["vantage"], servers["reference"]
    views = [tuple(r) for r in setup.paths[0].tolist()]
    pans = [
        i
        for i in range(1, len(views))
        if np.allclose(
            np.subtract(views[i][2:], views[i][:2]), np.subtract(views[i - 1][2:], views[i - 1][:2])
        )
        and max(abs(views[i][0] - views[i - 1][0]), abs(views[i][1] - views[i - 1][1])) < PAN_LIMIT
    ]
    sizes: dict[str, list[int]] = {}
    with httpx.Client(timeout=None) as client:
        sizes["reference"] = [len(client.get(reference.url + reference_url(r)).content) for r in views]
        if "postgis" in servers:
            postgis = servers["postgis"].url
            sizes["postgis"] = [len(client.get(postgis + postgis_url(r)).content) for r in views]
        sizes["viewport"] = [len(client.get(vantage.url + viewport_url(setup.doc, r)).content) for r in views]
        sizes["diff"] = [
            len(client.get(vantage.url + diff_url(setup.doc, views[i - 1], views[i])).content)
            for i in range(len(views))
        ]
        sizes["diff_gzip"] = []
        for i in range(len(views)):  # the bytes on the wire: the body as gzip'd, when it was
            answer = client.get(vantage.url + diff_url(setup.doc, views[i - 1], views[i]), headers=GZIP)
            answer.read()
            sizes["diff_gzip"].append(answer.num_bytes_downloaded)
    ws = vantage.url.replace("http://", "ws://") + f"/documents/{setup.doc}/stream"
    with connect(ws, compression=None, max_size=None) as stream:
        sizes["stream"], sizes["stream_deflate"] = [], []
        # permessage-deflate as uvicorn negotiates it (12-bit window, memLevel 5, the context
        # kept between messages): each message's compressed payload, less the 4-byte tail it drops
        deflate = zlib.compressobj(wbits=-12, memLevel=5)
        for seq, r in enumerate(views):
            stream.send(json.dumps({"seq": seq, "viewport": r, "limit": LIMIT}))
            message = stream.recv().encode()
            sizes["stream"].append(len(message))
            sizes["stream_deflate"].append(
                len(deflate.compress(message) + deflate.flush(zlib.Z_SYNC_FLUSH)) - 4
            )
    for mode, per_step in sizes.items():
        setup.step_bytes[mode] = (float(np.mean(per_step[1:])), float(np.mean([per_step[i] for i in pans])))
    print(f"bytes per step measured over {len(views) - 1} steps ({len(pans)} pure pans)", file=sys.stderr)


# -- running the load ----------------------------------------------------------------------


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process (all its threads), from /proc/<pid>/stat."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def tree_cpu_seconds(pid: int) -> float:
    """CPU of a process, its live children and the children it reaped: a PostgreSQL server's
    postmaster with its backends and background workers."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    total = sum(int(v) for v in fields[11:15]) / os.sysconf("SC_CLK_TCK")
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                if int(f.read().rsplit(")", 1)[1].split()[1]) == pid:
                    total += cpu_seconds(int(entry))
        except (OSError, ValueError, IndexError):  # gone meanwhile
            continue
    return total


def children_cpu_seconds() -> float:
    """CPU of the finished children we waited for: the load generators (servers still run)."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def measured(server: Server, generate: Callable[[], LoadResult], database: int | None = None) -> Run:
    """One load run; the server's CPU includes its database server's (postmaster ``database``)."""

    def server_cpu() -> float:
        return cpu_seconds(server.pid) + (tree_cpu_seconds(database) if database is not None else 0.0)

    s0, c0, t0 = server_cpu(), children_cpu_seconds(), time.perf_counter()
    load = generate()
    wall = time.perf_counter() - t0
    return Run(load, (server_cpu() - s0) / wall, (children_cpu_seconds() - c0) / wall)


def load_runner(
    mode: Mode,
    servers: dict[str, Server],
    setup: Setup,
    work: Path,
    args: argparse.Namespace,
    database: int | None = None,
) -> Callable[[float], Run]:
    """A function of seconds that runs one mode's load and returns its Run."""
    server = servers[mode.server]
    database = database if mode.server == "postgis" else None
    if mode.key in ("stream", "stream_deflate"):
        paths_file = work / "stream-paths.json"
        paths_file.write_text(json.dumps([p.tolist() for p in setup.paths]))
        ws = server.url.replace("http://", "ws://") + f"/documents/{setup.doc}/stream"
        deflate = mode.key == "stream_deflate"
        return lambda seconds: measured(
            server, lambda: run_stream(ws, paths_file, seconds, LIMIT, mode.label, deflate)
        )
    threads = min(args.threads, args.panners)
    requests = "diff" if mode.key == "diff_gzip" else mode.key
    per_panner = [request_paths(requests, setup.doc, p) for p in setup.paths]
    headers = GZIP if mode.key == "diff_gzip" else None
    script = write_wrk_script(work / "wrk", mode.key, interleave(per_panner, threads), headers)
    return lambda seconds: measured(
        server, lambda: run_wrk(server.url, script, args.panners, threads, seconds, mode.label), database
    )


def run_rounds(runners: dict[str, Callable[[float], Run]], args: argparse.Namespace) -> dict[str, list[Run]]:
    """Every mode once per round; the order rotates each round so no mode always follows the
    same neighbour. A short untimed run of each mode first (lazy imports, first connections)."""
    if args.warmup > 0:
        for runner in runners.values():
            runner(args.warmup)
    keys = list(runners)
    schedule = [keys[r % len(keys) :] + keys[: r % len(keys)] for r in range(args.rounds)]
    jobs = [(r, k) for r, order in enumerate(schedule) for k in order]
    runs: dict[str, list[Run]] = {k: [] for k in keys}
    for r, key in tqdm(jobs, desc="load runs", unit="run", file=sys.stderr) if tqdm else jobs:
        if not tqdm:
            print(f"round {r + 1}: {key} ...", file=sys.stderr, flush=True)
        runs[key].append(runners[key](args.seconds))
    return runs


# -- reporting -----------------------------------------------------------------------------


def median(runs: list[Run], value: Callable[[Run], float]) -> float:
    return float(statistics.median(value(r) for r in runs))


def ratio(value: float, base: float) -> str:
    return f"{value / base:.2f}x" if base else "n/a"


def modes_table(setup: Setup, args: argparse.Namespace) -> list[str]:
    runs = setup.runs
    rps = {k: median(v, lambda r: r.load.rps) for k, v in runs.items()}
    step = setup.step_bytes
    pg = "postgis" in runs
    lines = [
        f"### {setup.title}: {setup.n:,} items, {args.panners} panners, {args.seconds:g} s per run, "
        f"{args.rounds} rounds (medians)",
        "",
        "| mode | req/s | req/s range | / reference |"
        + (" / postgis |" if pg else "")
        + " p50 ms | p99 ms | bytes per step | bytes per pan step | pan / vantage full |"
        + (" pan / postgis |" if pg else "")
        + " server CPU | server CPU µs per answer | load-gen CPU |",
        "|---|---:|---:|---:|"
        + ("---:|" if pg else "")
        + "---:|---:|---:|---:|---:|"
        + ("---:|" if pg else "")
        + "---:|---:|---:|",
    ]
    for mode in MODES:
        if mode.key not in runs:
            continue
        rs = runs[mode.key]
        lo, hi = min(r.load.rps for r in rs), max(r.load.rps for r in rs)
        lines.append(
            f"| {mode.label} | {rps[mode.key]:,.0f} | {lo:,.0f}–{hi:,.0f} | {ratio(rps[mode.key], rps['reference'])} |"
            + (f" {ratio(rps[mode.key], rps['postgis'])} |" if pg else "")
            + f" {median(rs, lambda r: r.load.p50_us) / 1e3:,.2f} | {median(rs, lambda r: r.load.p99_us) / 1e3:,.2f} "
            f"| {_bytes(step, mode.key, 0)} | {_bytes(step, mode.key, 1)} | {_share(step, mode.key, 1)} |"
            + (f" {_share(step, mode.key, 1, 'postgis')} |" if pg else "")
            + f" {median(rs, lambda r: r.server_cpu):.2f} | {median(rs, lambda r: r.server_cpu / r.load.rps * 1e6):,.0f} |"
            + f" {median(rs, lambda r: r.client_cpu):.2f} |"
        )
    lines += [
        "",
        "- bytes: the JSON body of each answer along panner 0's whole path (HTTP headers not counted), "
        "over all steps and over the pure pan steps only (same size, moved < 200 units; jumps and zooms "
        "are answered whole by every mode); for gzip, the body as sent (answers under 1 kB go as they "
        "are); for permessage-deflate, each message's payload as the server compresses it (a 12-bit "
        "window kept across messages).",
        "- CPU columns: cores busy on average during the run (server process incl. its threads; the "
        "load generator process); on this machine 2 cores are all there is."
        + (
            " For postgis the server's CPU includes PostgreSQL's (postmaster, backends, background workers)."
            if pg
            else ""
        ),
        f"- postgis: {setup.postgis_versions}" if pg else f"- postgis: skipped ({setup.postgis_skipped}).",
        "",
    ]
    return lines


def _bytes(step: dict[str, tuple[float, float]], mode: str, which: int) -> str:
    return f"{step[mode][which]:,.0f}" if mode in step else "–"


def _share(step: dict[str, tuple[float, float]], mode: str, which: int, base: str = "viewport") -> str:
    return ratio(step[mode][which], step[base][which]) if mode in step else "–"


def setup_table(setup: Setup) -> list[str]:
    n = setup.n

    def rss(value: int) -> str:
        return f"{value / MB:,.0f}; {value / n:,.0f}"

    return [
        "| measure | value |",
        "|---|---:|",
        f"| import {n:,} items (s, request start to answer) | {setup.import_s:,.2f} |",
        f"| start-up to /health (s) | {setup.startup_health_s:,.2f} |",
        f"| start-up to first viewport (s) | {setup.startup_first_view_s:,.2f} |",
        f"| RSS right after import (MB; B/item) | {rss(setup.rss_import)} |",
        f"| RSS steady, after restart + warm-up (MB; B/item) | {rss(setup.rss_steady)} |",
        f"| RSS after all load runs (MB) | {setup.rss_after_load / MB:,.0f} |",
        f"| items per viewport (mean of {CHECKS} checked) | {setup.items_per_view:,.0f} |",
        f"| reference server: start-up to /health (s); RSS (MB) "
        f"| {setup.ref_startup_s:,.2f}; {setup.ref_rss / MB:,.0f} |",
        *postgis_rows(setup),
        "",
    ]


def postgis_rows(setup: Setup) -> list[str]:
    if setup.postgis_skipped is not None:
        return [f"| postgis | skipped: {setup.postgis_skipped} |"]
    load = setup.postgis_load
    total = load["copy_s"] + load["index_s"] + load["analyze_s"]
    return [
        f"| postgis load {int(load['rows']):,} rows (s): COPY; GiST index; ANALYZE; total "
        f"| {load['copy_s']:,.2f}; {load['index_s']:,.2f}; {load['analyze_s']:,.2f}; {total:,.2f} |",
        f"| postgis table; index (MB) | {load['table_bytes'] / MB:,.0f}; {load['index_bytes'] / MB:,.0f} |",
        f"| postgis server: start-up to /health (s); RSS (MB, the app alone) "
        f"| {setup.postgis_startup_s:,.2f}; {setup.postgis_rss / MB:,.0f} |",
    ]


def bar_section(setup: Setup) -> list[str]:
    runs, n = setup.runs, setup.n
    rps = {k: median(v, lambda r: r.load.rps) for k, v in runs.items()}
    step = setup.step_bytes
    p50 = {k: median(v, lambda r: r.load.p50_us) for k, v in runs.items()}
    p99 = {k: median(v, lambda r: r.load.p99_us) for k, v in runs.items()}

    def verdict(ok: bool) -> str:
        return "**PASS**" if ok else "**FAIL**"

    scale = n / FULL_N
    import_target, rss_target = 10.0 * scale, 500 * MB * scale
    judged = n >= FULL_N // 2  # below that the interpreter's fixed ~100 MB swamps a per-item RSS target
    lines = ["### bar", ""]
    lines.append(
        f"- vantage full-viewport req/s >= 2x reference: {ratio(rps['viewport'], rps['reference'])} "
        f"{verdict(rps['viewport'] >= 2 * rps['reference'])}"
    )
    for k in ("diff", "stream"):
        share, overall = step[k][1] / step["viewport"][1], step[k][0] / step["viewport"][0]
        lines.append(
            f"- {k} bytes per pan step <= 1/10 of vantage full viewport: {share:.3f} "
            f"(1/{1 / share:,.0f}) {verdict(share <= 0.1)}; over all steps, jumps and zooms "
            f"included: {overall:.3f} (1/{1 / overall:,.0f})"
        )
    for k in ("diff", "stream"):
        lines.append(
            f"- {k} req/s >= 3x reference: {ratio(rps[k], rps['reference'])} "
            f"{verdict(rps[k] >= 3 * rps['reference'])}"
        )
    if "postgis" in runs:
        for k in ("diff", "stream"):
            share = step[k][1] / step["postgis"][1]
            lines.append(
                f"- {k} vs postgis: req/s >= 3x: {ratio(rps[k], rps['postgis'])} "
                f"{verdict(rps[k] >= 3 * rps['postgis'])}; bytes per pan step <= 1/10: {share:.3f} "
                f"(1/{1 / share:,.0f}) {verdict(share <= 0.1)}"
            )
    else:
        lines.append(f"- diff and stream vs postgis: not measured, postgis skipped ({setup.postgis_skipped})")
    for k in ("viewport", "diff", "stream"):
        lines.append(
            f"- vantage {k} p99 < reference p50: {p99[k] / 1e3:,.2f} ms vs {p50['reference'] / 1e3:,.2f} ms "
            f"({ratio(p99[k], p50['reference'])}) {verdict(p99[k] < p50['reference'])}"
        )
    scaled = "" if n == FULL_N else f" (scaled to {n:,} items)"
    lines.append(
        f"- import <= 10 s per 1M items{scaled}: {setup.import_s:,.2f} s vs {import_target:,.2f} s "
        f"{verdict(setup.import_s <= import_target)}"
    )
    rss_verdict = verdict(setup.rss_steady <= rss_target) if judged else "not judged below 500k items"
    lines.append(
        f"- steady RSS <= 500 MB per 1M items{scaled}: {setup.rss_steady / MB:,.0f} MB vs "
        f"{rss_target / MB:,.0f} MB {rss_verdict}"
    )
    lines.append(
        f"- floor: vantage full viewport at {ratio(rps['viewport'], rps['hello'])} and diff at "
        f"{ratio(rps['diff'], rps['hello'])} of hello-world req/s ({rps['hello']:,.0f}); against the "
        f"hello-world on Vantage's protocol ({rps['hello_corked']:,.0f}), {ratio(rps['viewport'], rps['hello_corked'])} "
        f"and {ratio(rps['diff'], rps['hello_corked'])}"
    )
    return [*lines, ""]


def machine_header(args: argparse.Namespace) -> list[str]:
    cpu = cpu_model()
    try:
        wrk = (
            subprocess.run(["wrk", "-v"], capture_output=True, text=True)
            .stdout.splitlines()[0]
            .split(" [")[0]
        )
    except (OSError, IndexError):
        wrk = "wrk unknown"
    u = platform.uname()
    pkgs = versions(
        (
            "fastapi",
            "starlette",
            "uvicorn",
            "uvloop",
            "httptools",
            "websockets",
            "orjson",
            "msgspec",
            "shapely",
            "psycopg",
            "psycopg-pool",
            "numpy",
            "numba",
            "httpx",
        )
    )
    return [
        "## service_bench",
        "",
        f"- machine: {u.system} {u.release} {u.machine}, CPU {cpu}, nproc {len(os.sched_getaffinity(0))}",
        f"- python {platform.python_version()}; {pkgs}; {wrk}",
        f"- command: python -m benchmarks.service_bench {shlex.join(sys.argv[1:])}",
        f"- scene {args.scene}, scale {args.scale}, seed {args.seed}, {args.steps} steps per panner path, "
        f"wrk -t{min(args.threads, args.panners)} -c{args.panners}, warm-up {args.warmup:g} s per mode",
        "- servers: python -m uvicorn <app> --host 127.0.0.1 --port <free> --no-access-log --log-level warning "
        f"(one worker each; Vantage and the second hello-world with --http {UVICORN_HTTP})",
        f"- date {datetime.now(UTC):%Y-%m-%d %H:%M} UTC; load average at start "
        f"{', '.join(f'{v:.2f}' for v in os.getloadavg())} (a shared machine); code: {code_version()}",
        "",
    ]


def code_version() -> str:
    """The commit measured, and whether the service's code differed from it."""
    git = ["git", "-C", str(Path(__file__).resolve().parent.parent)]
    try:
        commit = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout
        dirty = subprocess.run(
            [*git, "status", "--porcelain", "app", "spatial"], capture_output=True, text=True
        )
    except OSError:
        return "unknown"
    changed = " with uncommitted changes in app/ or spatial/" if dirty.stdout.strip() else ""
    return f"commit {commit.strip() or 'unknown'}{changed}"


# -- main ----------------------------------------------------------------------------------


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.service_bench",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--scene",
        choices=("document", "whiteboard"),
        default="document",
        help="long document (2000 pages, ~1M items) or whiteboard (1M sticky notes)",
    )
    parser.add_argument(
        "--scale", type=float, default=1.0, help="fraction of the full item count (e.g. 0.05)"
    )
    parser.add_argument("--seconds", type=float, default=10.0, help="length of each load run")
    parser.add_argument("--rounds", type=int, default=3, help="rounds of all modes; medians are reported")
    parser.add_argument("--panners", type=int, default=8, help="concurrent panners (wrk connections)")
    parser.add_argument("--threads", type=int, default=2, help="wrk threads")
    parser.add_argument("--steps", type=int, default=2000, help="viewports per panner path (cycled)")
    parser.add_argument(
        "--warmup", type=float, default=1.0, help="untimed seconds of each mode first (0: none)"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--no-postgis",
        dest="postgis",
        action="store_false",
        help="skip the PostGIS server (it runs by default when PostgreSQL and PostGIS are installed)",
    )
    parser.add_argument("--out", help="also write the Markdown report to this path")
    args = parser.parse_args(argv)
    if args.scale <= 0 or args.seconds <= 0 or args.rounds < 1 or args.panners < 1 or args.steps < 2:
        parser.error("--scale and --seconds must be > 0, --rounds and --panners >= 1, --steps >= 2")
    return args


def start_servers(
    stack: ExitStack, work: Path, ndjson: Path, setup: Setup, args: argparse.Namespace
) -> dict[str, Server]:
    """Vantage (import, then restart on its data), the reference server, the hello-world and
    (unless skipped) PostGIS."""
    logs = work / "logs"
    logs.mkdir()
    # The per-connection stream rate limit protects a server from one client; here each panner
    # sends its next viewport as soon as the last is answered, so it is lifted to measure speed.
    env = {"VANTAGE_DATA_DIR": str(work / "data"), "VANTAGE_MAX_STREAM_RATE": "1e9"}
    vantage = stack.enter_context(vantage_server("vantage", env, logs))
    vantage.start().wait_ready()
    first_import(vantage, ndjson)
    print(f"importing {setup.n:,} items ...", file=sys.stderr, flush=True)
    setup.doc, setup.import_s = import_scene(vantage, ndjson, setup.n)
    setup.rss_import = vantage.rss()
    print(f"imported in {setup.import_s:.2f} s; restarting ...", file=sys.stderr, flush=True)
    restart(vantage, setup)
    reference = stack.enter_context(
        Server("reference", "benchmarks.reference_server:app", {"REFERENCE_NDJSON": str(ndjson)}, logs)
    )
    setup.ref_startup_s = reference.start().wait_ready()
    setup.ref_rss = reference.rss()
    hello = stack.enter_context(Server("hello", "benchmarks.hello_server:app", {}, logs))
    hello.start().wait_ready("/")
    corked = stack.enter_context(
        Server("hello_corked", "benchmarks.hello_server:app", {}, logs, VANTAGE_HTTP)
    )
    corked.start().wait_ready("/")
    servers = {"vantage": vantage, "reference": reference, "hello": hello, "hello_corked": corked}
    if args.postgis:
        postgis = start_postgis(stack, work, ndjson, setup, logs)
        if postgis is not None:
            servers["postgis"] = postgis
    else:
        setup.postgis_skipped = "--no-postgis"
    return servers


POSTGIS_SETTINGS = {
    # The table and its index (~300 MB at 1M items) fit in PostgreSQL's own cache, as a user
    # serving viewports from it would configure; the default 128 MB would not hold them.
    "shared_buffers": "512MB",
}


def start_postgis(stack: ExitStack, work: Path, ndjson: Path, setup: Setup, logs: Path) -> Server | None:
    """A PostgreSQL server of its own (tests/postgres.py), the scene loaded with PostGIS, and
    benchmarks/postgis_server.py on it; None (with ``setup.postgis_skipped`` saying why) if
    PostgreSQL or PostGIS is not installed."""
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
    import psycopg
    from postgres import PostgresMissing, postgres_server

    from .postgis_server import load as load_postgis

    try:
        database = stack.enter_context(postgres_server(work / "postgres"))
    except PostgresMissing as error:
        setup.postgis_skipped = str(error)
        return None
    with psycopg.connect(database.url, autocommit=True) as db:
        try:
            db.execute("CREATE EXTENSION postgis")
        except psycopg.Error as error:
            setup.postgis_skipped = (
                f"CREATE EXTENSION postgis failed ({str(error).strip().splitlines()[0]}): "
                f"install postgresql-{database.bin.parent.name}-postgis-3"
            )
            return None
        for name, value in POSTGIS_SETTINGS.items():
            db.execute(f"ALTER SYSTEM SET {name} = '{value}'")
    database.stop()  # shared_buffers takes a restart
    database.start()
    with psycopg.connect(database.url) as db:
        pg_version = db.execute("SHOW server_version").fetchone()[0]
        postgis_version = db.execute("SELECT postgis_lib_version()").fetchone()[0]
    setup.postgis_versions = (
        f"PostgreSQL {pg_version}, PostGIS {postgis_version}; shared_buffers {POSTGIS_SETTINGS['shared_buffers']}, "
        "fsync and synchronous_commit off (tests/postgres.py: a disposable server); "
        "benchmarks/postgis_server.py, pool of 8 connections, PostgreSQL writes the JSON"
    )
    print("loading the scene into PostGIS ...", file=sys.stderr, flush=True)
    setup.postgis_load = load_postgis(database.url, ndjson)
    setup.postgis_db_pid = database.pid
    server = stack.enter_context(
        Server("postgis", "benchmarks.postgis_server:app", {"POSTGIS_URL": database.url}, logs)
    )
    setup.postgis_startup_s = server.start().wait_ready()
    setup.postgis_rss = server.rss()
    return server


def exit_on_sigterm() -> None:
    """Turn SIGTERM into SystemExit, so the ``with`` blocks still stop the servers on the way out."""

    def handler(signum: int, frame: object) -> None:
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, handler)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    exit_on_sigterm()
    report = machine_header(args)
    print("\n".join(report), flush=True)
    boxes, kinds, title = make_scene(args.scene, args.scale, args.seed)
    setup = Setup(len(boxes), title, "", panner_paths(boxes, args.panners, args.steps, args.seed))
    with tempfile.TemporaryDirectory(prefix="service-bench-") as tmp, ExitStack() as stack:
        work = Path(tmp)
        ndjson = work / "scene.ndjson"
        write_ndjson(boxes, kinds, ndjson)
        del kinds
        servers = start_servers(stack, work, ndjson, setup, args)
        check_correctness(boxes, setup, servers)
        measure_step_bytes(setup, servers)
        del boxes  # the servers hold the scene now; keep this process out of their memory's way
        runners = {
            m.key: load_runner(m, servers, setup, work, args, setup.postgis_db_pid)
            for m in MODES
            if m.server in servers
        }
        setup.runs = run_rounds(runners, args)
        setup.rss_after_load = servers["vantage"].rss()
    lines = [*modes_table(setup, args), *setup_table(setup), *bar_section(setup)]
    print("\n".join(lines), flush=True)
    report += lines
    if args.out:
        Path(args.out).write_text("\n".join(report) + "\n")


if __name__ == "__main__":
    main()

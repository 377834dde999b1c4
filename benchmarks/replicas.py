"""Vantage on PostgreSQL: an import through a replica, and edits pushed across replicas.

Run from the repository root (a seeded plain script, not a test; needs Debian's ``postgresql``
package unless ``--database-url`` names a server)::

    python -m benchmarks.replicas --out /tmp/replicas.md      # 1M items, ~5 minutes
    python -m benchmarks.replicas --items 100000 --rounds 1 --edits 50

A PostgreSQL server of its own (tests/postgres.py: a disposable server, fsync off) and three
``uvicorn app.main:app`` processes, one worker each: replicas A and B on that database (each
with a data directory of its own for its snapshot files) and a server on SQLite, the default
store.

(a) Import: a whiteboard scene (``spatial.scenes``) written once as NDJSON, POSTed streamed
from disk into a new document, timed from the request's start to its answer. PostgreSQL
(through A) and SQLite take turns, ``--rounds`` rounds, the order swapped each round; medians.
Each round's document is deleted after it, except the last one on PostgreSQL, which (b) uses.

(b) Push latency: streams (WebSocket) held on B and on A, both showing one screen of that
document; ``--edits`` PUTs of an item inside that screen sent to A one at a time, each after a
seeded random pause. Per edit and stream: the time from sending the PUT to receiving the pushed
``"type": "edit"`` message of the version the PUT answered. A's stream is the floor (no store
between the writer and the stream); B learns of the edit through PostgreSQL (NOTIFY, the change
log, its 50 ms follow loop). Both streams get every edit, so both are measured on the same
edits at the same moments.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import statistics
import sys
import tempfile
import threading
import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import httpx
import numpy as np
import psycopg
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from spatial import scenes

from .machine import cpu_model, versions
from .servers import Server, vantage_server
from .service_bench import code_version, exit_on_sigterm, import_scene, write_ndjson

ROOT = Path(__file__).resolve().parent.parent
STORES = ("sqlite", "postgresql")
IMPORT_TARGET_S = 15.0  # for 1M items into PostgreSQL, end to end
FULL_N = 1_000_000
PUSH_TARGET_MS = 100.0  # p99 across replicas
PUSH_TIMEOUT_S = 5.0  # a push not seen by then counts as lost
SCREEN = (1920.0, 1080.0)
NOTE = (60.0, 40.0)  # the edited items' size
EDITED_IDS = 10  # the edits cycle through this many items; the first PUT of each creates it
LIMIT = 100_000


def percentile(ordered: list[float], q: float) -> float:
    """Nearest-rank percentile of an ascending list."""
    return ordered[min(len(ordered) - 1, max(0, round(q / 100 * len(ordered)) - 1))]


def verdict(ok: bool) -> str:
    return "**PASS**" if ok else "**FAIL**"


# -- (a) import ------------------------------------------------------------------------------


@dataclass
class Imports:
    seconds: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in STORES})
    doc: str = ""  # the last PostgreSQL round's document, kept for (b)
    database_growth: int = 0  # bytes the PostgreSQL database grew by with the first import


def run_imports(servers: dict[str, Server], ndjson: Path, n: int, rounds: int, database_url: str) -> Imports:
    result = Imports()

    def database_size() -> int:
        with psycopg.connect(database_url) as db:
            return db.execute("SELECT pg_database_size(current_database())").fetchone()[0]

    empty = database_size()
    for r in range(rounds):
        for store in STORES if r % 2 else STORES[::-1]:
            server = servers["a" if store == "postgresql" else "sqlite"]
            doc, seconds = import_scene(server, ndjson, n)
            result.seconds[store].append(seconds)
            print(f"round {r + 1}: {store} import {seconds:.2f} s", file=sys.stderr, flush=True)
            if store == "postgresql" and r == 0:
                result.database_growth = database_size() - empty
            if store == "postgresql" and r == rounds - 1:
                result.doc = doc
            else:  # so every round's import starts from the same store
                httpx.delete(f"{server.url}/documents/{doc}", timeout=None).raise_for_status()
    return result


# -- (b) push latency ------------------------------------------------------------------------


class Listener:
    """A stream showing one viewport, read in a thread of its own: when each edit version came."""

    def __init__(self, url: str, doc: str, viewport: tuple[float, ...]) -> None:
        ws_url = url.replace("http://", "ws://") + f"/documents/{doc}/stream"
        self._stack = ExitStack()
        self.ws = self._stack.enter_context(connect(ws_url, compression=None, max_size=None, open_timeout=60))
        t0 = time.perf_counter()
        self.ws.send(json.dumps({"seq": 1, "viewport": list(viewport), "limit": LIMIT}))
        first = json.loads(self.ws.recv(timeout=600))
        self.first_s = time.perf_counter() - t0  # the document opened on this replica, then answered
        if first.get("type") != "view":
            raise RuntimeError(f"stream on {url}: first message {str(first)[:300]}")
        self.shown = len(first["enter"])
        self.arrived: dict[int, float] = {}  # version -> perf_counter() when its push came
        self.unexpected: list[str] = []  # anything but an edit push: errors, views
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        try:
            for text in self.ws:
                now = time.perf_counter()
                message = json.loads(text)
                with self._cond:
                    if message.get("type") == "edit":
                        self.arrived.setdefault(message["version"], now)
                    else:
                        self.unexpected.append(str(message)[:300])
                    self._cond.notify_all()
        except ConnectionClosed:
            pass

    def wait(self, version: int, timeout: float) -> float | None:
        """When the push of ``version`` (or a later one) came; None if not within ``timeout``."""
        deadline = time.perf_counter() + timeout
        with self._cond:
            while True:
                came = [t for v, t in self.arrived.items() if v >= version]
                if came:
                    return min(came)
                left = deadline - time.perf_counter()
                if left <= 0:
                    return None
                self._cond.wait(left)

    def close(self) -> None:
        self._stack.close()
        self._thread.join(timeout=5)


@dataclass
class Pushes:
    viewport: tuple[float, ...]
    shown: int = 0
    first_s: dict[str, float] = field(default_factory=dict)  # replica -> first answer (opening the document)
    # per edit, ms from sending the PUT: its answer, the push on A's stream and on B's (None: lost)
    edits: list[tuple[float, float | None, float | None]] = field(default_factory=list)
    unexpected: list[str] = field(default_factory=list)
    consistency: str = ""

    def push_ms(self, name: str) -> list[float]:
        return [e[1 if name == "a" else 2] for e in self.edits if e[1 if name == "a" else 2] is not None]

    def lost(self, name: str) -> int:
        return len(self.edits) - len(self.push_ms(name))


def screen_around(boxes: np.ndarray, seed: int) -> tuple[float, ...]:
    """A screen-sized viewport centred on a seeded random item."""
    rng = np.random.default_rng(seed)
    x0, y0, x1, y1 = boxes[rng.integers(len(boxes))].tolist()
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    return (cx - SCREEN[0] / 2, cy - SCREEN[1] / 2, cx + SCREEN[0] / 2, cy + SCREEN[1] / 2)


def run_pushes(
    servers: dict[str, Server],
    doc: str,
    viewport: tuple[float, ...],
    edits: int,
    pause_ms: tuple[float, float],
    seed: int,
) -> Pushes:
    result = Pushes(viewport)
    rng = np.random.default_rng(seed + 1)
    listeners = {}
    try:
        for name in ("b", "a"):  # B first: its opening the document from PostgreSQL is measured cold
            listeners[name] = Listener(servers[name].url, doc, viewport)
            result.first_s[name] = listeners[name].first_s
        result.shown = listeners["b"].shown
        version = 0
        with httpx.Client(base_url=servers["a"].url, timeout=30) as client:
            for k in range(edits):
                time.sleep(rng.uniform(*pause_ms) / 1000)
                x = rng.uniform(viewport[0], viewport[2] - NOTE[0])
                y = rng.uniform(viewport[1], viewport[3] - NOTE[1])
                item = {"x0": x, "y0": y, "x1": x + NOTE[0], "y1": y + NOTE[1], "kind": "note", "z": 1}
                t0 = time.perf_counter()
                answer = client.put(f"/documents/{doc}/items/edit-{k % EDITED_IDS}", json=item)
                put_ms = (time.perf_counter() - t0) * 1e3
                answer.raise_for_status()
                version = answer.json()["version"]
                came = {name: listener.wait(version, PUSH_TIMEOUT_S) for name, listener in listeners.items()}
                push = {name: None if t is None else (t - t0) * 1e3 for name, t in came.items()}
                result.edits.append((put_ms, push["a"], push["b"]))
        result.consistency = consistency(servers, doc, viewport, version)
    finally:
        for name, listener in listeners.items():
            result.unexpected += [f"{name}: {m}" for m in listener.unexpected]
            listener.close()
    return result


def consistency(servers: dict[str, Server], doc: str, viewport: tuple[float, ...], version: int) -> str:
    """Whether A and B answer the viewport alike at the last edit's version."""
    params = {
        **dict(zip(("x0", "y0", "x1", "y1"), viewport, strict=True)),
        "limit": LIMIT,
        "min_version": version,
    }
    answers = {}
    for name in ("a", "b"):
        got = httpx.get(f"{servers[name].url}/documents/{doc}/viewport", params=params, timeout=30)
        got.raise_for_status()
        body = got.json()
        answers[name] = (body["version"], sorted((it["id"], it["x0"], it["y0"]) for it in body["items"]))
    if answers["a"] == answers["b"]:
        return (
            f"A and B answer the viewport alike at version {answers['a'][0]} ({len(answers['a'][1])} items)"
        )
    return f"**A and B differ**: A at version {answers['a'][0]}, B at version {answers['b'][0]}"


# -- the report ------------------------------------------------------------------------------


def header(args: argparse.Namespace, pg_version: str, database: str) -> list[str]:
    u = platform.uname()
    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    load = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    pkgs = versions(("fastapi", "uvicorn", "websockets", "httpx", "psycopg", "psycopg-pool", "numpy"))
    return [
        "# Replicas on PostgreSQL: import, and edits pushed across replicas",
        "",
        f"- command: `python -m benchmarks.replicas {shlex.join(sys.argv[1:])}`",
        f"- machine: {u.system} {u.release} {u.machine}, CPU {cpu_model()}, nproc "
        f"{len(os.sched_getaffinity(0))}, {memory:.0f} GiB; load average at start {load} (a shared machine)",
        f"- python {platform.python_version()}; {pkgs}; {pg_version}",
        f"- database: {database}",
        f"- code: {code_version()}",
        f"- servers: python -m uvicorn app.main:app, one worker each: replicas A and B on the database, "
        f"and one on SQLite; date {datetime.now(UTC):%Y-%m-%d %H:%M} UTC",
        f"- seed {args.seed}, {args.items:,} items, {args.rounds} round(s), {args.edits} edits, pause "
        f"{args.pause_ms[0]:g}–{args.pause_ms[1]:g} ms",
        "",
    ]


def import_section(imports: Imports, n: int, file_bytes: int, args: argparse.Namespace) -> list[str]:
    med = {s: statistics.median(v) for s, v in imports.seconds.items()}
    labels = {
        "sqlite": "SQLite (VANTAGE_DATA_DIR)",
        "postgresql": "PostgreSQL (VANTAGE_DATABASE_URL), through replica A",
    }
    lines = [
        f"## (a) Import of {n:,} items ({file_bytes / 1e6:,.0f} MB of NDJSON) through HTTP, end to end",
        "",
        "POST of the body streamed from disk, request start to answer; "
        f"{args.rounds} round(s), the stores taking turns (order swapped each round); medians.",
        "",
        "| store | median s | each round s | items/s (median) | / SQLite |",
        "|---|---:|---:|---:|---:|",
    ]
    for store in STORES:
        each = ", ".join(f"{v:.2f}" for v in imports.seconds[store])
        lines.append(
            f"| {labels[store]} | {med[store]:.2f} | {each} | {n / med[store]:,.0f} "
            f"| {med[store] / med['sqlite']:.2f}x |"
        )
    target = IMPORT_TARGET_S * n / FULL_N
    scaled = "" if n == FULL_N else f" (scaled to {n:,} items: {target:.2f} s)"
    lines += [
        "",
        f"- target: 1M items into PostgreSQL <= {IMPORT_TARGET_S:g} s end to end{scaled}: "
        f"{med['postgresql']:.2f} s {verdict(med['postgresql'] <= target)}",
        f"- the PostgreSQL database grew by {imports.database_growth / 1e6:,.0f} MB with the first import",
        "",
    ]
    return lines


def push_section(pushes: Pushes, args: argparse.Namespace) -> list[str]:
    def row(label: str, values: list[float], lost: int | str) -> str:
        v = sorted(values)
        if not v:
            return f"| {label} | 0 | {lost} | – | – | – | – | – |"
        over = sum(x > PUSH_TARGET_MS for x in v)
        return (
            f"| {label} | {len(v)} | {lost} | {percentile(v, 50):.1f} | {percentile(v, 90):.1f} "
            f"| {percentile(v, 99):.1f} | {v[-1]:.1f} | {over} |"
        )

    across, floor = sorted(pushes.push_ms("b")), sorted(pushes.push_ms("a"))
    p99 = percentile(across, 99) if across else float("inf")
    both = [
        (k, put, a, b) for k, (put, a, b) in enumerate(pushes.edits, 1) if a is not None and b is not None
    ]
    extra = sorted(b - a for _, _, a, b in both)
    slowest = sorted(both, key=lambda e: e[3], reverse=True)[:3]
    vp = ", ".join(f"{v:.1f}" for v in pushes.viewport)
    lines = [
        f"## (b) Edit push latency: {args.edits} PUTs to replica A, streams on B and on A",
        "",
        f"Viewport [{vp}] ({pushes.shown:,} items shown) of the last imported document; each edit a PUT "
        f"of one of {EDITED_IDS} notes to a random place inside it, sent after a pause of "
        f"{args.pause_ms[0]:g}–{args.pause_ms[1]:g} ms (seeded), the next only once both streams had "
        f"the push (or {PUSH_TIMEOUT_S:g} s passed: lost). Times in ms from sending the PUT.",
        "",
        f"| measure | edits | lost | p50 | p90 | p99 | max | over {PUSH_TARGET_MS:g} ms |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
        row("push to a stream on B (the other replica, through PostgreSQL)", across, pushes.lost("b")),
        row("push to a stream on A (the replica written to: the floor)", floor, pushes.lost("a")),
        row("PUT answered by A", [e[0] for e in pushes.edits], "–"),
        "",
        f"- target: p99 across replicas <= {PUSH_TARGET_MS:g} ms: {p99:.1f} ms "
        + (f"({p99 / percentile(floor, 99):.1f}x the floor's p99) " if floor else "")
        + verdict(p99 <= PUSH_TARGET_MS and not pushes.lost("b"))
        + (f" ({pushes.lost('b')} pushes lost)" if pushes.lost("b") else ""),
        "- what crossing replicas adds, per edit (B's push minus A's, the same edit): "
        + (
            f"p50 {percentile(extra, 50):.1f} ms, p90 {percentile(extra, 90):.1f} ms, p99 "
            f"{percentile(extra, 99):.1f} ms, max {extra[-1]:.1f} ms"
            if extra
            else "–"
        ),
        "- the slowest pushes to B, as edit number: B, A, the PUT's answer (ms): "
        + "; ".join(f"#{k}: {b:.1f}, {a:.1f}, {put:.1f}" for k, put, a, b in slowest)
        + " (edit #1 is the first since each replica opened the document)",
        f"- first answer of each stream (the document opened on that replica, then the view): B "
        f"{pushes.first_s['b']:.2f} s (read from PostgreSQL, built, its snapshot file written), A "
        f"{pushes.first_s['a']:.2f} s (open since its import)",
        f"- afterwards: {pushes.consistency}",
    ]
    if pushes.unexpected:
        lines.append(f"- unexpected stream messages ({len(pushes.unexpected)}): {pushes.unexpected[:3]}")
    return [*lines, ""]


def log_section(servers: dict[str, Server]) -> list[str]:
    """What the servers logged (uvicorn at --log-level warning: warnings and errors only)."""
    lines = ["## Server logs", ""]
    for name, server in servers.items():
        logged = [ln for ln in server.log_path.read_text(errors="replace").splitlines() if ln.strip()]
        said = "nothing" if not logged else f"{len(logged)} line(s), the first: `{logged[0][:240]}`"
        lines.append(f"- {name}: {said}")
    return [*lines, ""]


# -- main ------------------------------------------------------------------------------------


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.replicas",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--items", type=int, default=FULL_N, help="items in the imported scene")
    parser.add_argument("--rounds", type=int, default=3, help="import rounds per store; medians are reported")
    parser.add_argument("--edits", type=int, default=300, help="edits whose push is timed")
    parser.add_argument(
        "--pause-ms",
        type=float,
        nargs=2,
        default=(20.0, 100.0),
        metavar=("MIN", "MAX"),
        help="pause before each edit",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--database-url",
        help="a postgresql:// database to use instead of starting a server (tests/postgres.py)",
    )
    parser.add_argument("--out", help="also write the Markdown report to this path")
    args = parser.parse_args(argv)
    if args.items < 1 or args.rounds < 1 or args.edits < 1 or not 0 <= args.pause_ms[0] <= args.pause_ms[1]:
        parser.error("--items, --rounds and --edits must be >= 1, and 0 <= --pause-ms MIN <= MAX")
    return args


def start_database(stack: ExitStack, work: Path, args: argparse.Namespace) -> tuple[str, str]:
    """``(url, what it is)``: the one named, or a server of our own."""
    if args.database_url:
        return args.database_url, "the one --database-url names"
    sys.path.insert(0, str(ROOT / "tests"))
    from postgres import SETTINGS, postgres_server

    server = stack.enter_context(postgres_server(work / "postgres"))
    settings = ", ".join(f"{k} {v.strip(chr(39))}" for k, v in SETTINGS.items() if k != "listen_addresses")
    return (
        server.url,
        f"a PostgreSQL server of its own on loopback (tests/postgres.py: {settings}; the rest default)",
    )


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    exit_on_sigterm()
    boxes, kinds = scenes.whiteboard(n=args.items, seed=args.seed)
    viewport = screen_around(boxes, args.seed)
    with tempfile.TemporaryDirectory(prefix="replicas-bench-") as tmp, ExitStack() as stack:
        work = Path(tmp)
        logs = work / "logs"
        logs.mkdir()
        ndjson = work / "scene.ndjson"
        write_ndjson(boxes, kinds, ndjson)
        del boxes, kinds
        database_url, database = start_database(stack, work, args)
        with psycopg.connect(database_url) as db:
            pg_version = "PostgreSQL " + db.execute("SHOW server_version").fetchone()[0]
        report = header(args, pg_version, database)
        print("\n".join(report), flush=True)
        # room for the whole body whatever --items says (the default cap is 256 MB)
        common = {"VANTAGE_MAX_BODY_BYTES": str(max(256 << 20, 2 * ndjson.stat().st_size))}
        servers = {}
        for name, env in (
            ("a", {"VANTAGE_DATABASE_URL": database_url}),
            ("b", {"VANTAGE_DATABASE_URL": database_url}),
            ("sqlite", {}),
        ):
            env = {**common, **env, "VANTAGE_DATA_DIR": str(work / name)}
            servers[name] = stack.enter_context(vantage_server(name, env, logs))
            servers[name].start().wait_ready()
        try:
            imports = run_imports(servers, ndjson, args.items, args.rounds, database_url)
            pushes = run_pushes(servers, imports.doc, viewport, args.edits, tuple(args.pause_ms), args.seed)
        except Exception:
            for server in servers.values():
                print(f"--- {server.name} log:\n{server.log_tail()}", file=sys.stderr)
            raise
        lines = [
            *import_section(imports, args.items, ndjson.stat().st_size, args),
            *push_section(pushes, args),
            *log_section(servers),
        ]
    print("\n".join(lines), flush=True)
    if args.out:
        Path(args.out).write_text("\n".join(report + lines) + "\n")


if __name__ == "__main__":
    main()

"""How evenly `vantage serve --workers 2` spreads its work, against uvicorn's own workers.

Run from the repository root (a seeded plain script, not a test; needs ``wrk`` on the PATH)::

    .venv/bin/python -m benchmarks.worker_spread            # about 4 minutes
    .venv/bin/python -m benchmarks.worker_spread --help

Servers, each started fresh for every round so the load's connections meet idle workers:

- **Vantage, 2 workers**: ``vantage serve --workers 2``, a listening socket per worker
  (``SO_REUSEPORT``), forked after start-up;
- **one shared socket, 2 workers**: the same app under ``uvicorn --workers 2``, whose workers
  all accept from one socket (what ``vantage serve`` ran before);
- **Vantage, 1 worker**: for the CPU a request costs.

Loads, each from a separate process opening all its connections at once: ``wrk -t2 -c8``
panning ``/diff`` on a 300-page document, and 8 WebSocket streams panning (benchmarks.stream_load).
Per round: the CPU seconds each worker spent (``/proc/PID/stat``), the busiest worker's share of
them, requests/s and CPU per request. Medians over the rounds.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx

from app.launch import free_port, launch, stop, wait_until_up
from app.protocol import UVICORN_HTTP, UVICORN_WS
from app.stores import SQLiteStore

from .load import LoadResult, run_stream, run_wrk, write_wrk_script
from .machine import cpu_model, versions
from .working_set import children, cpu_seconds, diff_paths, random_views, scene, write_document

PAGES, SEED, CONNECTIONS = 300, 7, 8
LOAD_ENV = {"VANTAGE_MAX_STREAM_RATE": "1000000"}  # panners in lockstep pass a person's 120 a second


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


@contextmanager
def vantage(data_dir: Path, workers: int, log_path: Path) -> Iterator[tuple[str, list[int]]]:
    """``vantage serve --workers N``: ``(url, worker pids)``."""
    with open(log_path, "a") as output:
        process, url = launch(data_dir, "--workers", str(workers), env=LOAD_ENV, output=output)
        try:
            yield url, _workers(process.pid, workers)
        finally:
            stop(process, timeout=30)


@contextmanager
def shared_socket(data_dir: Path, workers: int, log_path: Path) -> Iterator[tuple[str, list[int]]]:
    """The same app under ``uvicorn --workers N``: every worker accepts from one socket."""
    port = free_port()
    env = {**os.environ, **LOAD_ENV, "VANTAGE_DATA_DIR": str(data_dir), "VANTAGE_WORKERS": str(workers)}
    command = [sys.executable, "-m", "uvicorn", "app.main:app", "--http", UVICORN_HTTP, "--ws", UVICORN_WS]
    command += ["--port", str(port), "--workers", str(workers), "--log-level", "warning"]
    with open(log_path, "a") as output:
        process = subprocess.Popen(command, env=env, stdout=output, stderr=subprocess.STDOUT)
        url = f"http://127.0.0.1:{port}"
        try:
            wait_until_up(url, process)
            yield url, _workers(process.pid, workers)
        finally:
            stop(process, timeout=30)


def _workers(parent: int, count: int, timeout: float = 120.0) -> list[int]:
    """The server's worker processes: its children that serve (not multiprocessing's helpers)."""
    if count == 1:
        return [parent]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = [pid for pid in sorted(children(parent)) if b"resource_tracker" not in _cmdline(pid)]
        if len(found) == count:
            return found
        time.sleep(0.1)
    raise RuntimeError(f"the server {parent} did not start {count} workers")


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except FileNotFoundError:
        return b""


def memory(pids: list[int]) -> tuple[float, float]:
    """``(private MiB of each process, summed PSS MiB)`` from /proc/PID/smaps_rollup."""
    private = pss = 0
    for pid in pids:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            fields = {
                n: int(v.split()[0])
                for n, _, v in (line.partition(":") for line in f)
                if v.strip()[:1].isdigit()
            }
        private += fields["Private_Clean"] + fields["Private_Dirty"]
        pss += fields["Pss"]
    return private / 1024 / len(pids), pss / 1024


def loaded(pids: list[int], load: Callable[[], LoadResult]) -> dict:
    """Run ``load``; the CPU seconds each worker spent meanwhile, and what the load did."""
    before = [cpu_seconds([pid]) for pid in pids]
    result = load()
    cpu = [cpu_seconds([pid]) - b for pid, b in zip(pids, before, strict=True)]
    total = sum(cpu)
    return {
        "cpu": cpu,
        "busiest": max(cpu) / total if total else 1.0,
        "rps": result.requests / (result.duration_us / 1e6),
        "cpu_ms": 1e3 * total / max(1, result.requests),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.worker_spread", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--rounds", type=int, default=5, help="rounds per server and load (default 5)")
    parser.add_argument("--seconds", type=float, default=6.0, help="seconds of each load (default 6)")
    args = parser.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="vantage-spread-"))
    log_path = work / "servers.log"
    log(f"data and logs in {work}")

    boxes, kinds = scene(PAGES, SEED)
    store = SQLiteStore(work)
    doc = write_document(store, "spread", boxes, kinds)
    store.close()
    wrk_script = write_wrk_script(work / "wrk", "diff", diff_paths(doc, boxes, 2, 2000, SEED))
    panners = [list(view) for view in random_views(boxes, 4000, seed=SEED)]
    stream_paths = work / "streams.json"
    stream_paths.write_text(json.dumps([panners[k::CONNECTIONS] for k in range(CONNECTIONS)]))

    servers = {
        "Vantage, 2 workers (a socket each)": lambda: vantage(work, 2, log_path),
        "one shared socket, 2 workers (uvicorn --workers)": lambda: shared_socket(work, 2, log_path),
        "Vantage, 1 worker": lambda: vantage(work, 1, log_path),
    }
    loads = {
        f"wrk -t2 -c{CONNECTIONS}, /diff": lambda url: run_wrk(
            url, wrk_script, CONNECTIONS, 2, args.seconds, "diff"
        ),
        f"{CONNECTIONS} streams": lambda url: run_stream(
            f"{url.replace('http', 'ws')}/documents/{doc}/stream",
            stream_paths,
            args.seconds,
            100_000,
            "streams",
        ),
    }
    with vantage(work, 1, log_path) as (url, _):  # the document's snapshot file built once
        httpx.get(f"{url}/documents/{doc}/viewport", params={"x0": 0, "y0": 0, "x1": 10, "y1": 10})
    runs: dict[tuple[str, str], list[dict]] = {}
    for round_ in range(args.rounds):
        for server_name, start in servers.items():  # the servers alternate within a round
            for load_name, load in loads.items():
                with start() as (url, pids):  # a fresh server: the load's connections all arrive at once
                    run = loaded(pids, lambda: load(url))
                runs.setdefault((server_name, load_name), []).append(run)
                log(
                    f"round {round_ + 1}: {server_name}, {load_name}: CPU s per worker "
                    f"{' / '.join(f'{c:.2f}' for c in run['cpu'])}, {run['rps']:,.0f} req/s"
                )

    idle = {}
    for server_name, start in servers.items():
        with start() as (url, pids):
            for _ in range(20):  # the document opened on each worker
                with httpx.Client() as fresh:
                    fresh.get(
                        f"{url}/documents/{doc}/viewport", params={"x0": 0, "y0": 0, "x1": 10, "y1": 10}
                    )
            parent = (
                []
                if len(pids) == 1
                else [int(Path(f"/proc/{pids[0]}/stat").read_text().rsplit(")", 1)[1].split()[1])]
            )
            idle[server_name] = (memory(pids), memory(parent + pids)[1])

    print(f"machine: {cpu_model()}, {os.cpu_count()} cores; {versions(('uvicorn', 'uvloop', 'numba'))}")
    print(f"`python -m benchmarks.worker_spread --rounds {args.rounds} --seconds {args.seconds:g}`\n")
    print(
        "| server | load | busiest worker's share of the CPU (median; each round) | req/s | CPU ms a request |"
    )
    print("|---|---|---|---:|---:|")
    for (server_name, load_name), rs in runs.items():
        shares = " ".join(f"{r['busiest']:.0%}" for r in rs)
        busiest = statistics.median(r["busiest"] for r in rs)
        rps = statistics.median(r["rps"] for r in rs)
        cpu_ms = statistics.median(r["cpu_ms"] for r in rs)
        print(f"| {server_name} | {load_name} | {busiest:.0%} ({shares}) | {rps:,.0f} | {cpu_ms:.3f} |")
    print("\n| server | private MiB a worker | PSS MiB of all its processes |")
    print("|---|---:|---:|")
    for server_name, ((private, _), pss) in idle.items():
        print(f"| {server_name} | {private:.0f} | {pss:.0f} |")


if __name__ == "__main__":
    main()

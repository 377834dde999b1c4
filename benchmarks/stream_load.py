"""WebSocket load for service_bench: N panners on Vantage's pan stream, each in lockstep.

wrk cannot speak WebSocket, so this runs as its own process (like wrk) and prints one JSON line
in the shape of service_bench's wrk ``done()``: requests, bytes, duration and latency in
microseconds, and error counts. Each panner is one connection that follows its own path: send
a viewport, wait for its answer, record the latency and the answer's bytes, send the next.
Compression is off unless ``--deflate`` (then permessage-deflate is negotiated, as browsers do),
so bytes are the JSON payload an HTTP client would also get::

    python -m benchmarks.stream_load --url ws://127.0.0.1:8000/documents/<id>/stream \\
        --paths /tmp/paths.json --seconds 10
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time
from dataclasses import dataclass, field

import orjson
from websockets.asyncio.client import connect
from websockets.exceptions import WebSocketException

from spatial import Rect

ERRORS = ("connect", "read", "write", "status", "timeout")  # as in wrk's summary


@dataclass
class Tally:
    latencies_us: list[float] = field(default_factory=list)
    bytes: int = 0
    errors: dict[str, int] = field(default_factory=lambda: dict.fromkeys(ERRORS, 0))


async def pan(
    url: str, path: list[Rect], limit: int, deadline: float, timeout: float, tally: Tally, deflate: bool
) -> None:
    """One panner: walk ``path`` (cycling) until the deadline, one viewport in flight at a time."""
    try:
        compression = "deflate" if deflate else None
        ws = await connect(url, compression=compression, max_size=None, open_timeout=timeout)
    except (OSError, WebSocketException, TimeoutError):
        tally.errors["connect"] += 1
        return
    async with ws:
        seq = 0
        while time.perf_counter() < deadline:
            message = {"seq": seq, "viewport": path[seq % len(path)], "limit": limit}
            t0 = time.perf_counter()
            try:
                await ws.send(orjson.dumps(message).decode())
            except WebSocketException:
                tally.errors["write"] += 1
                return
            try:
                # decode=False: the text frame's bytes as received, no str round trip
                answer = await asyncio.wait_for(ws.recv(decode=False), timeout)
            except TimeoutError:
                tally.errors["timeout"] += 1
                return
            except WebSocketException:
                tally.errors["read"] += 1
                return
            elapsed = time.perf_counter() - t0
            body = orjson.loads(answer)
            if body.get("type") != "view" or body.get("seq") != seq:
                tally.errors["status"] += 1  # an error message, or an answer to another view
            tally.latencies_us.append(elapsed * 1e6)
            tally.bytes += len(answer)
            seq += 1


def percentile(ordered: list[float], q: float) -> float:
    """Nearest-rank percentile of an ascending list (0 if empty)."""
    if not ordered:
        return 0.0
    return ordered[min(len(ordered) - 1, max(0, round(q / 100 * len(ordered)) - 1))]


async def run(
    url: str, paths: list[list[Rect]], seconds: float, limit: int, timeout: float, deflate: bool = False
) -> dict:
    tally = Tally()
    start = time.perf_counter()
    deadline = start + seconds
    await asyncio.gather(*(pan(url, p, limit, deadline, timeout, tally, deflate) for p in paths))
    duration_us = (time.perf_counter() - start) * 1e6
    lat = sorted(tally.latencies_us)
    return {
        "requests": len(lat),
        "bytes": tally.bytes,
        "duration_us": round(duration_us),
        "errors": tally.errors,
        "latency_us": {
            "p50": percentile(lat, 50),
            "p90": percentile(lat, 90),
            "p99": percentile(lat, 99),
            "max": lat[-1] if lat else 0.0,
        },
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.stream_load",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--url", required=True, help="ws://host:port/documents/<id>/stream")
    parser.add_argument("--paths", required=True, help="JSON file: one list of [x0, y0, x1, y1] per panner")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--limit", type=int, default=100_000, help="item cap sent with each viewport")
    parser.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for one answer")
    parser.add_argument("--deflate", action="store_true", help="negotiate permessage-deflate")
    args = parser.parse_args(argv)
    with open(args.paths) as f:
        paths = json.load(f)
    try:  # the client's own loop overhead lands in every latency it records: take the fast one
        from uvloop import run as run_loop
    except ImportError:
        run_loop = asyncio.run
    result = run_loop(run(args.url, paths, args.seconds, args.limit, args.timeout, args.deflate))
    sys.stdout.write(json.dumps(result) + "\n")


if __name__ == "__main__":
    main()

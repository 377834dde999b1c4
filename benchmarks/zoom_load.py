"""People zooming out to see the whole board, under load: per-screen answers against tiles.

Run from the repository root (a seeded plain script, not a test)::

    python -m benchmarks.zoom_load                                    # 200k notes (~2 min, 2 cores)
    python -m benchmarks.zoom_load --scale 0.05 --seconds 4 --rounds 1 --fit-seconds 3

A clustered board (``spatial.scenes.clustered_board``) is imported into a spawned Vantage
server (one worker, as ``vantage serve`` runs by default), and the simulator's users
(``app.simulate``: 60 Hz camera paths, the page's fetch policy, HTTP diffs by default) pan it,
half of them every so often zooming out to Fit, looking for 1-3 s, then diving into another
place. Two modes get the same users on the same paths, on the same server:

- per-screen: zoomed out, each answer carries every aggregate inline with its mask, drawn in
  that screen's pixels (the service's answers without ``tiles=true``);
- tiled: zoomed out, users ask ``tiles=true``, so answers carry only items drawn themselves
  and name the tiles holding the aggregates; each user fetches the tiles under its screen and
  margin it does not hold and keeps them (``app.simulate.users.HELD_TILES``), as a browser's
  cache does for the page; zoomed in (its tiles hold no aggregate), it asks without.

The modes alternate, ``--rounds`` rounds of ``--seconds`` each (per-screen first in odd
rounds, tiled first in even ones), so a warming server or a noisy neighbour hits both alike;
figures pool the rounds. Then a separate short phase per mode: ``--fit-clients`` clients open
the board at Fit (as the page opens a board) and sit there, nudging it now and then, while a
prober in a process of its own asks ``/health`` every 20 ms: its p99 is how the server's other
clients fare meanwhile. Server CPU is read from ``/proc`` of the server process; bytes are the
bodies as they came over the wire (gzip'd when the server sent them so; headers not counted),
tiles included.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import platform
import resource
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import orjson

from app.client import Client
from app.demo import ndjson_lines
from app.simulate.motion import FPS, fit_scale, screen_rect
from app.simulate.run import SCREEN, bounds_and_anchors, places, run_mode, user_paths, zooming_out
from app.simulate.users import ANSWERS, MIN_PX, Mode, Sent, UserLog
from spatial import scenes

from .machine import cpu_model
from .servers import vantage_server

FULL_N = 200_000  # notes at --scale 1
OVERSCAN = 0.5  # the page's margin (static/policy.json)
PROBE_EVERY = 0.02  # seconds between /health probes
# The prober: its own process, so the load's event loop and GIL never delay a probe.
PROBE = """
import sys, time, httpx, orjson
url, seconds, every = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
out = []
with httpx.Client(timeout=30) as http:
    end = time.time() + seconds
    while time.time() < end:
        t0 = time.perf_counter()
        ok = http.get(url + "/health").status_code == 200
        out.append((time.time(), time.perf_counter() - t0, ok))
        time.sleep(max(0.0, every - (time.perf_counter() - t0)))
print(orjson.dumps(out).decode())
"""


@dataclass
class Tally:
    """One mode's runs, pooled: every user's log, the seconds run, the CPU used meanwhile."""

    logs: list[UserLog] = field(default_factory=list)
    seconds: float = 0.0
    server_cpu: float = 0.0  # CPU seconds of the server process
    client_cpu: float = 0.0  # CPU seconds of this process (the users)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.zoom_load",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help=f"board size: {FULL_N:,} notes times this (default %(default)s)",
    )
    parser.add_argument("--users", type=int, default=32, help="users panning at once (default %(default)s)")
    parser.add_argument(
        "--seconds", type=float, default=15.0, help="each mode's run, each round (default %(default)s)"
    )
    parser.add_argument("--rounds", type=int, default=2, help="rounds of both modes (default %(default)s)")
    parser.add_argument(
        "--zoom-out-share",
        type=float,
        default=0.5,
        help="share of the users who zoom out to Fit every so often (default %(default)s)",
    )
    parser.add_argument(
        "--zoom-out-every",
        type=float,
        default=8.0,
        help="seconds between such a user's looks at the whole board, about (default %(default)s)",
    )
    parser.add_argument(
        "--transport",
        choices=("diff", "poll"),
        default="diff",
        help="HTTP answers asked (default %(default)s)",
    )
    parser.add_argument(
        "--fit-clients",
        type=int,
        default=100,
        help="clients at Fit in the /health phase (default %(default)s)",
    )
    parser.add_argument(
        "--fit-seconds", type=float, default=6.0, help="the /health phase, per mode (default %(default)s)"
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="the board and the users' paths (default %(default)s)"
    )
    parser.add_argument("--out", type=Path, help="also write the report (Markdown) here")
    args = parser.parse_args(argv)
    if min(args.scale, args.seconds, args.fit_seconds, args.zoom_out_every) <= 0:
        parser.error("--scale, --seconds, --fit-seconds and --zoom-out-every must be positive")
    if min(args.users, args.rounds, args.fit_clients) < 1 or not 0 <= args.zoom_out_share <= 1:
        parser.error("--users, --rounds and --fit-clients must be at least 1, --zoom-out-share within 0..1")
    return args


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # so the server is stopped on the way out
    n = max(1, round(FULL_N * args.scale))
    modes = {
        "per-screen": Mode(args.transport, OVERSCAN, True, tiles=False),
        "tiled": Mode(args.transport, OVERSCAN, True, tiles=True),
    }
    with ExitStack() as stack:
        work = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="vantage-zoom-load-")))
        server = stack.enter_context(
            vantage_server("vantage", {"VANTAGE_DATA_DIR": str(work / "data")}, work)
        )
        server.start()
        server.wait_ready()
        boxes, kinds = scenes.clustered_board(n=n, seed=args.seed)
        with Client(server.url, timeout=None) as vantage:
            doc = vantage.create_document(f"clustered board ({n:,} notes)")["id"]
            t0 = time.perf_counter()
            vantage.import_items(doc, b"".join(ndjson_lines(boxes, kinds)))
            imported = time.perf_counter() - t0
            bounds, anchors = bounds_and_anchors(vantage, doc)
            targets = places(vantage, doc, bounds, args.seed)
            _warm_up(vantage, doc, bounds)
        say(f"{n:,} notes imported in {imported:.1f} s; server {server.url}")
        looking = zooming_out(args.users, args.zoom_out_share)
        paths = user_paths(args, bounds, anchors, looking, targets)
        tallies = {name: Tally() for name in modes}
        for r in range(args.rounds):
            order = list(modes) if r % 2 == 0 else list(modes)[::-1]
            for name in order:
                say(f"round {r + 1}/{args.rounds}: {name}, {args.users} users for {args.seconds:g} s")
                _measured(tallies[name], server.pid, modes[name], server.url, doc, paths, args.seconds)
        fit_paths = [
            fit_path(args.seed + 10_000 + k, bounds, args.fit_seconds) for k in range(args.fit_clients)
        ]
        idle = _probe(server.url, 2.0)
        fits = {}
        for name, mode in modes.items():
            say(f"/health with {args.fit_clients} clients at Fit: {name}")
            fits[name] = _fit_phase(server.pid, mode, server.url, doc, fit_paths, args.fit_seconds)
        if server.proc is not None and server.proc.poll() is not None:
            raise SystemExit(f"the server died:\n{server.log_tail()}")
    report = render(args, n, tallies, fits, idle, len(looking))
    print(report)
    if args.out:
        args.out.write_text(report + "\n")


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


# -- the load ------------------------------------------------------------------------------


def fit_path(seed: int, bounds: tuple[float, float, float, float], seconds: float) -> np.ndarray:
    """Cameras ``(x, y, scale)`` a frame for someone who opened the board at Fit and sits
    there: rests of 0.5-2 s, and nudges of 0.2-0.6 s at 200-800 px/s in any direction."""
    rng = np.random.default_rng(seed)
    scale = fit_scale(bounds, SCREEN)
    cx, cy = (bounds[0] + bounds[2]) / 2, (bounds[1] + bounds[3]) / 2
    n = max(1, round(seconds * FPS))
    out = np.empty((n, 3))
    i = 0
    while i < n:
        rest = round(rng.uniform(0.5, 2.0) * FPS)
        angle, speed = rng.uniform(0, 2 * np.pi), rng.uniform(200, 800) / scale / FPS  # units a frame
        nudge = round(rng.uniform(0.2, 0.6) * FPS)
        for k in range(rest + nudge):
            if i >= n:
                break
            if k >= rest:
                cx = float(np.clip(cx + speed * np.cos(angle), bounds[0], bounds[2]))
                cy = float(np.clip(cy + speed * np.sin(angle), bounds[1], bounds[3]))
            out[i] = (cx - SCREEN[0] / 2 / scale, cy - SCREEN[1] / 2 / scale, scale)
            i += 1
    return out


def _warm_up(vantage: Client, doc: str, bounds: tuple[float, float, float, float]) -> None:
    """One answer of each kind at Fit and zoomed in, and a tile: what compiles once is compiled
    before any timing (and no path's own places are visited)."""
    scale = fit_scale(bounds, SCREEN)
    for s in (scale, scale * 16, 1.0):
        cx, cy = bounds[0] + (bounds[2] - bounds[0]) * 0.3, bounds[1] + (bounds[3] - bounds[1]) * 0.7
        rect = screen_rect((cx - SCREEN[0] / 2 / s, cy - SCREEN[1] / 2 / s, s), SCREEN)
        vantage.viewport(doc, rect, scale=s, min_px=MIN_PX)
        params = {"x0": rect[0], "y0": rect[1], "x1": rect[2], "y1": rect[3], "scale": s, "min_px": MIN_PX}
        answer = vantage.http.get(f"/documents/{doc}/viewport", params={**params, "tiles": "true"}).json()
        sheet = answer.get("tiles")
        if sheet:
            tx0, ty0, _, _ = sheet["range"]
            url = f"/documents/{doc}/tiles/{sheet['band']}/{sheet['z']}/{tx0}/{ty0}"
            vantage.http.get(url, params={"version": answer["version"]}).raise_for_status()


def _measured(
    tally: Tally, pid: int, mode: Mode, url: str, doc: str, paths: list[np.ndarray], seconds: float
) -> None:
    """Run the users once, adding what they saw and the CPU both sides used to ``tally``."""
    s0, c0, t0 = cpu_seconds(pid), self_cpu_seconds(), time.perf_counter()
    logs = asyncio.run(run_mode(mode, url, doc, paths, 10**9))
    tally.seconds += time.perf_counter() - t0
    tally.server_cpu += cpu_seconds(pid) - s0
    tally.client_cpu += self_cpu_seconds() - c0
    tally.logs += logs
    errors = [e for log in logs for e in log.errors]
    if errors:
        raise SystemExit(f"{len(errors)} requests failed, the first: {errors[0]}")


def _fit_phase(
    pid: int, mode: Mode, url: str, doc: str, paths: list[np.ndarray], seconds: float
) -> dict[str, object]:
    """Clients at Fit for ``seconds`` while the prober asks ``/health``."""
    prober = subprocess.Popen(
        [sys.executable, "-c", PROBE, url, str(seconds + 1.0), str(PROBE_EVERY)], stdout=subprocess.PIPE
    )
    time.sleep(0.5)  # the prober's start-up (imports), outside the window
    tally = Tally()
    start = time.time()
    _measured(tally, pid, mode, url, doc, paths, seconds)
    end = time.time()
    out, _ = prober.communicate(timeout=seconds + 60)
    probes = [(t, s) for t, s, ok in orjson.loads(out) if start <= t <= end and ok]
    return {"health": _health(probes), **figures(tally)}


def _probe(url: str, seconds: float) -> dict[str, float]:
    """``/health`` latency with nothing else going on."""
    out = subprocess.run(
        [sys.executable, "-c", PROBE, url, str(seconds), str(PROBE_EVERY)],
        capture_output=True,
        check=True,
        timeout=seconds + 60,
    ).stdout
    probes = [(t, s) for t, s, ok in orjson.loads(out) if ok]
    return _health(probes[5:])  # the first few pay the connection


def _health(probes: list[tuple[float, float]]) -> dict[str, float]:
    ms = np.array([s for _, s in probes]) * 1e3
    if not ms.size:
        return {"probes": 0, "p50": float("nan"), "p99": float("nan"), "max": float("nan")}
    return {"probes": int(ms.size), "p50": _pct(ms, 50), "p99": _pct(ms, 99), "max": float(ms.max())}


# -- the figures ----------------------------------------------------------------------------


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process (all its threads), from /proc/<pid>/stat."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def self_cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _pct(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if values.size else float("nan")


def figures(tally: Tally) -> dict[str, float]:
    """A mode's pooled figures: answers (viewport and diff) and what they cost."""
    sent: list[Sent] = [r for log in tally.logs for r in log.requests]
    answers = [r for r in sent if r.route in ANSWERS]
    tiles = [r for r in sent if r.route == "tile"]
    count = max(len(answers), 1)
    latency = np.array([r.latency for r in answers]) * 1e3
    drawn = np.array([r.drawn for r in answers if r.drawn is not None]) * 1e3
    zoomed_out = [r for r in answers if r.band is not None]
    return {
        "answers": len(answers),
        "answers_per_s": len(answers) / tally.seconds,
        "server_cpu_ms": tally.server_cpu / count * 1e3,
        "server_cores": tally.server_cpu / tally.seconds,
        "client_cores": tally.client_cpu / tally.seconds,
        "p50_ms": _pct(latency, 50),
        "p99_ms": _pct(latency, 99),
        "drawn_p50_ms": _pct(drawn, 50),
        "drawn_p99_ms": _pct(drawn, 99),
        "wire_bytes": sum(r.wire for r in sent) / count,
        "answer_bytes": sum(r.wire for r in answers) / count,
        "tiles": len(tiles) / count,
        "tile_bytes": sum(r.wire for r in tiles) / count,
        "tiles_empty": sum(log.tiles_empty for log in tally.logs) / max(len(tiles), 1),
        "tiles_held": sum(log.tiles_held for log in tally.logs)
        / max(sum(log.tiles_needed for log in tally.logs), 1),
        "coarsest_band": max((r.band for r in zoomed_out), default=float("nan")),
        "blank": float(np.mean([b for log in tally.logs for _, b in log.frames])),
    }


def render(
    args: argparse.Namespace,
    n: int,
    tallies: dict[str, Tally],
    fits: dict[str, dict[str, object]],
    idle: dict[str, float],
    looking: int,
) -> str:
    a, b = (figures(t) for t in tallies.values())

    def row(label: str, key: str, fmt: str) -> str:
        ratio = b[key] / a[key] if a[key] else float("nan")
        return f"| {label} | {format(a[key], fmt)} | {format(b[key], fmt)} | {ratio:.2f} |"

    command = "python -m benchmarks.zoom_load " + shlex.join(sys.argv[1:])
    lines = [
        f"Clustered board, {n:,} notes; {args.users} users ({looking} zooming out to Fit about every "
        f"{args.zoom_out_every:g} s), HTTP {args.transport}, overscan {OVERSCAN:g}; "
        f"{args.rounds} x {args.seconds:g} s a mode, alternating. {platform.system()} {platform.machine()}, "
        f"{os.cpu_count()} cores ({cpu_model()}), Python {platform.python_version()}. `{command}`",
        "",
        "| | (a) per-screen | (b) tiled | b/a |",
        "|---|---:|---:|---:|",
        row("answers/s", "answers_per_s", ",.1f"),
        row("server CPU per answer (ms, tiles included)", "server_cpu_ms", ",.2f"),
        row("server CPU (cores busy)", "server_cores", ".2f"),
        row("answer latency p50 (ms)", "p50_ms", ",.1f"),
        row("answer latency p99 (ms)", "p99_ms", ",.1f"),
        row("drawn p50 (ms: the answer and its tiles)", "drawn_p50_ms", ",.1f"),
        row("drawn p99 (ms)", "drawn_p99_ms", ",.1f"),
        row("bytes per answer on the wire (tiles included)", "wire_bytes", ",.0f"),
        row("  of which the answer", "answer_bytes", ",.0f"),
        row("  of which tiles", "tile_bytes", ",.0f"),
        row("tiles fetched per answer", "tiles", ",.2f"),
        row("share of tiles fetched holding no aggregate", "tiles_empty", ".1%"),
        row("share of tiles needed already held", "tiles_held", ".1%"),
        row("coarsest band answered", "coarsest_band", "g"),
        row("blank share of the screen, mean", "blank", ".2%"),
        row("client CPU (cores busy, the users' process)", "client_cores", ".2f"),
        "",
        f"`/health` every {PROBE_EVERY * 1e3:g} ms from its own process while {args.fit_clients} clients "
        f"open the board at Fit and sit there ({args.fit_seconds:g} s a mode); idle: "
        f"p50 {idle['p50']:.1f} ms, p99 {idle['p99']:.1f} ms.",
        "",
        "| | (a) per-screen | (b) tiled | b/a |",
        "|---|---:|---:|---:|",
    ]
    fa, fb = fits["per-screen"], fits["tiled"]
    ha, hb = fa["health"], fb["health"]
    assert isinstance(ha, dict) and isinstance(hb, dict)
    for label, x, y, fmt in (
        ("/health p50 (ms)", ha["p50"], hb["p50"], ",.1f"),
        ("/health p99 (ms)", ha["p99"], hb["p99"], ",.1f"),
        ("/health max (ms)", ha["max"], hb["max"], ",.1f"),
        ("answers", fa["answers"], fb["answers"], ",.0f"),
        ("answer latency p99 (ms)", fa["p99_ms"], fb["p99_ms"], ",.1f"),
        ("drawn p99 (ms)", fa["drawn_p99_ms"], fb["drawn_p99_ms"], ",.1f"),
        ("tiles fetched per answer", fa["tiles"], fb["tiles"], ",.1f"),
        ("server CPU per answer (ms, tiles included)", fa["server_cpu_ms"], fb["server_cpu_ms"], ",.2f"),
        ("bytes per answer on the wire (tiles included)", fa["wire_bytes"], fb["wire_bytes"], ",.0f"),
    ):
        ratio = float(y) / float(x) if x else float("nan")  # type: ignore[arg-type]
        lines.append(f"| {label} | {format(x, fmt)} | {format(y, fmt)} | {ratio:.2f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()

"""What a zoomed-out screen costs the server: per-screen answers against tiles, one client at a time.

Run from the repository root (a seeded plain script, not a test)::

    python -m benchmarks.zoomed_out                  # the 200k-note clustered board (~1 min)
    python -m benchmarks.zoomed_out --notes 20000 --repeat 3

A clustered board (``spatial.scenes.clustered_board``) is imported into a spawned Vantage server
(one worker, as ``vantage serve`` runs), restarted so the document opens cold from its file, and
asked, over HTTP with gzip, for full-HD screens:

- **Fit, first**: the whole board, the first answer of a cold document (a restart before each);
- **Fit, again**: the same screen asked again (by this client or another: the server cannot tell);
- **sweep, first / again**: zooming in from Fit to 1/16 pixel a unit by x1.25 steps about the
  middle, the first time, then again (by another client, and by the same one);
- **sweep about random notes**: the same sweep about four random notes (screens no one asked
  before).

Per-screen: ``/viewport`` as any client asks it, each aggregate with its mask in the screen's
pixels. Tiled: as the page asks, its zoom snapped to the ladder, ``tiles=true``, then every tile
the answer names that this client does not hold (a new client: every one; asked again by the same
client: none). Server CPU is read from ``/proc`` around each phase (10 ms ticks: phases repeat
``--repeat`` times and the total is divided), bytes as sent (gzipped). Medians over rounds.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from collections.abc import Callable
from functools import partial
from pathlib import Path

import httpx
import numpy as np

from app.demo import ndjson_lines
from app.tiles import ladder_level, ladder_scale
from spatial import scenes

from .machine import cpu_model
from .servers import vantage_server
from .service_bench import cpu_seconds

SCREEN = (1920, 1080)
STEP = 1.25  # the sweep's zoom step
DEEPEST = 1 / 16  # the sweep ends at this many pixels a unit


class Board:
    """The board served: its document, and the screens the phases ask."""

    def __init__(self, url: str, doc: str, boxes: np.ndarray, seed: int) -> None:
        self.url, self.doc, self.boxes = url, doc, boxes
        x0, y0 = boxes[:, :2].min(0)
        x1, y1 = boxes[:, 2:].max(0)
        self.fit = float(min(SCREEN[0] / (x1 - x0), SCREEN[1] / (y1 - y0)))
        self.middle = (float(x0 + x1) / 2, float(y0 + y1) / 2)
        self.sweep = [self.fit * STEP**k for k in range(int(math.log(DEEPEST / self.fit, STEP)) + 1)]
        rng = np.random.default_rng(seed)
        picks = rng.integers(len(boxes), size=4)
        self.elsewhere = [tuple(((boxes[i, :2] + boxes[i, 2:]) / 2).tolist()) for i in picks]

    def screen(self, scale: float, centre: tuple[float, float], tiled: bool) -> dict:
        if tiled:  # as the page draws zoomed out: a rung of the ladder, its corner on a pixel
            scale = ladder_scale(ladder_level(scale))
        x0 = math.floor((centre[0] - SCREEN[0] / 2 / scale) * scale) / scale
        y0 = math.floor((centre[1] - SCREEN[1] / 2 / scale) * scale) / scale
        params = {"x0": x0, "y0": y0, "x1": x0 + SCREEN[0] / scale, "y1": y0 + SCREEN[1] / scale}
        return {**params, "scale": scale, "min_px": 1, **({"tiles": "true"} if tiled else {})}


class Client:
    """One client: per-screen, or tiled holding the tiles it fetched."""

    def __init__(self, board: Board, tiled: bool) -> None:
        self.board, self.tiled = board, tiled
        self.http = httpx.Client(base_url=board.url, timeout=120, headers={"accept-encoding": "gzip"})
        self.held: set[str] = set()
        self.bytes = 0

    def sweep(self, screens: list[tuple[float, tuple[float, float]]]) -> None:
        for scale, centre in screens:
            self.show(scale, centre)

    def show(self, scale: float, centre: tuple[float, float]) -> None:
        answer = self._get(
            f"/documents/{self.board.doc}/viewport", self.board.screen(scale, centre, self.tiled)
        )
        sheet = answer.json().get("tiles")
        if not sheet:
            return
        tx0, ty0, tx1, ty1 = sheet["range"]
        for ty in range(ty0, ty1 + 1):
            for tx in range(tx0, tx1 + 1):
                path = f"/documents/{self.board.doc}/tiles/{sheet['band']}/{sheet['z']}/{tx}/{ty}"
                if path not in self.held:
                    self._get(path, {"version": answer.json()["version"]})
                    self.held.add(path)

    def _get(self, path: str, params: dict) -> httpx.Response:
        answer = self.http.get(path, params=params)
        answer.raise_for_status()
        self.bytes += (
            len(answer.content)
            if "content-encoding" not in answer.headers
            else int(answer.headers["content-length"])
        )
        return answer


def phase(pid: int, screens: int, run: Callable[[], None], repeat: int) -> float:
    """Server CPU ms a screen of ``run`` (``screens`` screens), run ``repeat`` times."""
    cpu = cpu_seconds(pid)
    for _ in range(repeat):
        run()
    return (cpu_seconds(pid) - cpu) / (screens * repeat) * 1e3


def measure(board: Board, pid: int, tiled: bool, repeat: int) -> dict[str, tuple[float, float]]:
    """Every phase but the first answer, for one kind of client: {phase: (CPU ms, KB) a screen}."""
    out = {}
    middle = [(s, board.middle) for s in board.sweep]

    def timed(name: str, screens: list, fresh: bool, times: int = repeat) -> None:
        """``screens`` asked ``times`` times: by a new client each time (holding no tile), or
        again by one that asked them once already (untimed)."""
        clients = [Client(board, tiled)]
        if not fresh:
            clients[0].sweep(screens)
            clients[0].bytes = 0

        def once() -> None:
            if fresh:
                clients.append(Client(board, tiled))
            clients[-1].sweep(screens)

        cpu = phase(pid, len(screens), once, times)
        out[name] = (cpu, sum(c.bytes for c in clients) / (len(screens) * times) / 1e3)

    fit = [(board.fit, board.middle)]  # one screen: asked 10x as often, for the 10 ms ticks
    timed("Fit, again by another client", fit, fresh=True, times=10 * repeat)
    timed("Fit, again by the same client", fit, fresh=False, times=10 * repeat)
    timed("sweep Fit..1/16, first", middle, fresh=True, times=1)
    timed("sweep Fit..1/16, again by another client", middle, fresh=True)
    timed("sweep Fit..1/16, again by the same client", middle, fresh=False)
    elsewhere = [(s, centre) for centre in board.elsewhere for s in board.sweep]
    timed("sweep about random notes, first", elsewhere, fresh=True, times=1)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.zoomed_out",
        description=__doc__.split("\n\n")[0],
        epilog="See the module docstring.",
    )
    parser.add_argument("--notes", type=int, default=200_000, help="notes on the board (default 200,000)")
    parser.add_argument("--rounds", type=int, default=3, help="rounds, each on a freshly started server")
    parser.add_argument(
        "--repeat", type=int, default=5, help="times each phase runs in a round (CPU ticks are 10 ms)"
    )
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    boxes, kinds = scenes.clustered_board(n=args.notes, seed=args.seed)
    body = b"".join(ndjson_lines(boxes, kinds))
    rows: dict[tuple[str, bool], list[tuple[float, float]]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        env = {"VANTAGE_DATA_DIR": str(work / "data")}
        server = vantage_server("zoomed-out", env, work).start()
        server.wait_ready()
        with httpx.Client(base_url=server.url, timeout=None) as http:
            doc = http.post("/documents", json={"name": "board"}).json()["id"]
            http.post(
                f"/documents/{doc}/items", content=body, headers={"content-type": "application/x-ndjson"}
            ).raise_for_status()
        server.stop()
        for r in range(args.rounds):
            for tiled in (False, True) if r % 2 == 0 else (True, False):
                server = vantage_server("zoomed-out", env, work).start()  # cold: opened from its file
                server.wait_ready()
                board = Board(server.url, doc, boxes, args.seed)
                client = Client(board, tiled)
                cpu = phase(server.pid, 1, partial(client.show, board.fit, board.middle), 1)
                rows.setdefault(("Fit, first answer of a cold document", tiled), []).append(
                    (cpu, client.bytes / 1e3)
                )
                for name, value in measure(board, server.pid, tiled, args.repeat).items():
                    rows.setdefault((name, tiled), []).append(value)
                server.stop()
                print(
                    f"round {r + 1}/{args.rounds}: {'tiled' if tiled else 'per-screen'} measured",
                    file=sys.stderr,
                )
    names = list(dict.fromkeys(name for name, _ in rows))
    median = lambda values, i: float(np.median([v[i] for v in values]))
    print(f"## Zoomed out, one client at a time: {args.notes:,}-note board")
    print(
        f"{cpu_model()}; {args.rounds} rounds x {args.repeat}; server CPU a screen (ms), KB a screen gzipped; medians\n"
    )
    print("| screen | per-screen CPU | per-screen KB | tiled CPU | tiled KB | CPU tiled / per-screen |")
    print("|---|---:|---:|---:|---:|---:|")
    for name in names:
        a, b = rows[name, False], rows[name, True]
        ratio = median(b, 0) / median(a, 0) if median(a, 0) else float("nan")
        print(
            f"| {name} | {median(a, 0):.2f} | {median(a, 1):.1f} | {median(b, 0):.2f} | {median(b, 1):.1f} | {ratio:.2f}x |"
        )


if __name__ == "__main__":
    main()

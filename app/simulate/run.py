"""``vantage simulate``: run the virtual users against a server, mode after mode, and report.

vantage simulate --spawn                       # a fresh server and document: the full report
vantage simulate --url http://127.0.0.1:8000 --doc <id> --users 16 --seconds 20
vantage simulate --spawn --zoom-out-share 0.5 --modes diff --lod on --tiles off,on
                                               # half the users look at the whole document
                                               # every so often: per-screen answers vs tiles
"""

from __future__ import annotations

import argparse
import asyncio
import ipaddress
import os
import platform
import shlex
import socket
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path
from urllib.parse import urlparse

import numpy as np
import orjson
from tqdm import tqdm

from spatial import scenes

from ..client import Client
from ..demo import ndjson_lines
from ..launch import launch, stop
from .motion import fit_scale, user_path
from .report import kinds_table, plot, summarise, table
from .users import MIN_PX, Budget, Mode, UserLog, run_user

__all__ = ["bounds_and_anchors", "main", "places", "run_mode", "user_paths", "zooming_out"]

SCREEN = (1280.0, 800.0)
ANCHORS = 5000  # items sampled as "go to" targets
LIMIT = 100_000  # the server's cap: the whole document at Fit, for the places to dive into


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="vantage simulate", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    target = parser.add_argument_group("target")
    target.add_argument("--url", default="http://127.0.0.1:8000", help="the server (default %(default)s)")
    target.add_argument("--doc", help="document id or name (default: the first document)")
    target.add_argument(
        "--spawn",
        action="store_true",
        help="start a server in a subprocess with a generated document, and stop it after",
    )
    target.add_argument(
        "--pages", type=int, default=500, help="pages of the generated document (with --spawn)"
    )
    target.add_argument(
        "--allow-remote",
        action="store_true",
        help="allow a target that is not loopback (only load what you own)",
    )
    load = parser.add_argument_group("load")
    load.add_argument(
        "--users", type=int, default=8, help="virtual users panning at once (default %(default)s)"
    )
    load.add_argument(
        "--seconds", type=float, default=5.0, help="length of each mode's run (default %(default)s)"
    )
    load.add_argument(
        "--max-requests", type=int, default=100_000, help="requests per mode at most, tiles included"
    )
    load.add_argument("--modes", default="poll,diff,stream", help="transports: poll, diff, stream")
    load.add_argument("--overscan", default="0,0.5", help="margins to compare, as a share of the screen")
    load.add_argument("--lod", default="on,off", help="level of detail: on, off or both")
    load.add_argument(
        "--tiles",
        default="off",
        help="tiles: off (per-screen answers, each aggregate with its mask), on (zoomed out, "
        "users ask with tiles=true and fetch the tiles under their screen they do not hold, "
        "keeping them; zoomed in, they ask without), or off,on to compare; on applies to poll "
        "and diff with level of detail (default %(default)s)",
    )
    load.add_argument(
        "--zoom-out-share",
        type=float,
        default=0.0,
        help="share of the users who, every so often, zoom out to see the whole document "
        "(Fit), look for 1-3 s, then dive into another place (default %(default)s)",
    )
    load.add_argument(
        "--zoom-out-every",
        type=float,
        default=10.0,
        help="seconds between such a user's looks at the whole document, about (the first "
        "within that many seconds; default %(default)s)",
    )
    load.add_argument("--seed", type=int, default=0, help="the users' paths (default %(default)s)")
    parser.add_argument("--out", default="simulation", help="folder for result.json and plot.png")
    args = parser.parse_args(argv)
    transports = args.modes.split(",")
    if not set(transports) <= {"poll", "diff", "stream"}:
        parser.error(f"--modes takes poll, diff and stream, got {args.modes!r}")
    try:
        overscans = [float(v) for v in args.overscan.split(",")]
    except ValueError:
        parser.error(f"--overscan takes numbers, got {args.overscan!r}")
    lods = args.lod.split(",")
    if not set(lods) <= {"on", "off"}:
        parser.error(f"--lod takes on and off, got {args.lod!r}")
    tiles = args.tiles.split(",")
    if not set(tiles) <= {"on", "off"}:
        parser.error(f"--tiles takes on and off, got {args.tiles!r}")
    if args.users < 1 or args.seconds <= 0 or args.max_requests < 1 or min(overscans) < 0:
        parser.error("--users, --seconds and --max-requests must be positive, --overscan >= 0")
    if not 0 <= args.zoom_out_share <= 1 or args.zoom_out_every <= 0:
        parser.error("--zoom-out-share must be within 0..1, --zoom-out-every positive")
    args.mode_list = [
        Mode(t, o, lod == "on", tile == "on")
        for t in transports
        for o in overscans
        for lod in lods
        for tile in tiles
        if tile == "off" or (t != "stream" and lod == "on")  # tiles: HTTP answers with LOD
    ]
    if not args.mode_list:
        parser.error("--tiles on needs --modes poll or diff, and --lod on")
    return args


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with ExitStack() as stack:
        if args.spawn:
            url, doc = _spawn(stack, args, out)
        else:
            url = args.url.rstrip("/")
            if not args.allow_remote and not _resolves_to_loopback(url):
                raise SystemExit(f"refusing to load {url}: not a loopback address (--allow-remote to insist)")
            with Client(url) as vantage:
                doc = _pick(vantage, args.doc)
        with Client(url) as vantage:
            bounds, anchors = bounds_and_anchors(vantage, doc)
            looking = zooming_out(args.users, args.zoom_out_share)
            targets = places(vantage, doc, bounds, args.seed) if looking else None
        paths = user_paths(args, bounds, anchors, looking, targets)
        runs: list[tuple[Mode, list[UserLog]]] = []
        for mode in tqdm(args.mode_list, desc="modes", unit="mode", file=sys.stderr):
            logs = asyncio.run(run_mode(mode, url, doc, paths, args.max_requests))
            for k, log in enumerate(logs):
                log.zooms_out = k in looking
            runs.append((mode, logs))
    rows = [summarise(mode, logs, args.seconds) for mode, logs in runs]
    text = table(rows)
    print(text)
    print("\nRequests by kind (bodies on the wire: gzip'd when the server sent them so):\n")
    print(kinds_table(rows))
    result = {
        "command": "vantage simulate " + shlex.join(sys.argv[1:] if argv is None else argv),
        "machine": f"{platform.system()} {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
        "target": url,
        "document": doc,
        "users": args.users,
        "seconds_per_mode": args.seconds,
        "seed": args.seed,
        "zoom_out_share": args.zoom_out_share,
        "zoom_out_every": args.zoom_out_every,
        "server_log": str(out / "server.log") if args.spawn else None,
        "modes": rows,
    }
    (out / "result.json").write_bytes(orjson.dumps(result, option=orjson.OPT_INDENT_2))
    plot(runs, out / "plot.png")
    print(f"\nwrote {out / 'result.json'} and {out / 'plot.png'}", file=sys.stderr)


async def run_mode(
    mode: Mode, url: str, doc: str, paths: list[np.ndarray], max_requests: int
) -> list[UserLog]:
    """A user per path (cameras per frame, from ``user_path``) on ``doc`` at ``url``, all at
    once in real time, fetching as ``mode`` says; at most ``max_requests`` requests in all."""
    budget = Budget(max_requests)
    t0 = time.perf_counter()
    return list(await asyncio.gather(*(run_user(mode, url, doc, path, SCREEN, budget, t0) for path in paths)))


def _resolves_to_loopback(url: str) -> bool:
    host = urlparse(url).hostname or ""
    try:
        return all(ipaddress.ip_address(info[4][0]).is_loopback for info in socket.getaddrinfo(host, None))
    except (socket.gaierror, ValueError):
        return False


def _pick(vantage: Client, wanted: str | None) -> str:
    for d in vantage.documents():
        if wanted in (None, d["id"], d["name"]):
            return d["id"]
    url = vantage.http.base_url
    raise SystemExit(
        f"no document {wanted!r} at {url}" if wanted else f"no documents at {url}: import one first"
    )


def bounds_and_anchors(vantage: Client, doc: str) -> tuple[tuple[float, float, float, float], np.ndarray]:
    """The document's bounds, and item centres to jump to."""
    bounds = vantage.describe(doc)["bounds"]
    if not bounds:
        raise SystemExit(f"document {doc} is empty")
    items = vantage.viewport(doc, bounds, limit=ANCHORS)["items"]
    anchors = np.array([((i["x0"] + i["x1"]) / 2, (i["y0"] + i["y1"]) / 2) for i in items]).reshape(-1, 2)
    return tuple(bounds), anchors


def user_paths(
    args: argparse.Namespace,
    bounds: tuple[float, float, float, float],
    anchors: np.ndarray,
    looking: set[int],
    targets: np.ndarray | None,
) -> list[np.ndarray]:
    """Each of ``args.users``' camera path (``user_path``, seeded from ``args.seed``), those in
    ``looking`` zooming out every ``args.zoom_out_every`` seconds and diving into ``targets``."""
    return [
        user_path(
            args.seed + k,
            bounds,
            anchors,
            args.seconds,
            SCREEN,
            zoom_out_every=args.zoom_out_every if k in looking else None,
            places=targets,
        )
        for k in range(args.users)
    ]


def zooming_out(users: int, share: float) -> set[int]:
    """Which of ``users`` look at the whole document every so often: ``share`` of them, spread.

    >>> sorted(zooming_out(6, 0.5)), sorted(zooming_out(4, 1.0)), zooming_out(4, 0.0)
    ([1, 3, 5], [0, 1, 2, 3], set())
    """
    return {k for k in range(users) if int((k + 1) * share + 1e-9) > int(k * share + 1e-9)}


def places(vantage: Client, doc: str, bounds: tuple[float, float, float, float], seed: int) -> np.ndarray:
    """``ANCHORS`` canvas points to dive into from the whole document, drawn as the items lie:
    the document at Fit, its items and aggregates (an aggregate weighs what it holds)."""
    scale = fit_scale(bounds, SCREEN)
    found = vantage.viewport(doc, bounds, scale=scale, min_px=MIN_PX, limit=LIMIT)["items"]
    if not found:
        raise SystemExit(f"document {doc} shows nothing at Fit")
    centres = np.array([((i["x0"] + i["x1"]) / 2, (i["y0"] + i["y1"]) / 2) for i in found])
    weights = np.array([float(i.get("count", 1)) for i in found])
    picks = np.random.default_rng(seed).choice(len(found), ANCHORS, p=weights / weights.sum())
    return centres[picks]


def _spawn(stack: ExitStack, args: argparse.Namespace, out: Path) -> tuple[str, str]:
    """A `vantage serve` on a free loopback port with a generated document; stopped on exit."""
    data = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="vantage-simulate-")))
    log = stack.enter_context(open(out / "server.log", "w"))  # noqa: SIM115 - closed by the stack
    try:
        server, url = launch(data, "--log-level", "info", output=log)
    except RuntimeError as error:
        raise SystemExit(f"{error}; see {out / 'server.log'}") from None
    stack.callback(stop, server)
    boxes, kinds = scenes.long_document(pages=args.pages, seed=args.seed)
    with Client(url) as vantage:
        doc = vantage.create_document(f"simulated report ({args.pages} pages)")["id"]
        vantage.import_items(doc, b"".join(ndjson_lines(boxes, kinds)))
    print(f"spawned {url} with {len(boxes):,} items (log: {out / 'server.log'})", file=sys.stderr)
    return url, doc

"""Virtual users: each follows its camera path in real time at 60 Hz and fetches what its
screen needs, by full-viewport polling, HTTP diffs or the WebSocket stream, as the page does.
With tiles, an HTTP user does as the page with ``tiles: true`` (``static/vantage-client.js``):
zoomed out, it asks with ``tiles=true`` (no aggregates inline; the answer names the tiles
holding them), and asks anew when the zoom crosses to another ladder level; once an answer has
no band, or the tiles it needs hold no aggregate, it is zoomed in and asks without; once an
answer without shows aggregates, it is zoomed out again and asks that view again with. It
starts zoomed out (its first answer names tiles, even at Fit). Zoomed out, it fetches the tiles
under its screen and margin, of those the last answer named, that it does not hold: when an
answer comes, and as the screen moves onto others between answers. It keeps the last
``HELD_TILES`` it used (a browser's cache would, for the page) and never fetches one it holds."""

from __future__ import annotations

import asyncio
import time
import zlib
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import NamedTuple
from urllib.parse import urlencode, urlsplit

import orjson
from websockets.asyncio.client import connect

from spatial import Rect

from ..tiles import ladder_level, tiles_over
from .coverage import blank_share
from .motion import FPS, screen_rect
from .policy import POLICY, Fetcher, grown

__all__ = ["ANSWERS", "Budget", "Mode", "Sent", "UserLog", "run_user"]

MIN_PX, LIMIT = POLICY["minPx"], int(POLICY["limit"])
HELD_TILES = 4096  # tiles a user keeps (its browser's cache), the least recently used dropped first
TILE_FETCHES = 6  # tiles a user fetches at once: a browser's connections to one host
ANSWERS = ("viewport", "diff", "stream")  # the routes that answer a screen; "tile" is the other


@dataclass(frozen=True)
class Mode:
    transport: str  # "poll" (full viewport), "diff" (HTTP) or "stream" (WebSocket)
    overscan: float  # margin fetched on each side, as a share of the screen
    lod: bool  # send scale and min_px, so sub-pixel items are left out
    tiles: bool = False  # zoomed out, ask with tiles=true and fetch the tiles (HTTP, with lod)

    @property
    def name(self) -> str:
        name = f"{self.transport} overscan={self.overscan:g} lod={'on' if self.lod else 'off'}"
        return name + " tiles=on" if self.tiles else name


class Sent(NamedTuple):
    """One request and its answer."""

    start: float  # seconds into the run it was sent
    latency: float  # seconds until its answer was read
    size: int  # the answer's body, decoded
    wire: int  # the answer's body as it came over the wire (gzip'd, when the server sent it so)
    entered: int  # items and aggregates that entered (0 for a tile)
    left: int  # ids that left
    route: str  # "viewport", "diff", "stream" (ANSWERS) or "tile"
    band: int | None = None  # the band the answer showed; a tile's band
    drawn: float | None = None  # seconds until the answer and the tiles it named were in


@dataclass
class UserLog:
    """What one user saw: every request (``Sent``), every frame's (time, blank share), the
    tiles its screen needed and how many of those it held already, and the errors."""

    requests: list[Sent] = field(default_factory=list)
    frames: list[tuple[float, float]] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    tiles_needed: int = 0  # under the screen and its margin, each time an answer came or they changed
    tiles_held: int = 0  # needed but held already: not fetched again
    tiles_empty: int = 0  # fetched, and holding no aggregate
    zooms_out: bool = False  # a user who looks at the whole document every so often


class Budget:
    """Requests left for the whole run, shared by its users."""

    def __init__(self, total: int) -> None:
        self.left = total

    def take(self) -> bool:
        if self.left <= 0:
            return False
        self.left -= 1
        return True


@dataclass
class _Request:
    rect: Rect
    scale: float
    sent: float  # seconds since the run began


class _User:
    def __init__(self, mode: Mode, doc: str, screen: tuple[float, float], budget: Budget, t0: float) -> None:
        self.mode, self.doc, self.screen, self.budget, self.t0 = mode, doc, screen, budget, t0
        self.log = UserLog()
        self.requested: _Request | None = None  # last asked for
        self.held: _Request | None = None  # last answered: its rect is what the client has
        self.version: int | None = None
        self.seq = 0  # stream messages sent
        self.fetcher = Fetcher(mode.overscan)  # the page's policy, at this mode's margin
        # Tiles: by URL, held (or on their way: None), and whether they hold an aggregate
        self.tiles: OrderedDict[str, bool | None] = OrderedDict()
        self.sheet: tuple[dict, int] | None = None  # the last answer's tiles, and its version
        self.covered: tuple | None = None  # tiles last found all held: no need to look again
        self.needed: list[str] = []  # the tiles under the screen and margin, as last found
        self.on_screen: Rect | None = None  # the latest frame's screen
        self.zoomed_out = mode.tiles  # the view shows aggregates: tiled, ask with tiles=true
        self.aggregates = 0  # held inline, from answers without tiles

    def now(self) -> float:
        return time.perf_counter() - self.t0

    def needs(self, screen: Rect, scale: float) -> bool:
        req = self.requested
        if req is not None and self.sheet is not None and ladder_level(scale) != ladder_level(req.scale):
            return True  # tiled: another ladder level, other tiles
        return self.fetcher.needs(req.rect if req else None, req.scale if req else scale, screen, scale)

    def request(self, screen: Rect, scale: float) -> _Request | None:
        if not self.budget.take():
            return None
        self.requested = _Request(self.fetcher.rect(screen, scale), scale, self.now())
        return self.requested

    def lod(self, req: _Request, prefix: str = "") -> dict:
        return {f"{prefix}scale": req.scale, "min_px": MIN_PX} if self.mode.lod else {}

    def answered(self, req: _Request, body: dict, size: int, route: str, wire: int | None = None) -> int:
        """Log the answer to ``req``; its place in the log."""
        entered = len(body["items"]) if "items" in body else len(body["enter"])
        left = len(body.get("leave", ()))
        latency, band = self.now() - req.sent, body.get("band")
        wire = size if wire is None else wire
        self.log.requests.append(Sent(req.sent, latency, size, wire, entered, left, route, band))
        self.version = body["version"]
        return len(self.log.requests) - 1

    def drawn(self, req: _Request, body: dict, at: int) -> None:
        """The answer to ``req`` (logged ``at``) and the tiles it named are in: the screen shows it."""
        self.log.requests[at] = self.log.requests[at]._replace(drawn=self.now() - req.sent)
        if not body["truncated"]:
            self.held = req

    def count_aggregates(self, body: dict) -> None:
        """Keep count of the aggregates held inline as an answer without tiles changes them."""
        if "items" in body or body["reset"]:
            self.aggregates = 0
        entries = body["items"] if "items" in body else body["enter"]
        self.aggregates += sum(e["id"].startswith("~") for e in entries)
        self.aggregates -= sum(i.startswith("~") for i in body.get("leave", ()))

    def tiles_show_aggregates(self) -> bool:
        """Whether the tiles needed last hold an aggregate (or may: not all are in)."""
        return any(self.tiles.get(url, True) is not False for url in self.needed)

    def missing_tiles(self, screen: Rect, answered: bool = False) -> list[str]:
        """URLs of the tiles under ``screen`` and its margin, of those the last answer named,
        that the user does not hold, taken as held from now on (they are on their way). Unless
        an answer just came (``answered``), nothing when those are the tiles it last found."""
        if self.sheet is None:
            return []
        sheet, version = self.sheet
        band, z = sheet["band"], sheet["z"]
        near = tiles_over(band, z, grown(screen, self.mode.overscan))
        tx0, ty0, tx1, ty1 = sheet["range"]
        span = (max(tx0, near[0]), max(ty0, near[1]), min(tx1, near[2]), min(ty1, near[3]))
        if (band, z, version, span) == self.covered and not answered:
            return []  # the same tiles as last time, all held
        base = f"/documents/{self.doc}/tiles/{band}/{z}"
        missing, self.needed = [], []
        for ty in range(span[1], span[3] + 1):
            for tx in range(span[0], span[2] + 1):
                url = f"{base}/{tx}/{ty}?version={version}"
                self.needed.append(url)
                self.log.tiles_needed += 1
                if url in self.tiles:
                    self.tiles.move_to_end(url)
                    self.log.tiles_held += 1
                    continue
                self.tiles[url] = None
                missing.append(url)
        while len(self.tiles) > HELD_TILES:
            self.tiles.popitem(last=False)
        self.covered = (band, z, version, span)
        return missing


class _Answer(NamedTuple):
    status: int
    body: bytes  # decoded
    wire: int  # the body's bytes as they came


class _Http:
    """A user's keep-alive HTTP/1.1 GETs to one server over at most ``connections`` at once, as
    a browser holds them. Lean on purpose: a load of many small requests (tiles) must measure
    the server, not the client (httpx spends ~1 ms of CPU a request, as much as the server)."""

    def __init__(self, url: str, connections: int, timeout: float = 30.0) -> None:
        parts = urlsplit(url)
        self.host, self.port = parts.hostname or "127.0.0.1", parts.port or 80
        self.timeout = timeout
        self._head = f"Host: {parts.netloc}\r\nAccept-Encoding: gzip\r\n\r\n".encode()
        self._idle: list[tuple[asyncio.StreamReader, asyncio.StreamWriter]] = []
        self._slots = asyncio.Semaphore(connections)

    async def get(self, path: str, params: dict | None = None) -> _Answer:
        """GET ``path`` (with ``params`` as its query).

        :raises OSError, asyncio.IncompleteReadError, TimeoutError: as the connection fails
        """
        target = f"{path}?{urlencode(params)}" if params else path
        request = f"GET {target} HTTP/1.1\r\n".encode() + self._head
        async with self._slots:
            while self._idle:  # a kept connection the server may have closed meanwhile: one try
                conn = self._idle.pop()
                try:
                    return await self._exchange(conn, request)
                except (OSError, asyncio.IncompleteReadError):
                    conn[1].close()
            conn = await asyncio.wait_for(asyncio.open_connection(self.host, self.port), self.timeout)
            try:
                return await self._exchange(conn, request)
            except BaseException:
                conn[1].close()
                raise

    async def _exchange(
        self, conn: tuple[asyncio.StreamReader, asyncio.StreamWriter], request: bytes
    ) -> _Answer:
        reader, writer = conn
        writer.write(request)
        head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), self.timeout)
        lines = head.decode("latin-1").split("\r\n")
        status = int(lines[0].split(" ", 2)[1])
        fields = {k.strip().lower(): v.strip() for k, _, v in (ln.partition(":") for ln in lines[1:] if ln)}
        if "content-length" in fields:
            body = await asyncio.wait_for(reader.readexactly(int(fields["content-length"])), self.timeout)
        elif fields.get("transfer-encoding", "").lower() == "chunked":
            body = await asyncio.wait_for(_chunks(reader), self.timeout)
        else:
            body = await asyncio.wait_for(reader.read(), self.timeout)  # to the close
            fields["connection"] = "close"
        if fields.get("connection", "").lower() == "close":
            writer.close()
        else:
            self._idle.append(conn)
        wire = len(body)
        if fields.get("content-encoding", "").lower() == "gzip":
            body = zlib.decompress(body, 31)
        return _Answer(status, body, wire)

    def close(self) -> None:
        for _, writer in self._idle:
            writer.close()
        self._idle.clear()


async def _chunks(reader: asyncio.StreamReader) -> bytes:
    """A chunked body, whole."""
    parts: list[bytes] = []
    while True:
        size = int((await reader.readuntil(b"\r\n")).split(b";", 1)[0], 16)
        if not size:
            await reader.readuntil(b"\r\n")  # no trailers are sent
            return b"".join(parts)
        parts.append(await reader.readexactly(size))
        await reader.readexactly(2)


async def run_user(
    mode: Mode,
    url: str,
    doc: str,
    path,
    screen: tuple[float, float],
    budget: Budget,
    t0: float,
) -> UserLog:
    """Follow ``path`` (cameras per frame) from ``t0`` on, fetching from the server at ``url``
    as ``mode`` says."""
    user = _User(mode, doc, screen, budget, t0)
    if mode.tiles and (mode.transport == "stream" or not mode.lod):
        raise ValueError(f"{mode.name}: tiles are for HTTP answers (poll, diff) with level of detail")
    if mode.transport == "stream":
        await _stream(user, url.replace("http", "ws", 1) + f"/documents/{doc}/stream", path)
        return user.log
    http = _Http(url, TILE_FETCHES if mode.tiles else 1)
    try:
        await _http(user, http, path)
    finally:
        http.close()
    return user.log


async def _frames(user: _User, path):
    """Each frame's (screen rect, scale) at its time, recording the blank area a person sees."""
    for i, camera in enumerate(path):
        delay = i / FPS - user.now()
        if delay > 0:
            await asyncio.sleep(delay)
        screen = user.on_screen = screen_rect(camera, user.screen)
        user.fetcher.track(user.now(), screen, float(camera[2]))
        user.log.frames.append((user.now(), blank_share(screen, user.held.rect if user.held else None)))
        yield screen, float(camera[2])


async def _http(user: _User, http: _Http, path) -> None:
    in_flight: asyncio.Task | None = None
    async for screen, scale in _frames(user, path):
        if in_flight is not None and not in_flight.done():
            continue  # one request at a time: the next frame asks again if still needed
        if user.needs(screen, scale):
            previous = user.held if user.mode.transport == "diff" else None
            req = user.request(screen, scale)
            if req is not None:
                in_flight = asyncio.create_task(_fetch(user, http, previous, req))
        elif user.mode.tiles and (missing := user.missing_tiles(screen)):
            in_flight = asyncio.create_task(_fetch_tiles(user, http, missing))  # moved onto new tiles
    if in_flight is not None:
        await in_flight


async def _fetch(user: _User, http: _Http, previous: _Request | None, req: _Request) -> None:
    """Ask for ``req`` (a diff from ``previous``, else the viewport) and take in the answer;
    with tiles, the tiles it needs too, or, when it shows aggregates inline, the view again tiled
    (the page does so as it leaves its stream)."""
    body, at = await _ask(user, http, previous, req)
    if body is None:
        return
    if user.mode.tiles and "tiles" not in body:  # asked without: zoomed in, or now out
        user.count_aggregates(body)
        if user.aggregates and user.budget.take():  # now out: the view again, tiled
            user.zoomed_out = True
            user.drawn(req, body, at)
            previous = user.held if user.mode.transport == "diff" else None
            req = user.requested = _Request(req.rect, req.scale, user.now())
            body, at = await _ask(user, http, previous, req)
            if body is None:
                return
    if user.mode.tiles and "tiles" in body:
        user.aggregates = 0  # tiled: they leave for the tiles
        user.sheet = (body["tiles"], body["version"]) if body["tiles"] else None
        assert user.on_screen is not None  # a frame asked
        await _fetch_tiles(user, http, user.missing_tiles(user.on_screen, answered=True))
        if user.sheet is None or not user.tiles_show_aggregates():
            user.zoomed_out, user.sheet = False, None  # zoomed in: no aggregate to draw
    user.drawn(req, body, at)


async def _ask(user: _User, http: _Http, previous: _Request | None, req: _Request) -> tuple[dict | None, int]:
    """The answer to ``req`` and its place in the log; None on an error (logged)."""
    base = f"/documents/{user.doc}"
    if previous is None:
        params = {
            **dict(zip(("x0", "y0", "x1", "y1"), req.rect, strict=True)),
            "limit": LIMIT,
            **user.lod(req),
        }
        url = f"{base}/viewport"
    else:
        params = {
            "from": ",".join(map(repr, previous.rect)),
            "to": ",".join(map(repr, req.rect)),
            "limit": LIMIT,
            "since": user.version,
            **user.lod(req),
            **user.lod(previous, "from_"),
        }
        url = f"{base}/diff"
    if user.zoomed_out:
        params["tiles"] = "true"
    try:
        response = await http.get(url, params)
    except (OSError, asyncio.IncompleteReadError, TimeoutError) as error:
        user.log.errors.append(f"{url}: {error!r}")
        return None, -1
    if response.status != 200:
        user.log.errors.append(f"{url}: {response.status} {response.body[:200]!r}")
        return None, -1
    body = orjson.loads(response.body)
    return body, user.answered(req, body, len(response.body), url.rsplit("/", 1)[1], response.wire)


async def _fetch_tiles(user: _User, http: _Http, urls: list[str]) -> None:
    """Fetch ``urls``, ``TILE_FETCHES`` at a time, as a browser does over its connections."""
    queue = iter(urls)

    async def worker() -> None:
        for url in queue:
            if not user.budget.take():
                user.tiles.pop(url, None)
                return
            start = user.now()
            try:
                response = await http.get(url)
            except (OSError, asyncio.IncompleteReadError, TimeoutError) as error:
                user.tiles.pop(url, None)
                user.log.errors.append(f"{url}: {error!r}")
                continue
            if response.status != 200:
                user.tiles.pop(url, None)
                user.log.errors.append(f"{url}: {response.status} {response.body[:200]!r}")
                continue
            size, wire = len(response.body), response.wire
            empty = b'"index":[]' in response.body
            user.log.tiles_empty += empty
            if url in user.tiles:
                user.tiles[url] = not empty
            band = int(url.split("/tiles/", 1)[1].split("/", 1)[0])
            user.log.requests.append(Sent(start, user.now() - start, size, wire, 0, 0, "tile", band))

    await asyncio.gather(*(worker() for _ in range(min(TILE_FETCHES, len(urls)))))


async def _stream(user: _User, ws_url: str, path) -> None:
    sent: dict[int, _Request] = {}
    async with connect(ws_url, compression=None, max_size=None) as ws:

        async def receive() -> None:
            async for message in ws:
                body = orjson.loads(message)
                if body.get("type") == "error":
                    user.log.errors.append(body["message"])
                elif body.get("type") == "view":
                    req = sent.pop(body["seq"], None)
                    for seq in [s for s in sent if s < body["seq"]]:
                        del sent[seq]  # superseded: the server answered a newer one
                    if req is not None:
                        user.drawn(req, body, user.answered(req, body, len(message), "stream"))

        reader = asyncio.create_task(receive())
        try:
            async for screen, scale in _frames(user, path):
                if user.needs(screen, scale) and (req := user.request(screen, scale)) is not None:
                    user.seq += 1
                    seq = user.seq
                    sent[seq] = req
                    message = {"seq": seq, "viewport": list(req.rect), "limit": LIMIT}
                    if user.mode.lod:
                        message |= {"scale": req.scale, "min_px": MIN_PX}
                    await ws.send(orjson.dumps(message).decode())
            deadline = user.now() + 2.0  # let the last answers arrive
            while sent and user.now() < deadline:
                await asyncio.sleep(0.01)
        finally:
            reader.cancel()

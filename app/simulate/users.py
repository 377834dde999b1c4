"""Virtual users: each follows its camera path in real time at 60 Hz and fetches what its
screen needs, by full-viewport polling, HTTP diffs or the WebSocket stream, as the page does."""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field

import httpx
import orjson
from websockets.asyncio.client import connect

from spatial import Rect

from .coverage import blank_share
from .motion import FPS, screen_rect
from .policy import POLICY, Fetcher

__all__ = ["Budget", "Mode", "UserLog", "run_user"]

MIN_PX, LIMIT = POLICY["minPx"], int(POLICY["limit"])


@dataclass(frozen=True)
class Mode:
    transport: str  # "poll" (full viewport), "diff" (HTTP) or "stream" (WebSocket)
    overscan: float  # margin fetched on each side, as a share of the screen
    lod: bool  # send scale and min_px, so sub-pixel items are left out

    @property
    def name(self) -> str:
        return f"{self.transport} overscan={self.overscan:g} lod={'on' if self.lod else 'off'}"


@dataclass
class UserLog:
    """What one user saw: every request's (start, latency, bytes, entered, left, route), every
    frame's (time, blank share), and the errors."""

    requests: list[tuple[float, float, int, int, int, str]] = field(default_factory=list)
    frames: list[tuple[float, float]] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)


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

    def now(self) -> float:
        return time.perf_counter() - self.t0

    def needs(self, screen: Rect, scale: float) -> bool:
        req = self.requested
        return self.fetcher.needs(req.rect if req else None, req.scale if req else scale, screen, scale)

    def request(self, screen: Rect, scale: float) -> _Request | None:
        if not self.budget.take():
            return None
        self.requested = _Request(self.fetcher.rect(screen, scale), scale, self.now())
        return self.requested

    def lod(self, req: _Request, prefix: str = "") -> dict:
        return {f"{prefix}scale": req.scale, "min_px": MIN_PX} if self.mode.lod else {}

    def answered(self, req: _Request, body: dict, size: int, route: str) -> None:
        entered = len(body["items"]) if "items" in body else len(body["enter"])
        left = len(body.get("leave", ()))
        self.log.requests.append((req.sent, self.now() - req.sent, size, entered, left, route))
        self.version = body["version"]
        if not body["truncated"]:
            self.held = req


async def run_user(
    mode: Mode,
    http: httpx.AsyncClient,
    ws_url: str,
    doc: str,
    path,
    screen: tuple[float, float],
    budget: Budget,
    t0: float,
) -> UserLog:
    """Follow ``path`` (cameras per frame) from ``t0`` on, fetching as ``mode`` says."""
    user = _User(mode, doc, screen, budget, t0)
    if mode.transport == "stream":
        await _stream(user, ws_url, path)
    else:
        await _http(user, http, path)
    return user.log


async def _frames(user: _User, path):
    """Each frame's (screen rect, scale) at its time, recording the blank area a person sees."""
    for i, camera in enumerate(path):
        delay = i / FPS - user.now()
        if delay > 0:
            await asyncio.sleep(delay)
        screen = screen_rect(camera, user.screen)
        user.fetcher.track(user.now(), screen, float(camera[2]))
        user.log.frames.append((user.now(), blank_share(screen, user.held.rect if user.held else None)))
        yield screen, float(camera[2])


async def _http(user: _User, http: httpx.AsyncClient, path) -> None:
    in_flight: asyncio.Task | None = None
    async for screen, scale in _frames(user, path):
        if in_flight is not None and not in_flight.done():
            continue  # one request at a time: the next frame asks again if still needed
        if user.needs(screen, scale):
            previous = user.held if user.mode.transport == "diff" else None
            req = user.request(screen, scale)
            if req is not None:
                in_flight = asyncio.create_task(_fetch(user, http, previous, req))
    if in_flight is not None:
        await in_flight


async def _fetch(user: _User, http: httpx.AsyncClient, previous: _Request | None, req: _Request) -> None:
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
    try:
        response = await http.get(url, params=params)
    except httpx.HTTPError as error:
        user.log.errors.append(f"{url}: {error!r}")
        return
    if response.status_code != 200:
        user.log.errors.append(f"{url}: {response.status_code} {response.text[:200]}")
        return
    user.answered(req, orjson.loads(response.content), len(response.content), url.rsplit("/", 1)[1])


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
                        user.answered(req, body, len(message), "stream")

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

"""The pan stream: a client sends viewports as it pans and gets what entered and left for each;
edits made by others to what it shows are pushed as they land.

Client -> server, one JSON text message per viewport::

    {"seq": 7, "viewport": [x0, y0, x1, y1], "scale": 0.5, "min_px": 1, "limit": 5000}

Server -> client, one JSON text message per answer, all of one shape::

    {"type": "view" | "edit", "seq": 7, "version": 12, "reset": false, "entered": 3,
     "truncated": false, "leave": ["w1", ...], "enter": [{item}, ...]}

A client applies ``leave`` then ``enter`` (an upsert: an edited item comes again); ``reset`` means
drop everything first. A viewport that arrives while an older one still waits replaces it: the
client gets an answer for its latest view (``seq`` says which), never a backlog. A bad message
gets ``{"type": "error", "message": ...}`` and changes nothing.
"""

import asyncio
import logging
import time

import orjson
from fastapi import APIRouter, Depends, HTTPException, WebSocket, WebSocketDisconnect
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..access import check
from ..config import Settings, get_settings
from ..documents import Document, Snapshot
from ..panning import View, change
from .viewport import cap

router = APIRouter(prefix="/documents/{doc}", tags=["viewport"])
log = logging.getLogger("vantage.stream")

NOT_FOUND = 4404  # application close code: the document does not exist
Job = tuple[View, int, dict]  # a view to answer, its item cap, and the message's type and seq


class ViewMessage(BaseModel):
    model_config = ConfigDict(extra="forbid")

    seq: int = 0
    viewport: tuple[float, float, float, float]
    scale: float | None = Field(None, gt=0)
    min_px: float = Field(0.0, ge=0)
    limit: int | None = Field(None, ge=1)


class Session:
    """One client's view: what it was last sent, so the next answer is only the change."""

    def __init__(self, document: Document, settings: Settings) -> None:
        self.document, self.settings = document, settings
        self.view: View | None = None  # as last answered
        self.snapshot: Snapshot | None = None  # that answer's version
        self.complete = False  # False until an answer fits its limit: the next one starts over
        self.limit, self.seq = settings.default_limit, 0
        self.latest: Job | None = None  # the newest viewport not yet answered
        self.errors: list[str] = []
        self.wake = asyncio.Event()
        self.received = self.sent = 0  # messages, for the log line at the end
        self.allowance, self.checked = settings.max_stream_rate, time.monotonic()  # a token bucket
        self.warned = -1.0  # when the client was last told it is over the rate

    def offer(self, text: str | bytes) -> None:
        """Take a client message: the newest viewport replaces any still waiting."""
        self.received += 1
        if not self._within_rate():
            return
        try:
            message = ViewMessage.model_validate_json(text)
            view = View.of(message.viewport, "viewport", message.scale, message.min_px)
        except ValidationError as error:
            self.errors.append("; ".join(f"{'.'.join(map(str, e['loc'])) or 'message'}: {e['msg']}"
                                         for e in error.errors()))  # fmt: skip
        except ValueError as error:
            self.errors.append(str(error))
        else:
            self.latest = (view, cap(message.limit, self.settings), {"type": "view", "seq": message.seq})
        self.wake.set()

    def _within_rate(self) -> bool:
        """Up to ``max_stream_rate`` messages a second (bursts of one second's worth); beyond,
        messages are dropped with an error, one a second at most."""
        now, rate = time.monotonic(), self.settings.max_stream_rate
        self.allowance = min(rate, self.allowance + (now - self.checked) * rate)
        self.checked = now
        if self.allowance >= 1:
            self.allowance -= 1
            return True
        if now - self.warned >= 1:
            self.warned = now
            self.errors.append(f"429: over {rate:g} messages a second (VANTAGE_MAX_STREAM_RATE); "
                               "messages beyond it are dropped")  # fmt: skip
            self.wake.set()
        return False

    def take(self) -> Job | None:
        """What to answer next (on the event loop, where ``offer`` runs): the latest viewport,
        else the current one again if the document changed under it."""
        if self.latest is not None:
            job, self.latest = self.latest, None
            return job
        if self.view is not None and self.document.snapshot is not self.snapshot:
            return self.view, self.limit, {"type": "edit", "seq": self.seq}
        return None

    def answer(self, view: View, limit: int, extra: dict) -> str | None:
        """The message for ``take``'s job; None for edits that did not touch this view."""
        snap = self.document.snapshot
        old, since = (self.view, self.snapshot) if self.complete else (None, None)
        answer = change(snap, view, old=old, since=since, cap=limit, extra=extra)
        self.view, self.snapshot, self.complete = view, snap, not answer.truncated
        self.limit, self.seq = limit, extra["seq"]
        return None if answer.empty and extra["type"] == "edit" else answer.body.decode()


@router.websocket("/stream")
async def stream(websocket: WebSocket, doc: str, settings: Settings = Depends(get_settings)) -> None:
    await websocket.accept()
    try:
        if settings.read_token:
            check(websocket)
        document = websocket.app.state.registry[doc]
    except HTTPException as error:  # 401/403 become close codes 4401/4403
        await websocket.send_text(_error(error.detail))
        await websocket.close(4000 + error.status_code, error.detail[:120])
        return
    except KeyError as error:
        await websocket.send_text(_error(error.args[0]))
        await websocket.close(NOT_FOUND, error.args[0][:120])
        return
    session = Session(document, settings)
    loop = asyncio.get_running_loop()
    unwatch = document.watch(lambda: loop.call_soon_threadsafe(session.wake.set))
    receiver = asyncio.create_task(_receive(websocket, session))
    try:
        while not receiver.done():
            waiting = asyncio.create_task(session.wake.wait())
            await asyncio.wait({waiting, receiver}, return_when=asyncio.FIRST_COMPLETED)
            waiting.cancel()
            session.wake.clear()
            for message in session.errors:
                await websocket.send_text(_error(message))
            session.errors.clear()
            while (job := session.take()) is not None:
                # Large views take milliseconds: compute off the event loop so others go on.
                if (text := await run_in_threadpool(session.answer, *job)) is not None:
                    await websocket.send_text(text)
                    session.sent += 1
    except WebSocketDisconnect:
        pass
    finally:
        unwatch()
        receiver.cancel()
        log.info("stream of %s closed: %d messages received, %d answers sent", doc, session.received, session.sent)


def _error(message: str) -> str:
    return orjson.dumps({"type": "error", "message": message}).decode()


async def _receive(websocket: WebSocket, session: Session) -> None:
    while True:
        message = await websocket.receive()
        if message["type"] == "websocket.disconnect":
            return
        session.offer(message.get("text") or message.get("bytes") or b"")

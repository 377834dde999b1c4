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

With signed access tokens, the token comes in the ``Authorization`` header or ``?token=`` (a
browser cannot set a WebSocket's headers), and a message ``{"token": "..."}`` replaces it
before it expires; one that grants no reading of the document is refused with an error
message, keeping the old. When the stream's token expires with no fresh one, the stream
closes with 4401.

Open it with ``?min_version=N`` to be answered at version N or later: a replica that cannot
reach it within ``VANTAGE_CATCH_UP_MS`` (its store is away) closes the stream with 1013 (try
again); a version never written closes it with 4409.

Close codes: 4404 the document does not exist (or was deleted), 4401/4403 no token (or an
expired one) or a wrong one, 4409 ``min_version`` is newer than the document, 1013 the server holds as many streams
as it may (``VANTAGE_MAX_STREAMS``), cannot reach its store, or holds as many bytes of
answers not yet read as it may (``VANTAGE_STREAM_UNREAD_MB``, shared by every stream); 1008 the client left an
answer unread for ``VANTAGE_STREAM_SEND_TIMEOUT`` seconds.
"""

import asyncio
import logging
import os
import re
import time

import orjson
from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from fastapi.concurrency import run_in_threadpool

from ..access import FULL, Access, Grant
from ..config import Settings
from ..documents import Document
from ..errors import Invalid, ServiceError
from ..registry import Registry
from ..session import Session, Streams

__all__ = ["router"]

router = APIRouter(prefix="/documents/{doc}", tags=["viewport"])
log = logging.getLogger("vantage.stream")

NOT_FOUND = 4404  # application close code: the document does not exist
ITEM_BYTES = 160  # the most an item takes in an answer, about: its JSON, or its id leaving
EXPIRED = 4401  # ...: the stream's token expired, and no fresh one came
TRY_AGAIN_LATER = 1013
POLICY = 1008
_VERSION = re.compile(r"[0-9]{1,18}")  # ASCII digits only: str.isdigit() takes "²" too


class Unread(Exception):
    """The client left an answer unread past the timeout."""


class Crowded(Exception):
    """Other clients' unread answers held the budget past the timeout."""


@router.websocket("/stream")
async def stream(websocket: WebSocket, doc: str) -> None:
    settings: Settings = websocket.app.state.settings
    streams: Streams = websocket.app.state.streams
    await websocket.accept(headers=[(b"x-vantage-worker", str(os.getpid()).encode())])
    if streams.open >= streams.limit:
        message = f"the server holds {streams.limit} streams, the most it may (VANTAGE_MAX_STREAMS): try again later"
        return await _close(websocket, TRY_AGAIN_LATER, message)
    registry: Registry = websocket.app.state.registry
    try:
        min_version = _min_version(websocket)
    except Invalid as error:
        return await _close(websocket, POLICY, error.message)
    try:
        document = await registry.get(doc)
        with registry.pinned(document):  # open while the stream is
            await registry.catch_up_to(document, min_version, settings.catch_up_ms / 1000)
            grant = websocket.scope.get("state", {}).get("grant", FULL)
            await _serve(websocket, document, settings, streams, grant)
    except ServiceError as error:  # 503s (not caught up, the store away) say: try again later
        code = TRY_AGAIN_LATER if error.status == 503 else 4000 + error.status  # 4404, 4409
        return await _close(websocket, code, error.message)


def _min_version(websocket: WebSocket) -> int | None:
    """The ``?min_version=`` the stream was opened with: its first answer is of that version or later."""
    text = websocket.query_params.get("min_version")
    if text is None:
        return None
    if not _VERSION.fullmatch(text):
        raise Invalid(f"min_version={text[:40]!r}: expected a version, a whole number >= 0")
    return int(text)


async def _serve(
    websocket: WebSocket, document: Document, settings: Settings, streams: Streams, grant: Grant
) -> None:
    doc = document.id
    streams.open += 1
    session = Session(document, settings)
    loop = asyncio.get_running_loop()
    unwatch = document.watch(lambda: loop.call_soon_threadsafe(session.wake.set))
    receiver = asyncio.create_task(_receive(websocket, session))

    async def send(text: str) -> None:
        # One answer in flight at a time, and newer viewports supersede waiting ones: a client
        # that stops reading pins one answer, for at most the timeout.
        try:
            await asyncio.wait_for(websocket.send_text(text), settings.stream_send_timeout)
        except TimeoutError:
            raise Unread from None

    try:
        while not receiver.done():
            waiting = asyncio.create_task(session.wake.wait())
            left = None if grant.expires is None else max(0.0, grant.expires - time.time())
            await asyncio.wait({waiting, receiver}, timeout=left, return_when=asyncio.FIRST_COMPLETED)
            waiting.cancel()
            session.wake.clear()
            if document.deleted:
                return await _close(websocket, NOT_FOUND, f"document {doc!r} was deleted")
            if session.renewal is not None:
                grant = _renewed(websocket.app.state.access, grant, session, doc)
            if grant.expired:
                return await _close(websocket, EXPIRED, "the stream's token expired: send a fresh one before")
            for message in session.errors:
                await send(_error(message))
            session.errors.clear()
            while (job := session.take()) is not None:
                # Every stream's answers being built or sent share one budget of bytes
                # (VANTAGE_STREAM_UNREAD_MB): clients that never read hold it, not an answer
                # each. An answer takes what its cap could hold, then what it holds.
                held = min(job.cap * ITEM_BYTES, streams.unread_budget)
                if not await streams.reserve(held, settings.stream_send_timeout):
                    raise Crowded
                try:
                    # Large views take milliseconds: compute off the event loop so others go
                    # on; a pan step's change takes less than the hop to a thread would.
                    text = (
                        session.answer(job)
                        if session.light(job)
                        else await run_in_threadpool(session.answer, job)
                    )
                    if text is not None:
                        streams.release(held - len(text))
                        held = len(text)
                        await send(text)
                        session.sent += 1
                finally:
                    streams.release(held)
    except WebSocketDisconnect:
        pass
    except Crowded:
        message = "answers other clients have not read fill the server's budget (VANTAGE_STREAM_UNREAD_MB): try again later"
        await _close(websocket, TRY_AGAIN_LATER, message)
    except Unread:
        timeout = settings.stream_send_timeout
        await _close(
            websocket,
            POLICY,
            f"an answer went unread for {timeout:g} s (VANTAGE_STREAM_SEND_TIMEOUT)",
            timeout,
        )
    finally:
        streams.open -= 1
        unwatch()
        receiver.cancel()
        log.info(
            "stream of %s closed: %d messages received, %d answers sent", doc, session.received, session.sent
        )


def _renewed(access: Access, grant: Grant, session: Session, doc: str) -> Grant:
    """The grant of the token the client sent, if it reads ``doc``; else the old one, and
    the client is told why."""
    token, session.renewal = session.renewal, None
    if token is None:  # none sent (the caller looks first)
        return grant
    try:
        fresh = access.grant(token.encode())
    except ServiceError as error:
        session.errors.append(f"{error.status}: {error.message}; the stream keeps its token")
        return grant
    if not fresh.reads(doc):
        session.errors.append(
            f"403: the token does not allow reading document {doc!r}; the stream keeps its token"
        )
        return grant
    return fresh


def _error(message: str) -> str:
    return orjson.dumps({"type": "error", "message": message}).decode()


async def _close(websocket: WebSocket, code: int, message: str, patience: float = 1.0) -> None:
    """Say why in an error message, then close; each waits at most ``patience`` seconds for
    a client that is not reading (then the connection is dropped without them)."""
    try:
        await asyncio.wait_for(websocket.send_text(_error(message)), patience)
        await asyncio.wait_for(websocket.close(code, message[:120]), patience)
    except (TimeoutError, WebSocketDisconnect, RuntimeError):  # not reading, or gone already
        pass


async def _receive(websocket: WebSocket, session: Session) -> None:
    while True:
        message = await websocket.receive()
        if message["type"] == "websocket.disconnect":
            return
        session.offer(message.get("text") or message.get("bytes") or b"")

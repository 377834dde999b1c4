"""The pan stream of a document (``WS /documents/{doc}/stream``): :class:`Stream` over
websockets' sync client and :class:`AsyncStream` over its asyncio one, each holding the items
in view as the page does; a refused or closed stream raises :class:`~app.client.VantageError`
with the status its close code stands for.

Open one with a client's ``stream(doc)`` or on its own (``Stream(url, doc, token)``);
websockets, which uvicorn's ``standard`` extra installs, is imported when one opens.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator, Iterator
from typing import Any
from urllib.parse import urlencode

from app.client import Rect, Token, VantageError, _Bearer, _params, _seg

__all__ = [
    "AsyncStream",
    "CLOSES",
    "GRACE",
    "Stream",
]

CLOSES = {1008: 408, 1013: 503}  # close codes that are not 4000 + an HTTP status
GRACE = 0.5  # seconds to wait, after an error message, for the close that may follow it


class _Held:
    """What a stream's client holds: the answers applied as the page does (``reset`` drops
    everything, then ``leave``, then ``enter`` upserts)."""

    def __init__(
        self,
        url: str,
        doc: str,
        token: Token,
        scale: float | None,
        min_px: float,
        limit: int | None,
        min_version: int | None = None,
    ) -> None:
        base = url.rstrip("/")
        base = "ws" + base[4:] if base.startswith("http") else base
        self.tokens = _Bearer(token)
        query = urlencode(_params(token=self.tokens.current(), min_version=min_version))
        self.url = f"{base}/documents/{_seg(doc)}/stream" + (f"?{query}" if query else "")
        self.doc, self.scale, self.min_px, self.limit = doc, scale, min_px, limit
        self.items: dict[str, dict] = {}  # id -> item: what is on screen (aggregates too)
        self.version = 0  # the document version the items reflect
        self.band: int | None = None  # the zoom band of the aggregates held (None: real items only)
        self.truncated = False
        self.seq = 0  # the last viewport sent
        self.answered = 0  # the seq of the last view answered
        self.errors: list[str] = []  # error messages received

    def _messages(
        self, rect: Rect, scale: float | None, min_px: float | None, limit: int | None
    ) -> list[str]:
        """A viewport's message, after the stream's fresh token when the last is about to expire."""
        fresh = self.tokens.renewed()
        renewal = [json.dumps({"token": fresh})] if fresh else []
        return [*renewal, self._message(rect, scale, min_px, limit)]

    def _message(self, rect: Rect, scale: float | None, min_px: float | None, limit: int | None) -> str:
        self.seq += 1
        message: dict[str, Any] = {"seq": self.seq, "viewport": [float(v) for v in rect]}
        scale = self.scale if scale is None else scale
        min_px = self.min_px if min_px is None else min_px
        limit = self.limit if limit is None else limit
        if scale is not None:
            message["scale"] = scale
        if min_px:
            message["min_px"] = min_px
        if limit is not None:
            message["limit"] = limit
        return json.dumps(message)

    def _apply(self, text: str | bytes) -> dict:
        answer = json.loads(text)
        if answer.get("type") == "error":
            self.errors.append(answer.get("message", ""))
            return answer
        if answer.get("reset"):
            self.items.clear()
        for key in answer["leave"]:
            self.items.pop(key, None)
        for item in answer["enter"]:
            self.items[item["id"]] = item
        self.version = answer["version"]
        if answer["type"] == "view":
            self.band, self.truncated = answer.get("band"), answer.get("truncated", False)
            self.answered = max(self.answered, answer["seq"])
        return answer

    def _closed(self, error: Exception) -> VantageError:
        received = getattr(error, "rcvd", None)
        code = received.code if received is not None else 1006
        reason = self.errors[-1] if self.errors else (received.reason if received is not None else "")
        status = code - 4000 if 4000 <= code < 5000 else CLOSES.get(code, 503)
        return VantageError.made(status, reason or f"the stream closed (code {code})", self.url)

    def _refused(self, error: Exception) -> VantageError:
        response = getattr(error, "response", None)
        if response is None:
            return VantageError.made(503, f"cannot open the stream: {error}", self.url)
        body = bytes(response.body or b"").decode(errors="replace")
        try:
            detail = json.loads(body)["detail"]
        except Exception:
            detail = body[:500] or f"the handshake was refused ({response.status_code})"
        return VantageError.made(response.status_code, detail, self.url)


class Stream(_Held):
    """A document's pan stream (``WS /documents/{doc}/stream``, websockets' sync client):
    send viewports, get what entered and left; ``items`` holds what is in view, kept from the
    answers and from the edits others make, which the server pushes.

    ::

        with Stream(url, doc, scale=0.5, min_px=1) as stream:
            stream.view((0, 0, 1920, 1080))   # sends, waits for its answer: stream.items is the view
            stream.send((0, 40, 1920, 1120))  # or send as you pan and read answers as they come:
            for answer in stream:             # each applied to stream.items before it is yielded
                ...

    A viewport sent while an older one still waits replaces it (the server answers the latest,
    ``seq`` says which). A refused or closed stream raises :class:`VantageError` (4404: no such
    document -> status 404; 4401/4403: token -> 401/403). With ``min_version``, its first answer
    is of that version or later (4409 -> 409: never written; 1013 -> 503: try again).
    """

    def __init__(
        self,
        url: str,
        doc: str,
        token: Token = None,
        *,
        scale: float | None = None,
        min_px: float = 0.0,
        limit: int | None = None,
        min_version: int | None = None,
        open_timeout: float = 30.0,
    ) -> None:
        from websockets.exceptions import InvalidHandshake
        from websockets.sync.client import connect

        super().__init__(url, doc, token, scale, min_px, limit, min_version)
        try:
            # entered: the connection itself (websockets >= 17.1 warns when connect() is used bare)
            self.ws = connect(self.url, open_timeout=open_timeout, max_size=None, proxy=None).__enter__()
        except InvalidHandshake as error:
            raise self._refused(error) from None
        except OSError as error:
            raise VantageError.made(503, f"cannot reach {self.url}: {error}", self.url) from None

    def __enter__(self) -> Stream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.ws.close()

    def send(
        self, rect: Rect, *, scale: float | None = None, min_px: float | None = None, limit: int | None = None
    ) -> int:
        """Send a viewport (the stream's ``scale``, ``min_px`` and ``limit`` unless given); its seq."""
        from websockets.exceptions import ConnectionClosed

        try:
            for message in self._messages(rect, scale, min_px, limit):
                self.ws.send(message)
        except ConnectionClosed as error:
            raise self._closed(error) from None
        return self.seq

    def receive(self, timeout: float | None = None) -> dict | None:
        """The next answer (a view, an edit pushed, or an error), applied to ``items``; None
        after ``timeout`` seconds without one.

        :raises VantageError: if the stream closes (with the status of its close code)
        """
        from websockets.exceptions import ConnectionClosed

        try:
            text = self.ws.recv(timeout)
        except TimeoutError:
            return None
        except ConnectionClosed as error:
            raise self._closed(error) from None
        return self._apply(text)

    def view(
        self,
        rect: Rect,
        *,
        scale: float | None = None,
        min_px: float | None = None,
        limit: int | None = None,
        timeout: float = 60.0,
    ) -> dict:
        """Send a viewport and wait for its answer (applying whatever comes before it): the
        answer; ``items`` is then the view.

        :raises VantageError: 422 if the server refused the viewport, or the stream closed
        :raises TimeoutError: no answer within ``timeout`` seconds
        """
        seq = self.send(rect, scale=scale, min_px=min_px, limit=limit)
        deadline = time.monotonic() + timeout
        while True:
            answer = self.receive(max(0.0, deadline - time.monotonic()))
            if answer is None:
                raise TimeoutError(f"no answer to viewport {seq} within {timeout:g} s")
            if answer["type"] == "error":
                self.receive(GRACE)  # a refusal closes the stream next: raises with its status
                raise VantageError.made(422, answer.get("message", ""), self.url)
            if answer["type"] == "view" and answer["seq"] >= seq:
                return answer

    def __iter__(self) -> Iterator[dict]:
        """Answers as they come, applied, until the server closes the stream normally."""
        from websockets.exceptions import ConnectionClosed, ConnectionClosedOK

        while True:
            try:
                text = self.ws.recv()
            except ConnectionClosedOK:
                return
            except ConnectionClosed as error:
                raise self._closed(error) from None
            yield self._apply(text)


class AsyncStream(_Held):
    """:class:`Stream` over websockets' asyncio client: ``async with AsyncStream(...) as s``
    (or ``await s.open()``), then ``await s.view(rect)``, ``s.send``, ``await s.receive()``,
    ``async for answer in s``."""

    def __init__(
        self,
        url: str,
        doc: str,
        token: Token = None,
        *,
        scale: float | None = None,
        min_px: float = 0.0,
        limit: int | None = None,
        min_version: int | None = None,
        open_timeout: float = 30.0,
    ) -> None:
        super().__init__(url, doc, token, scale, min_px, limit, min_version)
        self.open_timeout = open_timeout
        self.ws: Any = None

    async def open(self) -> AsyncStream:
        from websockets.asyncio.client import connect
        from websockets.exceptions import InvalidHandshake

        try:
            self.ws = await connect(self.url, open_timeout=self.open_timeout, max_size=None, proxy=None)
        except InvalidHandshake as error:
            raise self._refused(error) from None
        except OSError as error:
            raise VantageError.made(503, f"cannot reach {self.url}: {error}", self.url) from None
        return self

    async def __aenter__(self) -> AsyncStream:
        return await self.open()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def close(self) -> None:
        if self.ws is not None:
            await self.ws.close()

    async def send(
        self, rect: Rect, *, scale: float | None = None, min_px: float | None = None, limit: int | None = None
    ) -> int:
        """Send a viewport; its seq."""
        from websockets.exceptions import ConnectionClosed

        try:
            for message in self._messages(rect, scale, min_px, limit):
                await self.ws.send(message)
        except ConnectionClosed as error:
            raise self._closed(error) from None
        return self.seq

    async def receive(self, timeout: float | None = None) -> dict | None:
        """The next answer, applied; None after ``timeout`` seconds without one."""
        from websockets.exceptions import ConnectionClosed

        try:
            async with asyncio.timeout(timeout):
                text = await self.ws.recv()
        except TimeoutError:
            return None
        except ConnectionClosed as error:
            raise self._closed(error) from None
        return self._apply(text)

    async def view(
        self,
        rect: Rect,
        *,
        scale: float | None = None,
        min_px: float | None = None,
        limit: int | None = None,
        timeout: float = 60.0,
    ) -> dict:
        """Send a viewport and wait for its answer; see :meth:`Stream.view`."""
        seq = await self.send(rect, scale=scale, min_px=min_px, limit=limit)
        deadline = time.monotonic() + timeout
        while True:
            answer = await self.receive(max(0.0, deadline - time.monotonic()))
            if answer is None:
                raise TimeoutError(f"no answer to viewport {seq} within {timeout:g} s")
            if answer["type"] == "error":
                await self.receive(GRACE)
                raise VantageError.made(422, answer.get("message", ""), self.url)
            if answer["type"] == "view" and answer["seq"] >= seq:
                return answer

    async def __aiter__(self) -> AsyncIterator[dict]:
        """Answers as they come, applied, until the server closes the stream normally."""
        from websockets.exceptions import ConnectionClosed, ConnectionClosedOK

        while True:
            try:
                text = await self.ws.recv()
            except ConnectionClosedOK:
                return
            except ConnectionClosed as error:
                raise self._closed(error) from None
            yield self._apply(text)
